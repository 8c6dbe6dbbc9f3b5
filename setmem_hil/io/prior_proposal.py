"""PRIOR.toml proposed from modal estimates (``setmem-hil prior``), with every assumption named.

The brackets (choices where a lab has no other information; each is written as a comment in
the file):

* natural frequency: the estimate +-``WIDTH`` (5 %), narrowed to half the gap to a neighbour so
  the bands never overlap;
* damping: ``zeta_max = max(0.01, 10 zeta_estimate)``, at most 0.5;
* residue: ``b0`` within +-100 % of its least-squares estimate (the sign is kept), ``b1 = 0``
  (receptance of a displacement sensor); with complex residues (``prior --residues complex``, or
  ``auto`` when the real-residue estimate misses the data), ``b1`` within
  ``estimate +-(|estimate| + B1_SPREAD |b0| / omega_n)``: the residue's phase may move by about
  ``atan(B1_SPREAD)`` (14 deg) beyond the estimate's;
* the low pseudo-mode (what lies below the band): natural frequency in ``[0.01, 0.8]`` times the
  band's lowest frequency, ``zeta_max = 0.1``, ``b0`` within ``[0.1, 10]`` times its estimate.

Identification is guaranteed *relative to the prior*: if a bracket excludes the truth, the
intervals are those of the prior's world, not of the structure. Widen a bracket when in doubt.
"""

from __future__ import annotations

import math

import numpy as np


__all__ = ["format_prior_proposal", "WIDTH", "suspicious_modes", "misfit_advice"]

WIDTH = 0.05
B1_SPREAD = 0.25
"""Half-width of a complex residue's ``b1`` bracket beyond the estimate, as a fraction of
``|b0| / omega_n`` (module doc). Our judgement: enough on the public beam data, where the
estimate's phase is off by a few degrees between lines."""


def _num(x: float) -> str:
    return repr(float(f"{x:.8g}"))


def _bands(estimate) -> list[tuple[float, float]]:
    lo_band = estimate.band_rad_s[0]
    wn = [m.omega_n_rad_s for m in estimate.modes]
    out = []
    for i, m in enumerate(estimate.modes):
        if m.low_pseudo_mode:
            out.append((0.01 * lo_band, 0.8 * lo_band))
            continue
        lo, hi = wn[i] * (1 - WIDTH), wn[i] * (1 + WIDTH)
        if i > 0 and not estimate.modes[i - 1].low_pseudo_mode:
            lo = max(lo, math.sqrt(wn[i - 1] * wn[i]) * (1 + 1e-6))
        if i + 1 < len(wn):
            hi = min(hi, math.sqrt(wn[i] * wn[i + 1]) * (1 - 1e-6))
        repeated = i > 0 and not estimate.modes[i - 1].low_pseudo_mode and wn[i] <= wn[i - 1] * (1 + 1e-6)
        if repeated or not lo < hi:  # one pole in two brackets, or omega_min > omega_max (issue 62)
            raise ValueError(f"modes {i} and {i + 1} (counted from 1) were proposed at the same frequency, "
                             f"{wn[i] / (2 * math.pi):.6g} Hz: try one mode fewer, or write that bracket by hand")
        out.append((lo, hi))
    return out


SUSPICIOUS_ZETA = 0.1
"""A proposed damping above this, or above ``SUSPICIOUS_ZETA_RATIO`` times the median of the
other modes, is flagged (issue 25: a spurious mode at 946 Hz with zeta 0.18 was written silently).
Our judgement for lightly damped structures, where real modes sit at 1e-4 to 1e-2."""
SUSPICIOUS_ZETA_RATIO = 10.0


def suspicious_modes(estimate) -> list[tuple[int, str]]:
    """``(index, reason)`` of proposed modes whose damping is implausible for this structure:
    likely a computational mode of the fit, not a feature of the data (the low pseudo-mode,
    which stands for everything below the band, is never flagged)."""
    real = [(i, m) for i, m in enumerate(estimate.modes) if not m.low_pseudo_mode]
    flagged = []
    for i, m in real:
        others = [o.zeta for j, o in real if j != i]
        typical = float(np.median(others)) if others else math.nan
        if m.zeta > SUSPICIOUS_ZETA:
            flagged.append((i, f"damping {m.zeta:.3g} > {SUSPICIOUS_ZETA:g}"))
        elif others and m.zeta > SUSPICIOUS_ZETA_RATIO * typical:
            flagged.append((i, f"damping {m.zeta:.3g} is {m.zeta / typical:.0f} x the other modes' median {typical:.2g}"))
    return flagged


