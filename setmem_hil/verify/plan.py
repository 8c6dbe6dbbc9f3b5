"""The closed-loop verification as a plan on the run engine (issue 45).

``verification_plan(setup)`` yields requests (:mod:`setmem_hil.verify.messages`) and documents;
the engine performs them (:mod:`setmem_hil.verify.target_service`). It reads the target's
identity, loads the compensator (checksum read back), then for each gain of ``[verify] gains``,
ascending:

1. certifies the loop at that gain before engaging it (all gains before the first is engaged:
   a board's watchdog must not wait on the host's seconds of computing), with the target's
   sections, delay and hold (:mod:`setmem_hil.robust.implemented_loop`, the band certificate's
   level): below the full gain, robust stability of
   ``gain * K`` (mu-bar of the parametric and unmodelled blocks below 1: a smaller gain rejects
   less, so the performance it was designed for is not asked of it); at the full gain, robust
   performance (the implemented mu-bar below 1). Else :class:`NotEngaged`, nothing engaged;
2. engages it (confirmed by the state read back);
3. at each frequency, injects a sine at the summing junction and measures ``S = u/r`` and
   ``G = y/u`` with their bounds (:mod:`setmem_hil.estimation.closed_loop_point`), and checks
   ``S`` against the box's guaranteed prediction (:mod:`setmem_hil.robust.closed_loop_prediction`);
4. stops engaging higher gains after a step with a point outside the prediction (the model is
   falsified: a careful engineer does not push a loop whose model just failed further).

Before the first gain, with the target bypassed and the generator off, it records the rig at
rest (:data:`BASELINE_PERIODS` periods of the lowest modelled mode, at least
:data:`BASELINE_MIN_S`): the response's rms there is the rig's own noise and disturbance.

**A loop that does not settle is stopped** (:class:`LoopNotSettled`, exit 4 as a trip). After
the settling time (ten time constants of the box's nominal closed loop), a loop that behaves as
any plant of the box has left only noise besides the injection's sine. When the free part of the
response is larger than the forced part *and* :data:`NOT_SETTLED_FACTOR` times the rig at rest,
the loop rings where nothing predicted it: unstable, or so nearly that its growth is slower than
a dwell (the beam without damping grows with a time constant of minutes, never reaching a limit
in a dwell). Both conditions, so that a rig whose disturbance exceeds a small injection at an
anti-resonance does not trip. This rule is ours: the thesis stops before closing the loop.

However it ends (an error thrown in, an abort), its ``finally`` turns the generator off and
bypasses the target (confirmed). The frequencies, when the procedure gives none, come from the
prediction (:func:`chosen_frequencies`): the predicted peak of ``|W2 S|``, each modelled mode,
and the band's ends.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from setmem_hil.run.engine import Checkpoint, Emit
from setmem_hil.errors import DeviceError
from setmem_hil.estimation.analyser_sums import AnalyserSums, closed_loop_point_from_sums
from setmem_hil.estimation.closed_loop_point import ClosedLoopPoint, closed_loop_point
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.weights import Weights
from setmem_hil.robust.closed_loop_prediction import PredictedSensitivity, predicted_sensitivity
from setmem_hil.robust.implemented_loop import implemented_mu_bar, implemented_response
from setmem_hil.robust.validation import closed_loop_matrix
from setmem_hil.verify.messages import Bypass, Engage, IdentifyTarget, InjectAndRecord, LoadCompensator

__all__ = ["VerifySetup", "VerifiedPoint", "VerifyResult", "NotEngaged", "verification_plan", "chosen_frequencies", "settle_time_s",
           "informative", "INFORMATIVE_SPAN"]


INFORMATIVE_SPAN = 10.0
"""A point's prediction is *informative* when it is bounded and its ``|S|`` spans at most this factor
(``max <= INFORMATIVE_SPAN * min``, ``min > 0``; issue 63). A prediction of ``0..inf``, or of more
than a decade, cannot be contradicted by any measurement: such a point is reported as
uninformative and counts neither as inside nor as outside; ``verified`` needs informative points
(our rule: a decade, the span a lab reads as a check on a log-magnitude plot)."""

BASELINE_PERIODS = 2.0
BASELINE_MIN_S = 2.0
NOT_SETTLED_FACTOR = 10.0


class NotEngaged(Exception):
    """A gain step whose implemented mu-bar is not below 1: never engaged."""


class LoopNotSettled(DeviceError):
    """The loop rang after the settling time (see the module docstring): bypassed, exit 4."""


@dataclass(frozen=True)
class VerifySetup:
    """Everything the plan needs: the box and the compensator of the run, the target's timing."""

    model: IntervalModel
    calibration_gain: tuple[float, float] | None
    weights: Weights
    controller: Any  # continuous, rad/s, positive feedback
    sos: np.ndarray
    sos_gain: float
    prewarp_rad_s: float
    fs_hz: float
    delay_samples: int
    gains: tuple[float, ...]
    frequencies_rad_s: tuple[float, ...]
    injection_amplitude: float
    settle_s: float
    periods: int
    full_gain_mu_bar: float = math.nan  # the full gain's implemented mu-bar when the caller certified it already


