"""Figure of the discrepancy workflow: data, old model, new model and the disagreement bands.

Three panels on a log frequency axis: magnitude and phase of the data (with the bound as a
shaded tube on the magnitude), the old model (best point of the given or identified model) and
the new model (the chosen effect's fit); then the normalised residual ``|g - G| / R`` before
and after, with the level 1 (eq. 3.8) marked. Disagreement bands are shaded in every panel.
Headless (matplotlib's Agg backend).
"""

from __future__ import annotations

import os

import numpy as np

from setmem_hil.discrepancy.workflow import DiscrepancyReport


def plot_discrepancy(report: DiscrepancyReport, path: str | os.PathLike, title: str | None = None) -> None:
    """Write the figure of ``report`` to ``path`` (format from the extension, e.g. ``.png``).

    Parameters
    ----------
    report : DiscrepancyReport
        From :func:`setmem_hil.discrepancy.workflow.check_discrepancy`.
    path : path-like
        Output file.
    title : str, optional
        Figure title (default: the decision).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    data = report.data
    order = np.argsort(data.omega_rad_s)
    w = data.omega_rad_s[order]
    g = data.response[order]
    R = data.bound[order]
    dense = np.geomspace(w.min(), w.max(), 2000)
    dense = np.unique(np.concatenate([dense, w]))
    fig = Figure(figsize=(8.0, 9.0), constrained_layout=True)
    ax_mag, ax_ph, ax_res = fig.subplots(3, 1, sharex=True)
    for ax in (ax_mag, ax_ph, ax_res):
        for lo, hi in report.disagreement_bands:
            a, b = (lo / 1.02, hi * 1.02)
            ax.axvspan(a, b, color="tab:red", alpha=0.15, lw=0)
        ax.set_xscale("log")
        ax.grid(True, which="both", alpha=0.3)
    # the bound belongs to each measured point: error bars, never a band interpolated between them
    mag = np.abs(g)
    ax_mag.errorbar(w, mag, yerr=[np.where(R >= mag, 0.0, R), R], fmt="k.", ms=4, ecolor="0.55", capsize=2, label="data +- bound")
    old = report.old_fit.response(dense)
    ax_mag.loglog(dense, np.abs(old), "tab:blue", lw=1.2, label="old model")
    old_phase = np.unwrap(np.angle(old))
    # data phase placed on the old model's branch (unwrapping sparse, noisy points is unreliable)
    data_phase = np.interp(w, dense, old_phase) + np.angle(g / report.old_fit.response(w))
    ax_ph.semilogx(w, np.degrees(data_phase), "k.", ms=4)
    ax_ph.semilogx(dense, np.degrees(old_phase), "tab:blue", lw=1.2)
    if report.new_fit is not None:
        new = report.new_fit.response(dense)
        ax_mag.loglog(dense, np.abs(new), "tab:green", lw=1.2, ls="--", label=f"new model ({report.decision})")
        ax_ph.semilogx(dense, np.degrees(np.unwrap(np.angle(new))), "tab:green", lw=1.2, ls="--")
    ax_res.semilogy(w, np.maximum(report.old_fit.normalized_residual[order], 1e-4), "o-", color="tab:blue", ms=3, lw=0.8,
                    label=f"before (max {report.before['max_normalized_residual']:.3g})")
    if report.new_fit is not None:
        ax_res.semilogy(w, np.maximum(report.new_fit.normalized_residual[order], 1e-4), "s-", color="tab:green", ms=3, lw=0.8,
                        label=f"after (max {report.after['max_normalized_residual']:.3g})")
    ax_res.axhline(1.0, color="tab:red", lw=1.0, ls=":", label="bound (eq. 3.8)")
    ax_mag.set_ylabel("|G(j omega)|")
    ax_ph.set_ylabel("phase (deg)")
    ax_res.set_ylabel("|g - G| / R")
    ax_res.set_xlabel("omega (rad/s)")
    ax_mag.legend(loc="best", fontsize=8)
    ax_res.legend(loc="best", fontsize=8)
    names = ", ".join(e["name"] for e in report.effects) or "none"
    fig.suptitle(title or f"discrepancy: {names}")
    fig.savefig(path, dpi=110)