def misfit_advice(estimate, complex_residues: bool = False) -> str | None:
    """What to say when the proposal's own least-squares estimate misses some point by more than
    its bound (worst normalised residual > 1): identify will then most likely find no parameters.
    With complex residues the prior gives identify room the estimate did not use (its poles are
    fixed), so the warning is softer."""
    worst = estimate.max_normalized_residual
    if not worst > 1.0:
        return None
    what_to_try = ("try another --modes (a missing or spurious mode), --band around the modes of interest, "
                   "--residuals both, or check the bounds (--bound-rel/--bound-abs)")
    if complex_residues:
        return (f"the proposal's own estimate (poles fixed) misses the data by up to {worst:.3g} x the bound; the complex "
                f"residues' brackets may still hold the data, but if `setmem-hil identify` exits 3: {what_to_try}")
    return (f"the proposal's own estimate misses the data by up to {worst:.3g} x the bound, so `setmem-hil identify` "
            f"with this prior will most likely exit 3: {what_to_try}")


def _residue_brackets(m) -> tuple[float, float]:
    """``b0`` bracket of one estimated mode (module doc)."""
    if m.low_pseudo_mode:
        return tuple(sorted((0.1 * m.b0, 10.0 * m.b0)))
    return tuple(sorted((m.b0 - abs(m.b0), m.b0 + abs(m.b0))))


def _b1_lines(i: int, m, outputs, complex_residues: bool) -> list[str]:
    """``b1 = 0.0``, or the ``b1_min``/``b1_max`` brackets of mode ``i`` (one output)."""
    if not complex_residues or m.low_pseudo_mode:
        return ["b1 = 0.0"]
    lo, hi = _b1_bracket(m)
    return [f"b1_min = {_num(lo)}", f"b1_max = {_num(hi)}"]


def _b1_array_lines(brackets: list[tuple[float, float]]) -> list[str]:
    """Several outputs' ``b1`` brackets of one mode: ``b1 = 0.0`` when every one is fixed at 0."""
    if all(b == (0.0, 0.0) for b in brackets):
        return ["b1 = 0.0"]
    return ["b1_min = [" + ", ".join(_num(b[0]) for b in brackets) + "]",
            "b1_max = [" + ", ".join(_num(b[1]) for b in brackets) + "]"]


def _b1_bracket(m) -> tuple[float, float]:
    """``b1`` bracket of one complex-residue estimate (module doc)."""
    half = abs(m.b1) + B1_SPREAD * abs(m.b0) / m.omega_n_rad_s
    return m.b1 - half, m.b1 + half


def output_brackets(estimate, complex_residues: bool) -> list[dict[str, tuple[float, float]]]:
    """Per mode, the ``b0`` and ``b1`` brackets a proposal writes for one output's estimate
    (``b1`` fixed at 0 for real residues and for the low pseudo-mode)."""
    return [{"b0": _residue_brackets(m), "b1": _b1_bracket(m) if complex_residues and not m.low_pseudo_mode else (0.0, 0.0)}
            for m in estimate.modes]


def no_wider_than_alone(joint_estimate, joint: list[dict], alone_estimate, alone: list[dict]) -> list[dict]:
    """One output's brackets in a joint proposal, each no wider than the same output's own
    single-output proposal (issue 40: a second sensor must never make the first one's answer
    worse): where the output's own proposal has a mode at the same frequency (within the joint
    mode's +-5 % band) and a narrower bracket for a parameter, that bracket is taken whole."""
    bands = _bands(joint_estimate)
    out = []
    for i, (m, brackets) in enumerate(zip(joint_estimate.modes, joint)):
        lo, hi = bands[i]
        match = [k for k, a in enumerate(alone_estimate.modes)
                 if a.low_pseudo_mode == m.low_pseudo_mode and (m.low_pseudo_mode or lo <= a.omega_n_rad_s <= hi)]
        if not match:
            out.append(dict(brackets))
            continue
        own = alone[match[0]]
        out.append({key: own[key] if own[key][1] - own[key][0] < bracket[1] - bracket[0] else bracket
                    for key, bracket in brackets.items()})
    return out