@dataclass(frozen=True)
class VerifiedPoint:
    gain: float
    measured: ClosedLoopPoint
    prediction: PredictedSensitivity
    inside: bool  # consistent with an informative prediction (False where the prediction is uninformative)
    weighted_performance: float  # |W2 S| + |W1 g K_impl S| with the measured S
    informative: bool = True  # the prediction could have been contradicted (:data:`INFORMATIVE_SPAN`)

    @property
    def outside(self) -> bool:
        """An informative prediction the measurement contradicts: the model is falsified here."""
        return self.informative and not self.inside

    def to_document(self) -> dict:
        lo, hi = self.prediction.abs_range
        m = self.measured
        return {"omega_rad_s": m.omega_rad_s, "S_re": m.S.real, "S_im": m.S.imag, "S_bound": m.S_bound,
                "predicted_abs_S_min": lo, "predicted_abs_S_max": hi if math.isfinite(hi) else None, "inside": bool(self.inside),
                "informative": bool(self.informative),
                "G_re": m.G.real, "G_im": m.G.imag, "G_bound": m.G_bound, "weighted_performance": self.weighted_performance,
                "peak_drive": m.peak_drive, "peak_response": m.peak_response,
                **({"A_re": m.A.real, "A_im": m.A.imag, "A_bound": m.A_bound} if m.has_force else {})}


@dataclass
class VerifyResult:
    identity: Any = None
    checksum: int | None = None
    steps: list[dict] = field(default_factory=list)
    implemented_mu_bar: float = math.nan
    points: list[VerifiedPoint] = field(default_factory=list)
    baseline_rms: float = math.nan  # the response's rms with the target bypassed and the generator off

    @property
    def first_outside(self) -> VerifiedPoint | None:
        return next((p for p in self.points if p.outside), None)

    def informative_in_every_step(self) -> bool:
        """Did every gain step measure at least one point whose prediction is informative?"""
        return bool(self.steps) and all(any(p.get("informative", True) for p in step["points"]) for step in self.steps)


