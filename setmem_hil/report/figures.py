"""Figures of the run report (PNG, matplotlib's Agg canvas; no pyplot, no global state).

* :func:`sample_transfer_functions_figure`: the data with the model's uncertainty, drawn as the
  nine sample transfer functions of thesis Table 6-6 (figures 6-9, 6-15, 6-18, 6-23);
* :func:`pole_zero_figure`: their open-loop poles and zeros (figures 6-10, 6-16, 6-19, 6-24);
* :func:`mu_vs_frequency_figure`: mu-bar against frequency per iteration (figure 6-13);
* :func:`mu_peak_figure`: peak mu-bar per iteration labelled with the chosen frequency
  (figure 6-12);
* :func:`improvement_figure`: estimated mu-bar improvement against candidate frequency, one
  panel per iteration (figures 6-14, 6-17, 6-20).

The pure helpers (:data:`TABLE_6_6`, :func:`table_6_6_offsets`, :func:`modal_poles_zeros`)
carry the numerics and are tested on their own.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import IterationRecord
from setmem_hil.model.modal_model import IntervalModel, ModalParameters

__all__ = [
    "TABLE_6_6",
    "table_6_6_offsets",
    "modal_poles_zeros",
    "sample_transfer_functions_figure",
    "pole_zero_figure",
    "mu_vs_frequency_figure",
    "mu_peak_figure",
    "improvement_figure",
    "exact_ratio_figure",
]

# Thesis Table 6-6: offsets x of (a1, a0, b0) for modes 1-3; a parameter's value is
# mid + x (upper - mid). Transcription: the source text lost some cells; blank cells of
# transfer functions 1-6 are read as 1 (the table's values are -1, 0, 1, +-.5 and the lost
# glyphs are lone "1"s), the blank cell of transfer function 9 (the nominal model) as 0.
TABLE_6_6 = np.array(
    [
        # a11  a01   b01   a12   a02   b02   a13   a03   b03
        [-1.0, 1.0, -1.0, -1.0, 1.0, -1.0, -1.0, 1.0, -1.0],
        [1.0, -1.0, 1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0],
        [-1.0, -1.0, 1.0, -1.0, 1.0, 1.0, -1.0, 1.0, -1.0],
        [1.0, -1.0, 1.0, 1.0, -1.0, 1.0, 1.0, 1.0, 1.0],
        [1.0, 1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0, -1.0],
        [0.0, -1.0, -1.0, 0.0, -1.0, 1.0, 0.0, 1.0, -1.0],
        [-0.5, 0.0, 0.0, -0.5, 0.0, 0.0, -0.5, 0.0, 0.0],
        [0.5, 0.0, 0.0, 0.5, 0.0, 0.0, 0.5, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    ]
)


def table_6_6_offsets(n_modes: int) -> np.ndarray:
    """Unit offsets ``(9, n_modes, 4)`` for :meth:`IntervalModel.sample` (order a1, a0, b1, b0).

    Table 6-6 gives (a1, a0, b0) of three modes (b1 = 0 is fixed in the thesis); ``b1`` gets the
    offset 0 (its midpoint). With more than three modes the columns repeat (mode 4 uses mode
    1's), with fewer the first ones are used.
    """
    if n_modes < 1:
        raise ValueError(f"n_modes: expected >= 1, found {n_modes}")
    out = np.zeros((TABLE_6_6.shape[0], n_modes, 4))
    for i in range(n_modes):
        cols = TABLE_6_6[:, 3 * (i % 3): 3 * (i % 3) + 3]
        out[:, i, 0], out[:, i, 1], out[:, i, 3] = cols[:, 0], cols[:, 1], cols[:, 2]
    return out


def modal_poles_zeros(params: ModalParameters) -> tuple[np.ndarray, np.ndarray]:
    """Poles and zeros of ``G(s) = sum_i (b1_i s + b0_i) / (s^2 + a1_i s + a0_i)`` (eq. 2.24).

    Poles are the roots of each mode's denominator; zeros the roots of the numerator of the sum
    over the common denominator, ``sum_i (b1_i s + b0_i) prod_{j != i} (s^2 + a1_j s + a0_j)``.
    """
    v = np.asarray(params.values, dtype=float)
    dens = [np.array([1.0, a1, a0]) for a1, a0 in v[:, :2]]
    poles = np.concatenate([np.roots(d) for d in dens]) if len(dens) else np.zeros(0, complex)
    num = np.zeros(1)
    for i, (_, _, b1, b0) in enumerate(v):
        term = np.array([b1, b0])
        for j, d in enumerate(dens):
            if j != i:
                term = np.polymul(term, d)
        num = np.polyadd(num, term)
    num = np.trim_zeros(np.asarray(num, dtype=float), "f")
    zeros = np.roots(num) if num.size > 1 else np.zeros(0, complex)
    return poles.astype(complex), zeros.astype(complex)


def _save(fig: Figure, path: Path, **adjust: float) -> Path:
    # Fixed margins instead of tight_layout: its text-extent search dominates the run time.
    margins = dict(left=0.1, right=0.97, bottom=0.09, top=0.91, hspace=0.35, wspace=0.3)
    margins.update(adjust)
    fig.subplots_adjust(**margins)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100, format="png")
    return path


def _omega_grid(measurements: Sequence[Measurement]) -> np.ndarray:
    w = [m.omega_rad_s for m in measurements] or [1.0]
    lo = min(0.1, min(w) / 3.0)
    hi = max(100.0, max(w) * 3.0)
    return np.geomspace(lo, hi, 800)


def sample_transfer_functions_figure(model: IntervalModel, measurements: Sequence[Measurement], title: str, path: Path) -> Path:
    """Bode plot of the nine Table 6-6 sample models and the data (error bars: the bounds)."""
    fig = Figure(figsize=(8.0, 6.5))
    ax_mag, ax_ph = fig.subplots(2, 1, sharex=True)
    w = _omega_grid(measurements)
    offsets = table_6_6_offsets(model.n_modes)
    finite = np.all(np.isfinite(model.lower)) and np.all(np.isfinite(model.upper))
    nominal_phase = None
    if finite:
        for n, x in enumerate(offsets):
            g = model.sample(x).frequency_response(w)
            phase = np.degrees(np.unwrap(np.angle(g)))
            style = dict(lw=1.8, color="k") if n == 8 else dict(lw=0.9, alpha=0.8)
            label = "nominal (TF 9)" if n == 8 else (f"TF {n + 1}" if n < 8 else None)
            ax_mag.loglog(w, np.abs(g), label=label, **style)
            ax_ph.semilogx(w, phase, **style)
            if n == 8:
                nominal_phase = phase
    else:
        ax_mag.text(0.5, 0.5, "bounds not finite: no sample transfer functions", transform=ax_mag.transAxes, ha="center")
    if measurements:
        mw = np.array([m.omega_rad_s for m in measurements])
        mg = np.array([m.response for m in measurements])
        mb = np.array([m.bound for m in measurements])
        mag = np.abs(mg)
        open_below = mb >= mag  # |G| - bound <= 0: no lower limit on a log axis
        low = np.where(open_below, 0.0, mb)
        ax_mag.errorbar(mw, mag, yerr=[low, mb], fmt="o", ms=4, color="crimson", ecolor="crimson", capsize=2, label="data +- bound", zorder=5)
        if open_below.any():  # the bar reaches down to zero: an arrow, not a bar to an arbitrary floor
            ax_mag.plot(mw[open_below], mag[open_below] / 3.0, "v", ms=6, color="crimson", mfc="none", zorder=5,
                        label="bound >= |G| (open below)")
        data_phase = np.degrees(np.angle(mg))
        if nominal_phase is not None:  # the 360-degree branch nearest the nominal model's phase
            ref = np.interp(np.log(mw), np.log(w), nominal_phase)
            data_phase = data_phase + 360.0 * np.round((ref - data_phase) / 360.0)
        # phase error bound: asin(R / |G|); undetermined when R >= |G| (any phase is possible)
        known = ~open_below
        dphi = np.degrees(np.arcsin(np.clip(mb[known] / np.maximum(mag[known], 1e-300), 0.0, 1.0)))
        ax_ph.errorbar(mw[known], data_phase[known], yerr=dphi, fmt="o", ms=4, color="crimson", ecolor="crimson", capsize=2, zorder=5)
        if open_below.any():
            ref = np.interp(np.log(mw[open_below]), np.log(w), nominal_phase) if nominal_phase is not None else np.zeros(open_below.sum())
            ax_ph.plot(mw[open_below], ref, "x", ms=7, color="crimson", zorder=5, label="phase undetermined (bound >= |G|)")
            ax_ph.legend(fontsize=7, loc="lower left")
    ax_mag.set_ylabel("|G(j omega)| (receptance)")
    ax_ph.set_ylabel("phase (deg)")
    ax_ph.set_xlabel("frequency (rad/s)")
    ax_mag.set_title(title, fontsize=10)
    ax_mag.grid(True, which="both", alpha=0.3)
    ax_ph.grid(True, which="both", alpha=0.3)
    ax_mag.legend(fontsize=7, ncol=3, loc="lower left")
    return _save(fig, path)


def pole_zero_figure(model: IntervalModel, title: str, path: Path) -> Path:
    """Open-loop poles (x) and zeros (o) of the Table 6-6 sample models."""
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.subplots()
    if np.all(np.isfinite(model.lower)) and np.all(np.isfinite(model.upper)):
        for n, x in enumerate(table_6_6_offsets(model.n_modes)):
            poles, zeros = modal_poles_zeros(model.sample(x))
            color = "k" if n == 8 else f"C{n}"
            ax.plot(poles.real, poles.imag, "x", color=color, ms=7, label=f"TF {n + 1}")
            ax.plot(zeros.real, zeros.imag, "o", mfc="none", color=color, ms=6)
    ax.axvline(0.0, color="0.5", lw=0.8)
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("real (rad/s)")
    ax.set_ylabel("imaginary (rad/s)")
    ax.set_title(title + "\n(x poles, o zeros)", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, ncol=3)
    return _save(fig, path)


def mu_vs_frequency_figure(iterations: Sequence[IterationRecord], mu_target: float, path: Path) -> Path:
    """mu-bar (upper bound) against frequency, one curve per iteration (figure 6-13)."""
    fig = Figure(figsize=(8.0, 5.0))
    ax = fig.subplots()
    n = max(len(iterations), 1)
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    styles = ("-", "--", "-.", ":")
    for i, rec in enumerate(iterations):
        mu = np.where(np.isfinite(rec.mu), rec.mu, np.nan)
        color = cmap(0.9 * i / max(n - 1, 1))  # sequential: dark = early, yellow = late
        ax.semilogx(rec.omega, mu, color=color, ls=styles[i % len(styles)], lw=1.4,
                    label=f"k = {rec.k}" if n <= 12 or i in (0, n - 1) else None)
    ax.axhline(mu_target, color="k", ls="--", lw=1, label=f"goal {mu_target:g}")
    ax.set_xlabel("frequency (rad/s)")
    ax.set_ylabel("mu-bar (robust performance, upper bound)")
    ax.set_title("mu-bar against frequency per iteration (figure 6-13)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    return _save(fig, path)


def mu_peak_figure(iterations: Sequence[IterationRecord], mu_target: float, path: Path) -> Path:
    """Peak mu-bar per iteration, each point labelled with the next frequency (figure 6-12)."""
    fig = Figure(figsize=(8.0, 5.0))
    ax = fig.subplots()
    k = np.array([rec.k for rec in iterations], dtype=float)
    peak = np.array([rec.mu_peak if math.isfinite(rec.mu_peak) else np.nan for rec in iterations])
    ax.plot(k, peak, "o-", color="C0")
    for rec, y in zip(iterations, peak):
        if rec.next_omega is not None and math.isfinite(y):
            ax.annotate(f"{rec.next_omega:.4g}", (rec.k, y), textcoords="offset points", xytext=(0, -14), ha="center", fontsize=8)
    ax.axhline(mu_target, color="k", ls="--", lw=1, label=f"goal {mu_target:g}")
    _per_iteration_axes(ax, "peak mu-bar", "peak mu-bar per iteration; labels: next frequency (rad/s) (figure 6-12)")
    return _save(fig, path)


def _per_iteration_axes(ax, ylabel: str, title: str) -> None:
    """Labels, whole-number iteration ticks, grid and legend of a plot against the iteration k."""
    ax.set_xlabel("iteration k")
    ax.set_ylabel(ylabel)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)


def improvement_figure(iterations: Sequence[IterationRecord], path: Path, exact: dict | None = None) -> Path:
    """Estimated mu-bar improvement per candidate frequency, a panel per iteration (figure 6-14).

    ``exact`` (``k -> (omega, improvement)``) adds the candidates re-identified exactly: the choice
    is the highest of those, which need not be the highest point of the estimate."""
    exact = exact or {}
    recs = [r for r in iterations if np.size(r.candidate_omega)]
    n = max(len(recs), 1)
    ncols = 1 if n == 1 else 2
    nrows = math.ceil(n / ncols)
    fig = Figure(figsize=(8.0 if ncols == 2 else 7.0, 2.8 * nrows + 0.8))
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    for ax, rec in zip(axes, recs):
        order = np.argsort(rec.candidate_omega)
        ax.semilogx(rec.candidate_omega[order], rec.estimated_improvement[order], ".-", ms=2, lw=0.8, label="estimate (eq. 5.3)")
        if rec.k in exact:
            w_ex, v_ex = exact[rec.k]
            ok = np.isfinite(v_ex)
            ax.plot(w_ex[ok], v_ex[ok], "o", mfc="none", color="C1", ms=6, label="exact re-solve")
            if rec.next_omega is not None and ok.any():
                best = int(np.argmax(np.where(ok, v_ex, -np.inf)))
                ax.plot(w_ex[best], v_ex[best], "*", color="crimson", ms=11, label="chosen (highest exact)")
        if rec.next_omega is not None:
            ax.axvline(rec.next_omega, color="crimson", lw=0.8, ls="--")
        chosen = "" if rec.next_omega is None else f", chosen {rec.next_omega:.4g} rad/s"
        ax.set_title(f"iteration {rec.k}{chosen}", fontsize=9)
        ax.set_xlabel("candidate frequency (rad/s)", fontsize=8)
        ax.set_ylabel("improvement", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        if rec is recs[0]:
            ax.legend(fontsize=7, loc="upper left")
    if not recs:
        axes[0].text(0.5, 0.5, "no candidates scored (strategy without scores, or no iteration chose an input)", ha="center", transform=axes[0].transAxes, fontsize=9)
    for ax in axes[len(recs):] if recs else axes[1:]:
        ax.set_visible(False)
    fig.suptitle("estimated mu-bar improvement per candidate frequency (figure 6-14)", fontsize=10)
    height = fig.get_figheight()
    return _save(fig, path, hspace=0.75, top=1.0 - 0.75 / height, bottom=0.55 / height)


def interval_figure(iterations: Sequence[IterationRecord], path: Path) -> Path:
    """Parameter intervals per iteration: natural frequency, damping ratio and residue per mode.

    ``omega_n = sqrt(a0)`` (rad/s) and ``zeta = a1 / (2 omega_n)`` are drawn as the ranges the
    ``a0`` and ``a1`` intervals allow (eq. 2.25); ``b0`` in the data's units times (rad/s)^2.
    """
    fig = Figure(figsize=(9.0, 2.4 * max(iterations[0].lower.shape[0], 1) + 0.8 if iterations else 3.0))
    if not iterations:
        return _save(fig, path)
    n_modes = iterations[0].lower.shape[0]
    axes = np.atleast_2d(fig.subplots(n_modes, 3, squeeze=False))
    k = np.array([rec.k for rec in iterations], dtype=float)
    for i in range(n_modes):
        lo = np.array([rec.lower[i] for rec in iterations])
        hi = np.array([rec.upper[i] for rec in iterations])
        with np.errstate(divide="ignore", invalid="ignore"):
            wn_lo, wn_hi = np.sqrt(np.maximum(lo[:, 1], 0.0)), np.sqrt(np.maximum(hi[:, 1], 0.0))
            z_lo = lo[:, 0] / (2.0 * np.maximum(wn_hi, 1e-300))
            z_hi = hi[:, 0] / (2.0 * np.maximum(wn_lo, 1e-300))
        for ax, (a, b), label in zip(axes[i], ((wn_lo, wn_hi), (z_lo, z_hi), (lo[:, 3], hi[:, 3])),
                                     (f"mode {i + 1}: omega_n (rad/s)", f"mode {i + 1}: zeta", f"mode {i + 1}: b0")):
            finite = np.isfinite(a) & np.isfinite(b)
            ax.vlines(k[finite], a[finite], b[finite], color="C0", lw=5, alpha=0.7)
            ax.set_ylabel(label, fontsize=8)
            ax.grid(True, alpha=0.3)
            ax.tick_params(labelsize=7)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # iterations are whole numbers (issue 40)
            if i == n_modes - 1:
                ax.set_xlabel("iteration k", fontsize=8)
    fig.suptitle("parameter intervals per iteration (guaranteed bounds)", fontsize=10)
    return _save(fig, path, wspace=0.45, hspace=0.45, left=0.09, top=0.93)


EXACT_RATIO_GOAL = 1.1
"""Issue 62's target: every interval within 1.1x of the exact feasible set's extent."""


def exact_ratio_figure(per_iteration: dict[int, Sequence[float | None]], path: Path) -> Path:
    """Each mode's widest interval over the witnesses' reach, per iteration (issue 62 item 6).

    ``per_iteration`` maps ``k`` to one ratio per mode (None: nothing free to compare). The reach
    is spanned by parameter points checked to fit every point (an inner bound of the exact set),
    so each ratio is an upper bound of the box's width over the exact set's.
    """
    fig = Figure(figsize=(8.0, 4.5))
    ax = fig.subplots()
    ks = sorted(per_iteration)
    n_modes = max(len(per_iteration[k]) for k in ks)
    for i in range(n_modes):
        y = np.array([np.nan if i >= len(per_iteration[k]) or per_iteration[k][i] is None else per_iteration[k][i] for k in ks], dtype=float)
        if np.isfinite(y).any():
            ax.plot(ks, y, "o-", color=f"C{i % 10}", label=f"mode {i + 1}")
    ax.axhline(1.0, color="k", lw=1, label="the data's limit (1)")
    ax.axhline(EXACT_RATIO_GOAL, color="k", ls="--", lw=1, label=f"goal {EXACT_RATIO_GOAL:g}")
    _per_iteration_axes(ax, "widest interval / witnesses' reach", "how far each mode's box sits above the exact feasible set (upper bound)")
    return _save(fig, path)