def format_prior_proposal(estimate, source: str, residuals: tuple[str, ...] = (), outputs=None,
                          complex_reason: str | None = None, brackets: list[list[dict]] | None = None) -> str:
    """The PRIOR.toml text for ``estimate`` (a :class:`setmem_hil.estimation.modal_estimate.ModalEstimate`).

    ``outputs`` (issue 25): ``[(name, estimate), ...]`` of several outputs with common poles (the
    same ``estimate.modes`` frequencies and damping in each); the file then has
    ``outputs = [...]`` and ``b0_min``/``b0_max`` arrays, one entry per output.

    ``complex_reason``: the estimates have complex residues (``b1`` brackets are written), and
    why they were chosen (a line in the header).

    ``brackets`` (several outputs): per output, per mode, the ``b0``/``b1`` brackets to write
    (:func:`no_wider_than_alone`) instead of the ones of each output's joint estimate.
    """
    if outputs:  # the poles are common: the outputs differ in residues, and the header names the worst fit
        estimate = max((e for _, e in outputs), key=lambda e: e.max_normalized_residual)
    lo_hz, hi_hz = (w / (2 * math.pi) for w in estimate.band_rad_s)
    lines = [
        f"# Prior proposed by `setmem-hil prior` from {source}, band {lo_hz:.6g}-{hi_hz:.6g} Hz.",
        "# ASSUMPTIONS (edit them if you know better): natural frequency = estimate +-5 % (no overlaps);",
        "# zeta_max = max(0.01, 10 x estimate); b0 = estimate +-100 %; "
        + ("b1 = 0 (receptance)." if complex_reason is None else f"b1 = estimate +-(|estimate| + {B1_SPREAD:g} |b0| / omega_n)."),
        "# Identification is guaranteed RELATIVE TO THIS PRIOR: a bracket that excludes the truth",
        f"# gives intervals of the prior's world. Worst normalised residual of the estimate: {estimate.max_normalized_residual:.3g}.",
        "",
    ]
    if complex_reason is not None:
        lines[-1:-1] = [f"# COMPLEX RESIDUES (b1 free): {complex_reason}."]
    advice = misfit_advice(estimate, complex_reason is not None)
    if advice:
        lines[-1:-1] = [f"# WARNING: {advice}."]
    if outputs:
        lines[-1:-1] = ["# Several outputs: common poles (LSCF over all of them), residue brackets per output in this order"
                        + ("; none wider than that output's own single-output proposal:" if brackets is not None else ":"),
                        "outputs = [" + ", ".join(f'"{name}"' for name, _ in outputs) + "]"]
    flags = dict(suspicious_modes(estimate))
    for i, (m, (lo, hi)) in enumerate(zip(estimate.modes, _bands(estimate))):
        lines.append("[[mode]]")
        if i in flags:
            lines.append(f"# CHECK THIS MODE: {flags[i]}; likely a computational mode of the fit, not the structure's")
        b0_text = f"{m.b0:.4g}" if not outputs else "[" + ", ".join(f"{e.modes[i].b0:.4g}" for _, e in outputs) + "]"
        if m.low_pseudo_mode:
            lines.append("# low pseudo-mode: stands for what lies below the band (rigid-body mass line, lower modes);")
            lines.append("# ASSUMED: omega_n in [0.01, 0.8] x the band's lowest frequency, zeta_max 0.1, b0 in [0.1, 10] x estimate")
            zeta_max = 0.1
        else:
            b1_text = "" if complex_reason is None else ", b1 " + (f"{m.b1:.4g}" if not outputs else "[" + ", ".join(f"{e.modes[i].b1:.4g}" for _, e in outputs) + "]")
            lines.append(f"# estimate: {m.omega_n_rad_s / (2 * math.pi):.6g} Hz = {m.omega_n_rad_s:.6g} rad/s, zeta {m.zeta:.3g}, b0 {b0_text}{b1_text}")
            zeta_max = min(0.5, max(0.01, 10.0 * m.zeta))
        if outputs:
            per_output = ([b[i] for b in brackets] if brackets is not None else
                          [output_brackets(e, complex_reason is not None)[i] for _, e in outputs])
            b_min = "[" + ", ".join(_num(b["b0"][0]) for b in per_output) + "]"
            b_max = "[" + ", ".join(_num(b["b0"][1]) for b in per_output) + "]"
            b1_lines = _b1_array_lines([b["b1"] for b in per_output])
        else:
            b_lo, b_hi = _residue_brackets(m)
            b_min, b_max = _num(b_lo), _num(b_hi)
            b1_lines = _b1_lines(i, m, outputs, complex_reason is not None)
        lines += [f"omega_min = {_num(lo)}", f"omega_max = {_num(hi)}", f"zeta_max = {_num(zeta_max)}",
                  *b1_lines, f"b0_min = {b_min}", f"b0_max = {b_max}", ""]
    if residuals:
        lines += ["[residuals]", "# residual terms for modes outside the band (lower: mass line r/s^2, upper: flexibility r)",
                  "# ASSUMED: each within +-100 % of its least-squares estimate (+- the same for a zero estimate)",
                  f"lower = {'true' if 'lower' in residuals else 'false'}", f"upper = {'true' if 'upper' in residuals else 'false'}"]
        for name in residuals:
            r = (estimate.residuals or {}).get(name)
            if r is not None and r != 0.0:
                lo, hi = sorted((r - abs(r), r + abs(r)))
                lines += [f"{name}_min = {_num(lo)}", f"{name}_max = {_num(hi)}"]
        lines.append("")
    return "\n".join(lines)