def verification_plan(setup: VerifySetup, result: VerifyResult | None = None):
    """See the module docstring; fills and returns ``result`` (a caller that passes its own keeps
    what was measured however the plan ends)."""
    result = VerifyResult() if result is None else result
    result.identity = yield IdentifyTarget()
    yield Emit("target", {"identity": result.identity.text, "fs_hz": result.identity.fs_hz,
                          "delay_samples": result.identity.delay_samples})
    result.checksum = yield LoadCompensator(setup.sos, setup.sos_gain)
    yield Emit("loaded", {"checksum": f"{result.checksum:08X}", "sections": int(len(setup.sos))})
    # every step certified before anything is engaged: a board's watchdog must not wait on the
    # host's computing between two steps (seconds, against its 0.5 s)
    certificates = {gain: _certify_step(setup, gain) for gain in setup.gains}
    try:
        result.baseline_rms = yield from _rig_at_rest(setup)
        for gain in setup.gains:
            certified = certificates[gain]
            if gain >= 1.0:
                result.implemented_mu_bar = certified
            yield Checkpoint(f"engaging at gain {gain:g}")
            yield Engage(gain)
            kind = "performance" if gain >= 1.0 else "stability"
            yield Emit("engaged", {"gain": gain, "implemented_mu_bar": certified, "certified": kind})
            points: list[VerifiedPoint] = []
            try:
                yield from _measure_step(setup, gain, points, result.baseline_rms)
            finally:  # a step cut short by a fault keeps what it measured
                result.points += points
                result.steps.append({"gain": gain, "implemented_mu_bar": certified, "certified": kind,
                                     "points": [p.to_document() for p in points]})
            yield Emit("step", {"gain": gain, "points": len(points), "outside": sum(p.outside for p in points),
                                "uninformative": sum(not p.informative for p in points)})
            if any(p.outside for p in points):
                break
    finally:
        yield Bypass("the verification ended")
    return result


def _rig_at_rest(setup: VerifySetup):
    """The response's rms with the target bypassed and the generator off (the record is kept)."""
    modes = setup.model.midpoint.natural_frequencies
    lowest = float(np.min(modes[modes > 0])) if np.any(modes > 0) else 2 * math.pi
    duration = max(BASELINE_MIN_S, BASELINE_PERIODS * 2 * math.pi / lowest)
    yield Checkpoint("recording the rig at rest")
    record = yield InjectAndRecord(lowest, 0.0, 0.0, duration, label="baseline")
    if isinstance(record, AnalyserSums):
        rms = record.response_rms
    else:
        y = np.asarray(record.y, float)
        rms = float(np.sqrt(np.mean((y - y.mean()) ** 2)))
    yield Emit("baseline", {"response_rms": rms, "duration_s": duration})
    return rms


def _certify_step(setup: VerifySetup, gain: float) -> float:
    """The step's certified value (the band certificate's level, :mod:`~setmem_hil.robust.
    implemented_loop`): robust stability below the full gain, robust performance at it."""
    full = gain >= 1.0
    if gain == 1.0 and setup.full_gain_mu_bar < 1.0:  # certified by the command before anything moved: the same loop
        return float(setup.full_gain_mu_bar)
    loop = implemented_mu_bar(setup.model, setup.weights, _scaled(setup.controller, gain), setup.fs_hz, setup.delay_samples,
                              setup.prewarp_rad_s, setup.calibration_gain, performance=full)
    if not loop.guaranteed_mu_bar < 1.0:
        what = "mu-bar" if full else "robust-stability mu-bar"
        raise NotEngaged(f"gain {gain:g}: the loop as the target runs it has {what} {loop.mu_bar:.4g} (certified "
                         f"{loop.guaranteed_mu_bar:.4g}), not below 1: not engaged")
    return float(loop.guaranteed_mu_bar)


def _scaled(K, gain: float):
    import control

    return control.ss(K.A, K.B, np.asarray(K.C) * gain, np.asarray(K.D) * gain)


def _measure_step(setup: VerifySetup, gain: float, points: list, baseline_rms: float):
    for w in setup.frequencies_rad_s:
        yield Checkpoint(f"gain {gain:g}, {w:.4g} rad/s")
        record_s = setup.periods * 2 * math.pi / w
        record = yield InjectAndRecord(w, setup.injection_amplitude, setup.settle_s, record_s)
        if isinstance(record, AnalyserSums):  # the target's own analyser
            point = closed_loop_point_from_sums(record)
        else:
            point = closed_loop_point(record.t_s, record.r, record.u, record.y, w)
        k = complex(implemented_response(setup.controller, setup.fs_hz, setup.delay_samples, setup.prewarp_rad_s, [w])[0])
        prediction = predicted_sensitivity(setup.model, setup.weights, k, w, setup.calibration_gain, loop_gain=gain)
        # |W2 S| + |W1 K S| with the weights the claimed mu-bar was computed with
        performance = float(setup.weights.w2_magnitude(w)) * abs(point.S) + float(setup.weights.w1_magnitude(w)) * abs(gain * k * point.S)
        useful = informative(prediction)
        verified = VerifiedPoint(gain, point, prediction, useful and prediction.holds(point.S, point.S_bound), float(performance), useful)
        yield Emit("point", verified.to_document() | {"gain": gain})
        points.append(verified)
        _check_settled(point, gain, setup.settle_s, baseline_rms)


