"""Ringing modes seen through a lock-in: how long to wait, and what the readings may still hold.

After the last change of the drive (a level step, the output switched on) the response of mode
``i`` is the steady state plus a free oscillation at the mode's pole ``p_i = -sigma_i + j w_d``.
A lock-in demodulating at the drive frequency ``w`` shows that free part at the *beat*
``w_d - w``, decaying at ``sigma_i``, through its output filter (``n`` first-order stages of time
constant ``tau``). Pure numerics of the interval model (no I/O); the dwell
(:mod:`setmem_hil.drivers.instruments.phasor_dwell`) decides with it.

**Amplitude** (:class:`FreeResponseBound`; rigorous for the drive history the dwell applied).
With the modal coordinate ``xi' = p xi + f`` and ``y_i = 2 Re(r_i xi)`` (``r_i`` the pole's residue
of thesis eq. 2.6) the free part ``h = xi - xi_ss`` (the deviation from the present sine's steady
state ``xi_ss = F e^{j w t} / (j w - p)``) decays as ``|h| e^{-sigma t}`` while the drive is
constant, and jumps by at most ``|F_old| / |j w_old - p| + |F_new| / |j w_new - p|`` (the same
frequency: ``|F_new - F_old| / |j w - p|``) when the drive changes. Any input bounded by
``F_max`` also keeps ``|h| <= 2 F_max / sigma``. The tracker follows every drive change of every
dwell (the structure is assumed at rest when the experiment is opened) and the free response is
``|y_free| <= 2 |r| |h|``. Over the interval model every factor takes its worst value: ``sigma`` its
lower bound ``a1_min / 2`` (eq. 2.3: ``a1 = 2 zeta w_n``), ``|j w - p| >= sqrt(sigma_min^2 +
beat_min^2)``, ``|r| <= (|b1|max sqrt(a0max) + |b0|max) / (2 w_d,min)``.

**Measured motion.** With any damping >= 0 a free oscillation never grows: twice the largest
response a dwell measured (its magnitude plus its bound, times the force) bounds every mode's free
response from the end of that dwell on, decaying at ``sigma_min`` where that is known. It caps the
replay above where the interval box is still loose, and bounds the ringing of a resonance dwell
before the damping is bounded at all.

**Filter.** An input ``exp(s t)`` with ``s = -sigma + j beat`` leaves the cascade as
``exp(s t) / (1 + s tau)^n`` once the filter's own transient (``tau``) has passed, so the gain is
``|1 + s tau|^-n`` at the beat the frequency interval allows nearest the drive.

**Wait.** ``k`` decay times ``1 / sigma_min`` of every mode whose filter gain is at least
``PASSING_GAIN`` (``k = DECAY_TIMES``: ``exp(-6) = 0.25 %`` of the worst-case amplitude is left);
a mode whose damping lower bound is still 0 (the prior, before the first identification) has no
finite decay time: its readings rely on the settling test, and no allowance can be computed for
it. The allowance for what is left (:meth:`FreeResponseBound.allowance`) is added to the point's bound.
A mode whose beat the filter does attenuate may still ring so hard (a dwell at its resonance just
before) that its leak swamps the signal: :func:`leak_wait_s` waits until its bounded leak is below
``LEAK_FRACTION`` of the signal the model expects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.model.modal_model import IntervalModel

__all__ = ["DECAY_TIMES", "PASSING_GAIN", "LEAK_FRACTION", "RingingMode", "ringing_modes", "ringdown_wait_s", "leak_wait_s",
           "leak_time_constant", "FreeResponseBound"]

DECAY_TIMES = 6.0
PASSING_GAIN = 1e-2  # a beat attenuated below 1 % by the output filter is not waited for by decay times
LEAK_FRACTION = 0.01  # ...but a mode ringing so hard that even its filtered beat exceeds 1 % of the signal is


@dataclass(frozen=True)
class RingingMode:
    """One mode at a drive frequency: its slowest possible decay and the filter's gain at its beat."""

    mode: int  # 0-based
    sigma_min: float  # decay rate lower bound (1/s); 0: unknown
    filter_gain: float  # the output filter's gain at the nearest beat the interval allows

    @property
    def passes(self) -> bool:
        return self.filter_gain >= PASSING_GAIN

    @property
    def decay_time_s(self) -> float:
        return math.inf if self.sigma_min <= 0 else 1.0 / self.sigma_min


def _filter_gain(sigma: float, beat: float, tau: float, order: int) -> float:
    return float(abs(1.0 + complex(-sigma, beat) * tau) ** -order)


