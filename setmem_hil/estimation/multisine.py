"""Multisine excitation: several sinusoids in one record, phased for a low crest factor.

A multisine dwell measures several frequency-response points in one record and pays the
settling once (Pintelon and Schoukens, *System Identification: a Frequency Domain Approach*,
ch. 2 and 5; ISO 7626-2 allows any broadband excitation whose lines are resolved). The force is

    f(t) = sum_k a_k sin(omega_k t + phi_k),

and the safety limit applies to its *peak*, not to each line: :func:`design_multisine` picks
the phases for a low peak and then scales the (equal) amplitudes so that a guaranteed upper
bound of ``|f|`` over the whole record (:meth:`Multisine.peak_bound`) equals the allowed
peak.

Choices where the literature leaves room (documented, not from the thesis, which uses single
sines only):

* equal amplitudes: each line gets the same share of the force budget. The response's SNR then
  follows the structure (high near modes), like the single-sine loop's. On a sensor of few bits
  (an 8-bit oscilloscope) the lines are shaped instead, ``|G|^(-1/2)`` of the model's expected
  response (:func:`line_weights`), and split into records both channels resolve
  (:func:`resolvable_groups`).
* phases: Schroeder's (``phi_k = -pi k (k - 1) / n``, low crest factor for equally spaced
  lines) and a few seeded random sets; the one with the lowest sampled peak over the record
  wins. Our lines are arbitrary (not on a harmonic grid), so no closed form is optimal; the
  search is cheap (milliseconds) and deterministic (its seed is the frequencies' bytes).

Example
-------
>>> ms = design_multisine([1.0, 2.5, 4.0], peak_n=1.0, duration_s=60.0)
>>> bool(ms.peak_bound(60.0) <= 1.0 + 1e-12)
True
>>> bool(ms.amplitudes_n[0] > 1.0 / 3)  # better than the crest factor of aligned phases
True
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Multisine", "design_multisine", "schroeder_phases", "resolvable_groups", "line_weights"]


@dataclass(frozen=True)
class Multisine:
    """``f(t) = sum_k a_k sin(omega_k t + phi_k)`` (t from the moment the record starts)."""

    omegas_rad_s: tuple[float, ...]
    amplitudes_n: tuple[float, ...]
    phases_rad: tuple[float, ...]

    def __post_init__(self):
        n = len(self.omegas_rad_s)
        if n == 0 or len(self.amplitudes_n) != n or len(self.phases_rad) != n:
            raise ValueError(f"multisine: expected as many amplitudes and phases as frequencies (>= 1), found "
                             f"{n}, {len(self.amplitudes_n)}, {len(self.phases_rad)}")

    @property
    def n_lines(self) -> int:
        return len(self.omegas_rad_s)

    def force(self, t_s) -> np.ndarray:
        """The force at times ``t_s`` (seconds from the start of the record)."""
        t = np.asarray(t_s, dtype=float)
        w, a, p = (np.asarray(v, dtype=float) for v in (self.omegas_rad_s, self.amplitudes_n, self.phases_rad))
        return np.sin(np.multiply.outer(t, w) + p) @ a

    def peak_bound(self, duration_s: float) -> float:
        """A guaranteed upper bound of ``|f(t)|`` for ``0 <= t <= duration_s``.

        ``|f|`` is sampled with step ``h``; between samples it can exceed the sampled maximum by
        at most ``M2 h^2 / 8`` with ``M2 = sum_k a_k omega_k^2 >= |f''|`` (at an interior
        maximum ``f' = 0``, and a sample lies within ``h / 2`` of it).
        """
        peak, margin = _sampled_peak(self, duration_s)
        return peak + margin


def _grid(omegas, duration_s: float) -> np.ndarray:
    h = 2 * math.pi / max(omegas) / 32
    return np.arange(0.0, float(duration_s) + h, h)


def _sampled_peak(ms: Multisine, duration_s: float) -> tuple[float, float]:
    t = _grid(ms.omegas_rad_s, duration_s)
    h = t[1] - t[0] if t.size > 1 else 0.0
    m2 = float(np.dot(ms.amplitudes_n, np.square(ms.omegas_rad_s)))
    return float(np.max(np.abs(ms.force(t)))), m2 * h * h / 8


def schroeder_phases(n: int) -> np.ndarray:
    """Schroeder's phases ``phi_k = -pi k (k - 1) / n``, ``k = 1..n`` (low crest factor)."""
    k = np.arange(1, int(n) + 1)
    return -np.pi * k * (k - 1) / int(n)


def design_multisine(omegas_rad_s, peak_n: float, duration_s: float, trials: int = 24, weights=None) -> Multisine:
    """Multisine whose guaranteed peak over ``duration_s`` is ``peak_n``: equal amplitudes, or
    amplitudes in the proportions ``weights`` (:func:`line_weights`).

    Parameters
    ----------
    omegas_rad_s : sequence of float
        The lines (distinct, positive); kept in the given order.
    peak_n : float
        Largest force allowed at any instant of the record.
    duration_s : float
        Longest the record may last (settling, windows and possible extensions).
    trials : int
        Seeded random phase sets tried besides Schroeder's.
    weights : sequence of float, optional
        Positive relative amplitudes, one per line (default: all equal).

    Returns
    -------
    Multisine
        A single line is a plain sine of amplitude ``peak_n`` and phase 0.
    """
    w = np.asarray(omegas_rad_s, dtype=float).ravel()
    if w.size == 0 or not np.all(np.isfinite(w)) or np.any(w <= 0):
        raise ValueError(f"multisine: expected positive finite frequencies, found {omegas_rad_s!r}")
    if np.unique(w).size != w.size:
        raise ValueError(f"multisine: frequencies must be distinct, found {w.tolist()}")
    if not (math.isfinite(peak_n) and peak_n > 0 and math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"multisine: expected a positive peak and duration, found {peak_n!r} N, {duration_s!r} s")
    n = w.size
    if n == 1:
        return Multisine((float(w[0]),), (float(peak_n),), (0.0,))
    order = np.argsort(w)
    candidates = []
    schroeder = np.empty(n)
    schroeder[order] = schroeder_phases(n)
    candidates.append(schroeder)
    rng = np.random.default_rng(int.from_bytes(hashlib.sha256(w.tobytes()).digest()[:8], "little"))
    candidates.extend(rng.uniform(0, 2 * np.pi, n) for _ in range(int(trials)))
    shape = np.ones(n) if weights is None else np.asarray(weights, dtype=float).ravel()
    if shape.size != n or not np.all(np.isfinite(shape)) or np.any(shape <= 0):
        raise ValueError(f"multisine: expected one positive weight per line, found {weights!r}")
    ones = tuple(float(v) for v in shape / shape.max())
    best = min(candidates, key=lambda p: sum(_sampled_peak(Multisine(tuple(w), ones, tuple(p)), duration_s)))
    unit = Multisine(tuple(float(v) for v in w), ones, tuple(float(v) for v in np.mod(best, 2 * np.pi)))
    a = float(peak_n) / unit.peak_bound(duration_s)
    return Multisine(unit.omegas_rad_s, tuple(a * v for v in ones), unit.phases_rad)


def line_weights(gains) -> np.ndarray:
    """Relative line amplitudes for a channel pair of limited resolution: ``|G|^(-1/2)`` of the
    expected response (largest 1). The force's lines then span as many decades as the
    response's, half the spread of ``|G|`` each, instead of the whole spread on the response
    channel (equal forces) or on the force channel (equal responses). Not finite: equal."""
    g = np.asarray(gains, dtype=float)
    if g.size == 0 or not np.all(np.isfinite(g)) or np.any(g <= 0):
        return np.ones(g.size)
    w = 1.0 / np.sqrt(g)
    return w / w.max()


def _resolved(gains: np.ndarray, dynamic_range: float) -> bool:
    """Every line of a record shaped by :func:`line_weights` at least ``1 / dynamic_range`` of
    the summed amplitudes on the force channel and on the response channel."""
    w = line_weights(gains)
    force, response = w / w.sum(), w * gains / np.dot(w, gains)
    return bool(min(force.min(), response.min()) * dynamic_range >= 1.0 - 1e-12)


def resolvable_groups(gains, dynamic_range: float) -> list[list[int]]:
    """The lines (by index) split into records a channel pair of limited resolution can hold,
    each record's lines shaped by :func:`line_weights`: the expected response gains ``|G|``
    largest first, each line joining the current record while every line stays at least
    ``1 / dynamic_range`` of the record's summed amplitudes on both channels (each channel is
    ranged for that sum's peak; a smaller line would sit in its quantization and noise), else
    opening the next. Each record's lines stay in the order given; the records come smallest
    first (the largest lines ring on longest). Gains not finite: one record.

    A choice of this project (the thesis measures single sines): an 8-bit oscilloscope ranged
    for a resonant line of the first mode saw a line near the second mode at 1 % of its
    screen, and that point's bound came out seven times the one a DAQ gives."""
    g = np.asarray(gains, dtype=float)
    if g.size == 0 or not np.all(np.isfinite(g)) or np.any(g <= 0) or not math.isfinite(dynamic_range):
        return [list(range(g.size))]
    groups: list[list[int]] = []
    for i in np.argsort(-g, kind="stable"):
        if groups and _resolved(g[groups[-1] + [int(i)]], dynamic_range):
            groups[-1].append(int(i))
        else:
            groups.append([int(i)])
    # the smallest first: a record's modes ring on after it, for minutes near a lightly damped
    # mode, and the next record's channels must hold that ringing as well as their own lines
    return [sorted(g_) for g_ in reversed(groups)]