def informative(prediction: PredictedSensitivity) -> bool:
    """Could a measurement contradict this prediction? Bounded, and ``|S|`` within a factor of
    :data:`INFORMATIVE_SPAN`."""
    lo, hi = prediction.abs_range
    return prediction.bounded and lo > 0 and math.isfinite(hi) and hi <= INFORMATIVE_SPAN * lo


def _near(omega_rad_s: float) -> str:
    return f" near {omega_rad_s:.4g} rad/s" if math.isfinite(omega_rad_s) else ""  # the analyser's sums carry no spectrum


def _check_settled(point: ClosedLoopPoint, gain: float, settle_s: float, baseline_rms: float) -> None:
    """:class:`LoopNotSettled` when the free part of the response exceeds both the forced part and
    :data:`NOT_SETTLED_FACTOR` times the rig at rest (see the module docstring)."""
    free, forced_rms = point.free_response_rms, point.forced_response_amplitude / math.sqrt(2.0)
    rest = baseline_rms if math.isfinite(baseline_rms) else 0.0
    if free > forced_rms and free > NOT_SETTLED_FACTOR * rest:
        raise LoopNotSettled(
            f"the loop did not settle at gain {gain:g}: at {point.omega_rad_s:.4g} rad/s, after the settling time of {settle_s:.4g} s, "
            f"the response rings{_near(point.free_response_omega_rad_s)} ({free:.3g} rms, more than the injected "
            f"response's {forced_rms:.3g} and {free / rest if rest > 0 else math.inf:.3g}x the rig at rest): "
            "the loop is unstable or nearly so; bypassed")


def chosen_frequencies(model: IntervalModel, weights: Weights, controller, fs_hz: float, delay_samples: int, prewarp_rad_s: float,
                       gain=None) -> tuple[float, ...]:
    """The predicted peak of ``|W2 S|`` (the largest predicted ``|S|`` weighted, among informative
    predictions: :func:`informative`), every modelled
    mode's natural frequency (the box's midpoint), and the band's ends (half the lowest mode,
    twice the highest, below 0.4 Nyquist)."""
    modes = model.midpoint.natural_frequencies
    lo, hi = 0.5 * float(np.min(modes)), min(2.0 * float(np.max(modes)), 0.4 * math.pi * fs_hz)
    grid = np.geomspace(lo, hi, 400)
    k = implemented_response(controller, fs_hz, delay_samples, prewarp_rad_s, grid)
    weighted = []
    for w, kw in zip(grid, k):  # the peak among predictions that can be contradicted (issue 63)
        prediction = predicted_sensitivity(model, weights, complex(kw), float(w), gain)
        s_max = prediction.abs_range[1]
        weighted.append(float(weights.w2_magnitude(w)) * s_max if informative(prediction) else -1.0)
    peak = float(grid[int(np.argmax(weighted))])
    chosen = sorted({round(float(v), 9) for v in (lo, peak, *modes, hi) if lo <= v <= hi})
    return tuple(chosen)


def settle_time_s(model: IntervalModel, controller, gain: float = 1.0, constants: float = 10.0, floor_s: float = 1.0) -> float:
    """``constants`` time constants of the slowest pole of the nominal closed loop (the box's
    midpoint under ``gain * K``), at least ``floor_s``."""
    slowest = float(np.min(-np.linalg.eigvals(closed_loop_matrix(model.midpoint, _scaled(controller, gain))).real))
    return max(floor_s, constants / slowest) if slowest > 0 else floor_s