def ringing_modes(model: IntervalModel, omega_rad_s: float, tau_s: float, order: int) -> list[RingingMode]:
    """Every modelled mode's decay rate bound and filter gain at drive frequency ``omega_rad_s``."""
    out = []
    for i in range(model.n_modes):
        sigma_min, sigma_max = _sigma_range(model, i)
        beat = _beat(model, i, omega_rad_s)
        gain = _filter_gain(min(sigma_max, 0.99 / tau_s), beat, tau_s, order)  # a larger sigma attenuates less (worst case)
        out.append(RingingMode(i, sigma_min, gain))
    return out


def _sigma_range(model: IntervalModel, i: int) -> tuple[float, float]:
    """Bounds of mode ``i``'s decay rate ``sigma = a1 / 2`` (eq. 2.3) over the box."""
    return max(model.lower[i, 0], 0.0) / 2.0, max(model.upper[i, 0], 0.0) / 2.0


def _damped_frequency_low(model: IntervalModel, i: int) -> float:
    """The lowest damped natural frequency ``sqrt(a0 - sigma^2)`` the box allows."""
    return math.sqrt(max(model.lower[i, 1] - _sigma_range(model, i)[1] ** 2, 0.0))


def _beat(model: IntervalModel, i: int, omega: float) -> float:
    """The smallest |w_d - omega| the interval box allows."""
    wd_lo = _damped_frequency_low(model, i)
    wd_hi = math.sqrt(max(model.upper[i, 1], 0.0))
    return 0.0 if wd_lo <= omega <= wd_hi else min(abs(omega - wd_lo), abs(omega - wd_hi))


def ringdown_wait_s(modes: list[RingingMode]) -> float:
    """``DECAY_TIMES`` decay times of the slowest passing mode with a known decay rate (0 if none)."""
    times = [m.decay_time_s for m in modes if m.passes and m.sigma_min > 0]
    return DECAY_TIMES * max(times) if times else 0.0


def _residue_max(model: IntervalModel, i: int) -> float:
    """``|r| <= (|b1|max sqrt(a0max) + |b0|max) / (2 w_d,min)`` over the box (inf when unbounded)."""
    b1 = max(abs(model.lower[i, 2]), abs(model.upper[i, 2]))
    b0 = max(abs(model.lower[i, 3]), abs(model.upper[i, 3]))
    wd_lo = _damped_frequency_low(model, i)
    return (b1 * math.sqrt(model.upper[i, 1]) + b0) / (2.0 * wd_lo) if wd_lo > 0 else math.inf


def _pole_distance(model: IntervalModel, i: int, omega: float) -> float:
    """The smallest ``|j omega - p|`` the box allows: ``hypot(sigma_min, beat)``."""
    return math.hypot(_sigma_range(model, i)[0], _beat(model, i, omega))


def _per_distance(force: float, distance: float) -> float:
    if force == 0:
        return 0.0
    return force / distance if distance > 0 else math.inf


class FreeResponseBound:
    """Bounds the free part of every modelled mode through the drive history (module docstring).

    :meth:`drive` records every change of the drive (frequency, level, output on or off);
    :meth:`bound` replays the whole history with the *current* interval model: the true
    parameters lie in it (and intervals never loosen, eq. 5.4-5.5), so decays and jumps computed
    with it bound what happened, also before the model knew as much. A jump the model cannot
    bound (a drive at a frequency the mode's interval allows) restarts from the any-input bound
    ``2 F_max / sigma``; a mode whose damping lower bound is still 0 has no bound.
    """

    def __init__(self, force_max_n: float):
        self.events: list[tuple[float, float, float]] = []  # (time, omega, force) from time on
        self.motions: list[tuple[float, float]] = []  # (time, measured response amplitude) at each dwell's end
        self.force_max = force_max_n

    def drive(self, t: float, omega: float, force: float) -> None:
        """The drive became ``force`` (amplitude, N; 0: output off) at ``omega`` at time ``t``."""
        self.events.append((float(t), float(omega), float(force)))

    def bound(self, model: IntervalModel, i: int, t: float) -> float:
        """``|xi - xi_ss|`` bound of mode ``i`` at time ``t`` (inf: not boundable yet)."""
        sigma = _sigma_range(model, i)[0]
        if sigma <= 0:  # no damping lower bound: nothing decays in the worst case; the settling test decides
            return math.inf
        cap = 2.0 * self.force_max / sigma
        h, last_t, omega, force = 0.0, 0.0, 0.0, 0.0  # at rest when the experiment was opened
        for when, new_omega, new_force in self.events:
            if when > t:
                break
            h *= math.exp(-sigma * (when - last_t))
            dist_old = _pole_distance(model, i, omega)
            dist_new = _pole_distance(model, i, new_omega)
            if new_omega == omega:
                jump = _per_distance(abs(new_force - force), dist_new)
            else:
                jump = _per_distance(force, dist_old) + _per_distance(new_force, dist_new)
            h = min(h + jump, cap)
            last_t, omega, force = when, new_omega, new_force
        return min(h * math.exp(-sigma * (t - last_t)), cap)

    def record_motion(self, t: float, amplitude: float) -> None:
        """A dwell ending at ``t`` measured a response of ``amplitude`` (output units: the point's
        magnitude plus its bound, times the force). With any damping >= 0 a free oscillation
        never grows, so twice this bounds every mode's free response afterwards, also where the
        intervals do not bound the damping yet."""
        self.motions.append((float(t), float(amplitude)))

    def free_output(self, model: IntervalModel, i: int, t: float, measured_cap: bool = True) -> float:
        """Bound of mode ``i``'s free response (output units) at ``t``: the history replay
        (:meth:`bound`), or the measured motions if smaller (``measured_cap``)."""
        if not self.motions and not self.events:
            return 0.0
        sigma = _sigma_range(model, i)[0]
        replay = 2.0 * _residue_max(model, i) * self.bound(model, i, t)
        replay = math.inf if math.isnan(replay) else replay
        if not measured_cap:
            return replay
        measured = max((2.0 * a * math.exp(-sigma * (t - when)) for when, a in self.motions if when <= t), default=math.inf)
        return min(replay, measured)

    def allowance(self, model: IntervalModel, times_s: np.ndarray, omega: float, tau_s: float, order: int,
                  force_n: float) -> float:
        """Worst-case error, in receptance units, of the mean of readings taken at ``times_s``
        (clock times after the last drive change) through the output filter, relative to the
        measured force amplitude ``force_n``: every passing mode's free response (the history
        replay of :meth:`free_output`) times the filter's gain at its beat. Modes with no finite
        bound (no damping lower bound yet) are left out: they rely on the settling test and the
        trend fit; filtered beats leak as fast oscillations the readings' scatter shows."""
        times = np.asarray(times_s, dtype=float)
        start = float(times.min())
        total = 0.0
        for mode in ringing_modes(model, omega, tau_s, order):
            if not mode.passes:  # a filtered beat leaks as a fast oscillation: the scatter sees it
                continue         # (and the time constant was chosen to keep it small: leak_time_constant)
            free = self.free_output(model, mode.mode, start, measured_cap=False)
            if math.isfinite(free):
                total += free * mode.filter_gain * float(np.mean(np.exp(-mode.sigma_min * (times - start))))
        return total / force_n


def leak_wait_s(tracker: FreeResponseBound, model: IntervalModel, omega: float, tau_s: float, order: int, now: float,
                force_n: float, expected: float) -> float:
    """How long until every filtered (non-passing) mode's bounded leak through the output filter
    is below ``LEAK_FRACTION`` of the ``expected`` response magnitude (receptance units, at
    ``force_n``); 0 when nothing leaks that much or the model cannot tell (no damping bound,
    no finite expectation)."""
    if not (math.isfinite(expected) and expected > 0 and force_n > 0):
        return 0.0
    wait = 0.0
    for mode in ringing_modes(model, omega, tau_s, order):
        if mode.passes or mode.sigma_min <= 0:
            continue
        leak = tracker.free_output(model, mode.mode, now) * mode.filter_gain / force_n
        if math.isfinite(leak) and leak > LEAK_FRACTION * expected:
            wait = max(wait, math.log(leak / (LEAK_FRACTION * expected)) / mode.sigma_min)
    return wait


def leak_time_constant(tracker: FreeResponseBound, model: IntervalModel, omega: float, order: int, now: float,
                       time_constants_s: tuple[float, ...], base_tau_s: float, force_n: float, expected: float,
                       max_steps: int = 3) -> float:
    """The shortest of the lock-in's time constants from ``base_tau_s`` up (at most ``max_steps``
    longer) at which every mode's measured-motion bound (:meth:`FreeResponseBound.free_output`:
    valid for any damping >= 0) leaks through the filter at less than ``LEAK_FRACTION`` of the
    ``expected`` response; modes too near the drive for a longer filter to help are the wait's
    business. ``base_tau_s`` where nothing leaks that much or nothing is known."""
    if not (math.isfinite(expected) and expected > 0 and force_n > 0 and tracker.motions):
        return base_tau_s
    longer = [t for t in time_constants_s if t >= base_tau_s][: max_steps + 1]
    for tau in longer:
        leaks = [tracker.free_output(model, i, now) * _filter_gain(0.0, _beat(model, i, omega), tau, order)
                 for i in range(model.n_modes) if _beat(model, i, omega) * tau > 3.0]
        if all(leak <= LEAK_FRACTION * expected * force_n for leak in leaks):
            return tau
    return longer[-1] if longer else base_tau_s
