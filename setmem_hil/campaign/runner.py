"""The iterative identification / control / experiment loop (thesis Algorithm 5.1, chapter 5).

``run_campaign`` measures the procedure's initial frequencies, then repeats:

2. identify the parameter intervals from all data so far, never loosening the previous bounds
   (eq. 5.4-5.5; the result is also intersected with them);
3. design the H2 controller and compute mu-bar with the monotone safeguard (eq. 5.8-5.12,
   :mod:`setmem_hil.design.safeguard`), so the reported mu-bar never increases;
4. stop when mu-bar < the goal (default 1) or when the experiment budget is spent;
5-7. choose the next frequency with the procedure's strategy (:mod:`setmem_hil.design.strategies`;
   ``"mu"`` is eq. 5.3 via :func:`setmem_hil.design.input_design.choose_input`), measure it, and go on.

**A region that keeps disappointing** (section 6.3.4's trap): after three consecutive
single-frequency iterations in one region that each lowered mu-bar by less than a quarter of
the improvement predicted for them, that region is left out of the candidates for the rest of
the campaign (:mod:`setmem_hil.design.unproductive_region`; journal event ``left-out``). It
depends only on the mu-bar values and choices, so a replay leaves out the same regions.

**Journal and resume (REPLAY).** Every measurement is written to the journal as soon as it is
taken, every iteration's bounds, mu-bar, sensitivities and candidate scores after it is
computed. A campaign resumed from its journal reruns the loop from the start: whenever it needs
measurement ``n`` and the journal holds it, the stored one is used (its frequency must match:
otherwise :class:`CampaignReplayError`), and iterations already stored are not re-added. Before
the first new dwell the experiment's ``n_measured`` (if it has one) is set to the number of
stored measurements, so the simulated noise continues exactly. Nothing depends on the wall
clock or a global RNG: the same seed gives the same measurements and choices serially, resumed
or on Dask workers.

**Model hook.** After every identification the experiment's ``update_model(model)`` (if it has
one, e.g. :class:`setmem_hil.drivers.sine_dwell.SineDwellExperiment`) is called with the
iteration's interval model (the bounds the journal stores), so later dwells fit their decaying
transients with the narrowed pole estimates (eq. 2.25 midpoints, interval bands). A replay
repeats the same identifications in the same order and so makes the same calls: the experiment
is in the same state at the first new dwell as in an uninterrupted run.

**Single-threaded BLAS.** The numerics of every iteration (identification, H2 design, mu
analysis, input choice) run with BLAS pinned to one thread in the calling thread
(:func:`setmem_hil.numerics.blas_threads.blas_one_thread`): the matrices are small, so this is about
twice as fast in CPU time on the 2-core target, and results do not depend on how many BLAS
threads a machine or Dask worker would otherwise use.

**Noise bound of a candidate.** The effect estimate needs ``R(omega)``, the total error bound a
measurement at ``omega`` will report. ``experiment.total_bound(omega)`` is used when the
experiment has it (the simulated beam); otherwise the bounds measured so far are interpolated
linearly in ``log omega`` (of ``log R`` when all are positive), held constant outside the
measured range.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from setmem_hil.numerics.blas_threads import blas_one_thread
from setmem_hil.errors import CampaignReplayError, DeviceError
from setmem_hil.model.experiment import (
    CalibrationScaledExperiment,
    BoundPredictingExperiment,
    Experiment,
    Measurement,
    ModelAwareExperiment,
    OutputModelsAwareExperiment,
    PlanningExperiment,
    MultisineExperiment,
    OutputConfirmingExperiment,
    ResumableExperiment,
)
from setmem_hil.model.mu_floor import floor_message, floor_modes
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.identification.calibration_scale import measured_scale_prior, plant_bounds
from setmem_hil.design.input_design import InputChoice, candidate_frequencies, choose_input, sensitivity_matrix, uniform_weights
from setmem_hil.design.unproductive_region import RUN, Outcome, describe, outside_regions, predicted_improvement, unproductive_region
from setmem_hil.io.procedure import Procedure
from setmem_hil.design.safeguard import SafeguardOutcome, certified_value, safeguarded_design
from setmem_hil.robust.robust_design import FINAL_TUNING
from setmem_hil.design.strategies import check_strategy, log_sweep_frequency, random_frequency

ProgressFn = Callable[..., None]

EXACT_RESOLVE_EVENT = "exact-resolve"
"""Journal event holding, as JSON, the candidates re-identified exactly at an iteration and their
improvement (the choice is the best of these; the report's figure 6-14 shows them)."""

EXACT_RESOLVE_OUTER_ITERATIONS = 1
"""Algorithm 3.1 passes of the exact re-solves of the top candidates (speed; see the report)."""


@dataclass(frozen=True)
class IterationSummary:
    """One row of the figure-6-12 table."""

    k: int
    n_points: int
    mu_peak: float
    mu_peak_omega: float
    next_omega: float | None
    safeguard: str
    basis: str
    compute_s: float
    compute_cpu_s: float = 0.0
    rig_s: float = 0.0  # device seconds of the dwells this iteration asked for (measured after it)
    mu_peak_certified: bool = False  # mu_peak bounds mu-bar on the whole band, not only the grid
    mu_certified_intervals: int = 0
    design: str = "h2"  # the design that made the kept compensator: "robust" or "h2" (issue 38)
    floor_modes: tuple[int, ...] = ()  # modes whose box blocks every compensator (setmem_hil.model.mu_floor)

    def to_document(self) -> dict:
        return {
            "k": self.k,
            "mu_peak": self.mu_peak,
            "mu_peak_certified": bool(self.mu_peak_certified),
            "mu_certified_intervals": int(self.mu_certified_intervals),
            "next_omega": self.next_omega,
            "n_points": self.n_points,
            "mu_peak_omega": self.mu_peak_omega,
            "safeguard": self.safeguard,
            "basis": self.basis,
            "compute_s": self.compute_s,
            "compute_cpu_s": self.compute_cpu_s,
            "rig_s": float(self.rig_s),
            "design": self.design,
            "floor_modes": [int(m) for m in self.floor_modes],
        }


@dataclass(frozen=True)
class CampaignSummary:
    """Result of :func:`run_campaign`; :meth:`to_document` is ``summary.json``."""

    reached_goal: bool
    final_mu_peak: float
    experiments_added: int
    wall_s: float
    iterations: tuple[IterationSummary, ...]
    strategy: str
    seed: int | None
    goal_mu: float
    max_experiments: int
    stop_reason: str
    replayed_measurements: int = 0
    rig_s: float = 0.0  # device seconds of every dwell, initial points included
    extra: dict = field(default_factory=dict)

    @property
    def compute_s_per_iteration(self) -> float:
        """Mean compute time of an iteration (identification, design, analysis, input choice)."""
        if not self.iterations:
            return 0.0
        return float(np.mean([it.compute_s for it in self.iterations]))

    def to_document(self) -> dict:
        return {
            "reached_goal": bool(self.reached_goal),
            "final_mu_peak": float(self.final_mu_peak),
            "experiments_added": int(self.experiments_added),
            "wall_s": float(self.wall_s),
            "iterations": [it.to_document() for it in self.iterations],
            "strategy": self.strategy,
            "seed": self.seed,
            "goal_mu": float(self.goal_mu),
            "max_experiments": int(self.max_experiments),
            "stop_reason": self.stop_reason,
            "compute_s_per_iteration": self.compute_s_per_iteration,
            "compute_cpu_s_per_iteration": float(np.mean([it.compute_cpu_s for it in self.iterations])) if self.iterations else 0.0,
            "replayed_measurements": int(self.replayed_measurements),
            "rig_s": float(self.rig_s),
            **self.extra,
        }


def candidate_noise_bound(experiment: Any, omega_rad_s: np.ndarray, measured: list[Measurement]) -> np.ndarray:
    """``R(omega)`` expected at the candidates (see the module docstring)."""
    w = np.asarray(omega_rad_s, dtype=float)
    if isinstance(experiment, BoundPredictingExperiment):
        return np.broadcast_to(np.asarray(experiment.total_bound(w), dtype=float), w.shape).copy()
    if not measured:
        raise ValueError("candidate_noise_bound: no measurements to interpolate the error bound from")
    mw = np.array([m.omega_rad_s for m in measured], dtype=float)
    mb = np.array([m.bound for m in measured], dtype=float)
    order = np.argsort(mw, kind="stable")
    mw, mb = mw[order], mb[order]
    x = np.log(mw)
    if np.all(mb > 0):
        return np.exp(np.interp(np.log(w), x, np.log(mb)))
    return np.interp(np.log(w), x, mb)


class _Replay:
    """Measurement source that serves stored journal measurements first (REPLAY resume)."""

    def __init__(self, experiment: Experiment, journal, emit: ProgressFn, total: int, control=None):
        self.experiment = experiment
        self.control = control
        self.journal = journal
        self.emit = emit
        self.total = total
        self.stored = journal.measurements() if journal is not None else []
        self.count = 0
        self._synced = False

    def _make_safe(self) -> None:
        """What a pause waits for: every exciter output confirmed off (read back)."""
        if isinstance(self.experiment, OutputConfirmingExperiment):
            self.experiment.confirm_output_off()

    def _checkpoint(self) -> None:
        """The live view's checkpoint between dwells; a pause is journaled when it holds (the
        outputs confirmed off) and when it ends, each event with its time (issue 39, item 4)."""
        if self.control is None:
            return
        held_since = []

        def safe_and_journaled() -> None:
            self._make_safe()
            held_since.append(time.monotonic())
            if self.journal is not None:
                self.journal.add_event("paused", f"paused before measurement {self.count}: every exciter output confirmed off")

        self.control.checkpoint(safe_and_journaled)  # may wait (paused) or raise CampaignAborted
        if held_since and self.journal is not None:
            self.journal.add_event("unpaused", f"went on after {time.monotonic() - held_since[0]:.1f} s paused")

    def measure(self, omega_rad_s: float, *, iteration: int, role: str) -> Measurement:
        index = self.count
        self.count += 1
        if index < len(self.stored):
            m = self.stored[index]
            if not math.isclose(m.omega_rad_s, omega_rad_s, rel_tol=1e-9, abs_tol=1e-12):
                raise CampaignReplayError(
                    str(getattr(self.journal, "path", "journal")),
                    f"measurement {index + 1}",
                    f"stored at {m.omega_rad_s:.9g} rad/s but the procedure now asks for {omega_rad_s:.9g} rad/s "
                    "(different procedure, seed, strategy or software version?)",
                )
            self.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=True)
            return m
        self._checkpoint()  # between dwells: may wait (paused) or raise CampaignAborted
        if not self._synced:
            if self.stored and isinstance(self.experiment, ResumableExperiment):
                self.experiment.n_measured = len(self.stored)
            self._synced = True
        self.emit("measure", index=index + 1, total=self.total, omega_rad_s=float(omega_rad_s), replayed=False)
        m = self.experiment.measure(float(omega_rad_s))
        if self.journal is not None:
            self.journal.add_measurement(m, iteration=iteration, role=role)
        return m


    def measure_record(self, omegas_rad_s, *, iteration: int, role: str) -> list[Measurement]:
        """Several frequencies in one multisine record (``[dwell] signal = "multisine"``).

        Stored lines are served from the journal; if any line of the record is missing (a kill
        while the record's lines were being written) the whole record is measured again with
        its first line's index, which reproduces the stored lines exactly, and only the missing
        ones are journaled. One frequency is an ordinary :meth:`measure`.
        """
        lines = [float(w) for w in omegas_rad_s]
        if len(lines) == 1:
            return [self.measure(lines[0], iteration=iteration, role=role)]
        start = self.count
        stored = [self.measure(w, iteration=iteration, role=role) for w in lines[: max(0, len(self.stored) - start)]]
        if len(stored) == len(lines):
            return stored
        if not isinstance(self.experiment, MultisineExperiment):
            raise DeviceError(f"{type(self.experiment).__name__} cannot measure a multisine record "
                              "([dwell] signal = \"multisine\" needs backend kind 'sim' or 'time-domain')")
        self._checkpoint()
        if isinstance(self.experiment, ResumableExperiment):
            self.experiment.n_measured = start  # the record's noise is seeded with its first line's index
        self._synced = True
        self.count = start + len(lines)
        self.emit("measure", index=start + 1, total=self.total, omega_rad_s=lines[0], replayed=False, record_omegas=tuple(lines))
        record = self.experiment.measure_multisine(lines)
        for m in record[len(stored):]:
            if self.journal is not None:
                self.journal.add_measurement(m, iteration=iteration, role=role)
        return stored + list(record[len(stored):])


def identify_sensors(measured: list[Measurement], procedure: Procedure, previous, scales=None):
    """Several sensors (issue 25): every output's data in one identification with shared poles
    (:func:`~setmem_hil.identification.algorithm.identify_outputs`). Returns the control output
    as a one-output result (the analysis, the H2 design and the input design use it; the other
    outputs have tightened its poles) and every output's model, for the next iteration."""
    from setmem_hil.identification.algorithm import identify_outputs

    datas = [FrequencyData.from_measurements(measured, output=k) for k in range(1 + len(measured[0].others))]
    priors = [procedure.prior if scales is None else measured_scale_prior(procedure.prior, scales[k]) for k in range(len(datas))]
    multi = identify_outputs(datas, priors, list(procedure.backend.output_order()), previous=previous,
                             settings=_identify_settings())
    models = list(multi.models) if previous is None else [m.intersect(p) for m, p in zip(multi.models, previous)]
    return multi.for_output(0), models


def sensors_document(procedure: Procedure, models, scales=None) -> dict:
    """The journal's ``iteration.outputs``: every output's bounds, control output first (the
    plant's: with calibration ``scales``, the residues widened by them)."""
    if scales is not None:
        models = [plant_bounds(m, scale) for m, scale in zip(models, scales)]
    return {"names": list(procedure.backend.output_order()), "lower": [m.lower.tolist() for m in models], "upper": [m.upper.tolist() for m in models]}


def goal_certified(outcome: SafeguardOutcome, goal) -> bool:
    """The stopping test of chapter 5: mu-bar below the goal *as certified on the whole
    frequency band* (issue 27), never on the grid's value alone."""
    return bool(outcome.certified_mu < goal.mu_target)


def controller_matrices(K) -> dict | None:
    """The compensator's ``A, B, C, D`` as lists (the journal's form; rad/s, ``u = K y``); None
    for an analysis without a state-space compensator (test doubles of the analysis)."""
    if not all(hasattr(K, name) for name in "ABCD"):
        return None
    return {name: np.atleast_2d(np.asarray(getattr(K, name), dtype=float)).tolist() for name in "ABCD"}


def measure_batch(source: _Replay, procedure: Procedure, omegas, *, iteration: int, role: str) -> list[Measurement]:
    """The frequencies one after the other (``[dwell] signal = "sine"``) or in one multisine record."""
    if procedure.dwell_signal == "multisine":
        return source.measure_record(omegas, iteration=iteration, role=role)
    return [source.measure(w, iteration=iteration, role=role) for w in omegas]


def _identify_settings(exact_resolve: bool = False):
    from setmem_hil.identification.algorithm import IdentifySettings

    if exact_resolve:
        return IdentifySettings(max_outer_iterations=EXACT_RESOLVE_OUTER_ITERATIONS)
    return IdentifySettings()


def next_frequency(
    strategy: str,
    k: int,
    n_added: int,
    procedure: Procedure,
    result,
    data: FrequencyData,
    outcome: SafeguardOutcome,
    experiment: Any,
    measured: list[Measurement],
    seed: int | None,
    sensor_models=None,
    left_out: tuple[tuple[float, float], ...] = (),
    floor_modes: tuple[int, ...] = (),
) -> InputChoice:
    """Algorithm 5.1 steps 5-7 for one strategy (see :mod:`setmem_hil.design.strategies`);
    ``sensor_models`` (several sensors): every output's model, so the exact re-solves predict
    every sensor's point (:class:`~setmem_hil.design.input_design.OtherOutputs`); ``left_out``:
    regions (rad/s) no candidate is taken from (:mod:`setmem_hil.design.unproductive_region`);
    ``floor_modes``: the floor's modes, whose removal ranks first (the ``"mu"`` strategy)."""
    settings = procedure.input_design.resolved(procedure.weights.reference_frequency_rad_s(), procedure.safety)
    empty = np.zeros(0)
    if strategy == "log-sweep":
        return InputChoice(log_sweep_frequency(n_added, settings), empty, empty, "sweep")
    if strategy == "random":
        return InputChoice(random_frequency(seed, k, settings), empty, empty, "random")
    model = result.model
    omega = candidate_frequencies(k, settings)
    omega = omega[outside_regions(omega, left_out)]
    R = candidate_noise_bound(experiment, omega, measured)
    cost = dwell_seconds(experiment, model, omega) if settings.ranking == "per_rig_second" else None
    if strategy == "mu":
        weights = sensitivity_matrix(outcome.analysis.sensitivities, model.n_modes)
        weights = np.where(model.fixed, 0.0, weights)
        if not np.any(weights > 0):  # no parameter limits mu (section 5.4.2): fall back to widths
            weights = uniform_weights(model)
        scoring = "mu"
    else:
        weights = uniform_weights(model)
        scoring = "max-reduction"
    return choose_input(
        result,
        data,
        procedure.prior,
        omega,
        R,
        weights,
        scoring=scoring,
        exact_resolve_top=settings.exact_resolve_top,
        identify_settings=_identify_settings(exact_resolve=True),
        cost_s=cost,
        other_outputs=None if sensor_models is None else other_outputs(procedure, measured, sensor_models, omega, R),
        floor_modes=floor_modes if strategy == "mu" else (),
    )


def other_outputs(procedure: Procedure, measured: list[Measurement], sensor_models, omega: np.ndarray, control_bound: np.ndarray):
    """Every sensor's data, model and expected bound at the candidates (issue 25): the control
    output's as for one sensor, each other output's interpolated from its own measured bounds
    (log-log, as :func:`candidate_noise_bound` does on a rig that cannot predict them)."""
    from setmem_hil.design.input_design import OtherOutputs

    outputs = range(len(sensor_models))
    datas = tuple(FrequencyData.from_measurements(measured, output=k) for k in outputs)
    bounds = (control_bound,) + tuple(candidate_noise_bound(None, omega, datas[k].measurements()) for k in outputs if k > 0)
    return OtherOutputs(datas, (procedure.prior,) * len(datas), tuple(procedure.backend.output_order()), tuple(sensor_models), bounds)


def dwell_seconds(experiment: Any, model, omega_rad_s: np.ndarray) -> np.ndarray:
    """Rig seconds a dwell at each frequency is expected to take: the experiment's own plan
    (:class:`~setmem_hil.model.experiment.PlanningExperiment`), else the sine dwell's plan with the
    current interval model (:func:`setmem_hil.estimation.dwell_estimate.plan_dwell`): the
    settling follows from the pole intervals, long near a lightly damped mode, short between modes."""
    from setmem_hil.estimation.dwell_estimate import DwellSettings, plan_dwell

    settings = DwellSettings()
    out = np.empty(np.size(omega_rad_s))
    for i, w in enumerate(np.atleast_1d(omega_rad_s)):
        plan = experiment.plan(float(w)) if isinstance(experiment, PlanningExperiment) else plan_dwell(settings, model, float(w))
        out[i] = plan.skip_s + plan.window_s
    return out


def batch_frequencies(first: float, strategy: str, k: int, n_added: int, procedure: Procedure, result, data: FrequencyData,
                      outcome: SafeguardOutcome, experiment: Any, measured: list[Measurement], seed: int | None, count: int,
                      left_out: tuple[tuple[float, float], ...] = ()) -> list[float]:
    """``count`` frequencies for one iteration (``[input_design] per_iteration``), ``first`` first.

    Each further choice is made on the data plus the frequencies already chosen, as the
    certainty-equivalent measurements eq. 4.53 predicts (the interval model's midpoint response
    with the bound expected there, widened when the midpoint response is not consistent with the
    data), re-identified: the effect of a frequency is re-estimated given the ones already in the
    batch, so their expected improvements do not overlap. A repeated choice ends the batch early.
    """
    from setmem_hil.identification.algorithm import identify

    from setmem_hil.errors import InconsistentDataError, SolverError

    chosen = [float(first)]
    model = result.model
    for j in range(1, count):
        w = np.array(chosen)
        trial, augmented = result, data
        if strategy in ("mu", "max-reduction"):
            # the midpoint response need not be feasible: widen the predicted points' bounds until
            # the data stay consistent (the choice then counts on less from them); give up after 4
            for widen in (1.0, 2.0, 4.0, 8.0):
                predicted = FrequencyData(w, model.midpoint.frequency_response(w), widen * candidate_noise_bound(experiment, w, measured))
                try:
                    with blas_one_thread():
                        trial = identify(data.appended(predicted), procedure.prior, previous=model, settings=_identify_settings())
                    augmented = data.appended(predicted)
                    break
                except (InconsistentDataError, SolverError):
                    continue
            else:
                break
        choice = next_frequency(strategy, k * 1000 + j if strategy == "random" else k, n_added + j, procedure, trial,
                                augmented, outcome, experiment, measured, seed, left_out=left_out)
        if any(math.isclose(choice.next_omega_rad_s, c, rel_tol=1e-9) for c in chosen):
            break
        chosen.append(float(choice.next_omega_rad_s))
    return chosen


def run_campaign(
    procedure: Procedure,
    experiment: Experiment,
    journal=None,
    *,
    seed: int | None = None,
    strategy: str | None = None,
    progress: ProgressFn | None = None,
    continue_stored: bool = False,
    control=None,
    design: str | None = None,
    floor_aware: bool | None = None,
) -> CampaignSummary:
    """Run Algorithm 5.1 on ``experiment`` until mu-bar < goal or the budget is spent.

    Parameters
    ----------
    procedure : Procedure
        Prior, initial frequencies, goal, input-design settings and weights.
    experiment : Experiment
        Anything with ``measure(omega)``; ``total_bound(omega)``, ``n_measured`` and
        ``update_model(model)`` (called after every identification) are used when present.
        Closing it is the caller's job.
    journal : setmem_hil.io.journal.Journal, optional
        Receives every measurement immediately and every iteration; an existing journal's
        contents are replayed (resume). ``finish(summary)`` is called at the end unless the run
        was already finished.
    seed : int, optional
        Seed of the random baseline (default ``procedure.seed``); the experiment's own noise seed
        is set where the experiment is built.
    strategy : str, optional
        Overrides ``procedure.input_design.strategy``: ``"mu"``, ``"log-sweep"``, ``"random"``,
        ``"max-reduction"``.
    progress : callable, optional
        ``progress(event, **info)`` with events ``"measure"`` (index, total, omega_rad_s,
        replayed), ``"iteration"`` (k, n_points, mu_peak, mu_peak_omega, safeguard, outputs: every
        sensor's bounds with several sensors, else None),
        ``"left-out"`` (k, region, message: a region left out of the candidates,
        :mod:`setmem_hil.design.unproductive_region`), ``"chosen"`` (k, next_omega) and
        ``"finished"`` (summary).
    continue_stored : bool, optional
        Continue a stopped run with a changed procedure (``run --resume DIR --procedure FILE``):
        every measurement stored in ``journal`` is data from the start (none is measured again,
        no replay check), iterations continue after the last stored one, and the bounds are not
        intersected with the old ones (the prior may have changed).
    control : setmem_hil.model.experiment.CampaignControl, optional
        ``checkpoint()`` before every new dwell (pause, abort; the live view).
    design : str, optional
        Overrides ``procedure.design_method``: ``"robust"`` (the compensator tuned to the mixed-mu
        bound, warm-started from the previous iteration's) or ``"h2"`` (the thesis).
    floor_aware : bool, optional
        Rank the candidates that remove a floor (:mod:`setmem_hil.model.mu_floor`) first; default:
        with the robust design only (``--design h2`` stays the thesis's loop, bit for bit).

    Returns
    -------
    CampaignSummary

    Raises
    ------
    setmem_hil.errors.InconsistentDataError
        When no parameters fit the data and the prior (logged to the journal first).
    CampaignReplayError
        When a resumed journal's measurements differ from what this procedure would measure.
    KeyboardInterrupt
        Propagates unchanged; every completed dwell is already in the journal.
    """
    from setmem_hil.errors import InconsistentDataError
    from setmem_hil.identification.algorithm import identify
    from setmem_hil.robust.analysis import ROBUST_CERTIFICATE_RTOL, analyze_robust_performance

    strategy = check_strategy(strategy or procedure.input_design.strategy)
    seed = procedure.seed if seed is None else int(seed)
    emit: ProgressFn = progress if progress is not None else (lambda event, **info: None)
    goal = procedure.goal
    t_start = time.perf_counter()

    stored_iterations = {}
    already_finished = False
    if journal is not None:
        stored_iterations = {rec.k: rec for rec in journal.iterations()}
        already_finished = bool(journal.run_info().get("finished"))
    total = len(procedure.initial_omegas_rad_s) + int(goal.max_experiments)
    source = _Replay(experiment, journal, emit, total, control)
    replayed_before = len(source.stored)

    # the sensors' calibration: one scale per output, on the residues (calibration_scale); the
    # analysis holds the control output's as one common gain on the plant
    scales = tuple(experiment.calibration_scales) if isinstance(experiment, CalibrationScaledExperiment) else None
    gain = None if scales is None else (1.0 / scales[0][1], 1.0 / scales[0][0])

    method = design or procedure.design_method
    floor_aware = (method == "robust") if floor_aware is None else bool(floor_aware)

    def robust_analysis(model, **options):
        return analyze_robust_performance(model, procedure.weights, gain=gain, certificate_rtol=ROBUST_CERTIFICATE_RTOL, **options)

    def analyze(model, controller):
        if method == "h2":
            return analyze_robust_performance(model, procedure.weights, controller=controller, gain=gain)
        if controller is not None:
            return robust_analysis(model, controller=controller)
        # the robust design starts from the H2 design or the compensator kept last, the better
        warm = None if previous_outcome is None else (previous_outcome.analysis.controller, rows[-1].design)
        return robust_analysis(model, design="robust", warm_start=warm)

    k, n_added = 1, 0
    if continue_stored and journal is not None:
        measured = list(source.stored)
        n_added = sum(1 for row in journal.measurement_rows() if row["role"] == "added")
        k = max(stored_iterations, default=0) + 1
        source.count = len(measured)
        source.stored, source._synced, replayed_before = [], True, len(measured)
        stored_iterations = {}
        if isinstance(experiment, ResumableExperiment):
            experiment.n_measured = len(measured)  # simulated noise goes on, never repeats
    else:
        measured = measure_batch(source, procedure, procedure.initial_omegas_rad_s, iteration=0, role="initial")
    previous_model = None
    previous_sensor_models = None
    plant_procedure = procedure
    if scales is not None:  # identification and input design work on the data as measured
        procedure = replace(procedure, prior=measured_scale_prior(procedure.prior, scales[0]))
    sensor_models = None
    previous_outcome: SafeguardOutcome | None = None
    rows: list[IterationSummary] = []
    # what each iteration's experiment was predicted to do and did (section 6.3.4's trap)
    outcomes: list[Outcome] = []
    left_out: list[tuple[float, float]] = []
    last_experiment: tuple[float | None, float] | None = None  # (frequency or None for several, predicted)
    while True:
        t_it, cpu_it = time.perf_counter(), time.process_time()
        data = FrequencyData.from_measurements(measured)
        try:
            with blas_one_thread():
                if measured[0].others:  # several sensors: shared poles, the control output's model drives the rest
                    result, sensor_models = identify_sensors(measured, plant_procedure, previous_sensor_models, scales)
                else:
                    result = identify(data, procedure.prior, previous=previous_model, settings=_identify_settings())
        except InconsistentDataError as exc:
            if journal is not None and k not in stored_iterations:
                journal.add_event("inconsistent-data", f"iteration {k}: {exc}")
            raise
        model = result.model if previous_model is None else result.model.intersect(previous_model)
        if isinstance(experiment, ModelAwareExperiment):  # later dwells model their transients with these poles
            experiment.update_model(model)
        if sensor_models is not None and isinstance(experiment, OutputModelsAwareExperiment):
            experiment.update_output_models(sensor_models)
        with blas_one_thread():
            outcome = safeguarded_design(model, previous_outcome, analyze)
            previous_design = rows[-1].design if rows else "h2"
            if method == "robust" and goal_certified(outcome, goal):  # the delivered compensator: more margin
                outcome = polished(outcome, lambda box, warm: robust_analysis(box, design="robust", warm_start=warm,
                                                                               tuning=FINAL_TUNING), previous_design)
        plant = model if scales is None else plant_bounds(model, scales[0])  # its interval hull, for the journal
        analysis = outcome.analysis
        kept_design = kept_design_of(outcome, previous_design)
        floor = floor_modes(model)
        emit("iteration", k=k, n_points=len(measured), mu_peak=outcome.mu_peak,
             mu_peak_omega=float(analysis.mu_peak_omega), safeguard=outcome.branch, design=kept_design, floor_modes=floor,
             rig_s=float(sum(m.rig_s for m in measured)), mu_peak_certified=outcome.certified,
             outputs=None if sensor_models is None else sensors_document(procedure, sensor_models, scales))
        if last_experiment is not None and previous_outcome is not None:
            outcomes.append(Outcome(last_experiment[0], last_experiment[1], previous_outcome.mu_peak - outcome.mu_peak))
            region = unproductive_region(outcomes)
            if region is not None:
                left_out.append(region)
                message = f"iteration {k}: {describe(region, outcomes[-RUN:])}"
                if journal is not None and k not in stored_iterations:
                    journal.add_event(UNPRODUCTIVE_REGION_EVENT, message)
                emit("left-out", k=k, region=region, message=message)
                outcomes.clear()
        reached = goal_certified(outcome, goal)
        certified_intervals = int(getattr(analysis, "mu_certified_intervals", 0))
        budget_spent = n_added >= goal.max_experiments
        choice: InputChoice | None = None
        if not (reached or budget_spent):
            with blas_one_thread():
                choice = next_frequency(strategy, k, n_added, procedure, result, data, outcome, experiment, measured, seed,
                                        sensor_models=sensor_models, left_out=tuple(left_out),
                                        floor_modes=floor if floor_aware else ())
        next_omega = None if choice is None else choice.next_omega_rad_s
        compute_s = time.perf_counter() - t_it
        compute_cpu_s = time.process_time() - cpu_it

        if journal is not None:
            stored = stored_iterations.get(k)
            if stored is None:
                from setmem_hil.io.journal import IterationRecord

                journal.add_iteration(IterationRecord(
                    k=k,
                    n_points=len(measured),
                    lower=plant.lower,
                    upper=plant.upper,
                    mu_peak=float(outcome.mu_peak),
                    mu_peak_omega=float(analysis.mu_peak_omega),
                    mu_lower_peak=float(analysis.mu_lower_peak),
                    omega=np.asarray(analysis.omega, dtype=float),
                    mu=np.asarray(analysis.mu, dtype=float),
                    sensitivities={str(key): float(v) for key, v in analysis.sensitivities.items()},
                    next_omega=next_omega,
                    candidate_omega=np.zeros(0) if choice is None else choice.candidate_omega_rad_s,
                    estimated_improvement=np.zeros(0) if choice is None else choice.estimated_improvement,
                    controller_order=int(analysis.controller_order),
                    safeguard=outcome.branch,
                    wall_s=float(compute_s),
                    embedding_gamma=np.asarray(result.embedding_gamma, dtype=float),
                    mismatch_ratio=np.asarray(result.mismatch_ratio, dtype=float),
                    controller=controller_matrices(analysis.controller),
                    mu_peak_certified=bool(outcome.certified),
                    mu_certified_intervals=certified_intervals,
                    outputs=None if sensor_models is None else sensors_document(procedure, sensor_models, scales),
                    common_gain=None if gain is None else {"gain": list(gain), "lower": model.lower.tolist(), "upper": model.upper.tolist()},
                    design=kept_design,
                    floor_modes=floor,
                ))
                if floor:
                    journal.add_event(FLOOR_EVENT, f"iteration {k}: {floor_message(floor)}")
                if choice is not None and np.size(choice.resolved_omega_rad_s):
                    import json

                    journal.add_event(EXACT_RESOLVE_EVENT, json.dumps({
                        "k": k, "omega_rad_s": [float(w) for w in choice.resolved_omega_rad_s],
                        "improvement": [None if not math.isfinite(v) else float(v) for v in choice.resolved_improvement]}))
                if outcome.branch != "new-design":
                    tried = ", ".join(f"{b} {v:.4f}" for b, v in outcome.tried.items())
                    journal.add_event("safeguard", f"iteration {k}: eq. 5.12 branch {outcome.branch} (mu-bar {tried})")
            elif not _same_choice(stored.next_omega, next_omega):
                raise CampaignReplayError(
                    str(getattr(journal, "path", "journal")), f"iteration {k}",
                    f"stored next frequency {stored.next_omega} rad/s but the replay chose {next_omega} rad/s",
                )
        rows.append(IterationSummary(
            k=k, n_points=len(measured), mu_peak=float(outcome.mu_peak), mu_peak_omega=float(analysis.mu_peak_omega),
            next_omega=next_omega, safeguard=outcome.branch, basis="" if choice is None else choice.basis,
            compute_s=float(compute_s), compute_cpu_s=float(compute_cpu_s), mu_peak_certified=bool(outcome.certified),
            mu_certified_intervals=certified_intervals, design=kept_design, floor_modes=floor,
        ))
        if choice is None:
            break
        batch = [next_omega]
        per_iteration = min(procedure.input_design.per_iteration, goal.max_experiments - n_added)
        if per_iteration > 1:
            batch = batch_frequencies(next_omega, strategy, k, n_added, procedure, result, data, outcome, experiment,
                                      measured, seed, per_iteration, tuple(left_out))
            if journal is not None and k not in stored_iterations and len(batch) > 1:
                journal.add_event(BATCH_EVENT, f"iteration {k}: " + ", ".join(f"{w:.9g}" for w in batch) + " rad/s")
        last_experiment = (batch[0] if len(batch) == 1 else None, predicted_improvement(choice))
        for w in batch:
            emit("chosen", k=k, next_omega=w)
        added = measure_batch(source, procedure, batch, iteration=k, role="added")
        measured.extend(added)
        n_added += len(added)
        rows[-1] = replace(rows[-1], rig_s=float(sum(m.rig_s for m in added)))
        previous_model, previous_outcome = model, outcome
        previous_sensor_models = sensor_models
        k += 1

    summary = CampaignSummary(
        reached_goal=bool(reached),
        final_mu_peak=rows[-1].mu_peak,
        experiments_added=n_added,
        wall_s=time.perf_counter() - t_start,
        iterations=tuple(rows),
        strategy=strategy,
        seed=seed,
        goal_mu=float(goal.mu_target),
        max_experiments=int(goal.max_experiments),
        stop_reason="goal" if reached else "budget",
        replayed_measurements=min(replayed_before, source.count),
        rig_s=float(sum(m.rig_s for m in measured)),
    )
    if journal is not None and not already_finished:
        journal.finish(summary.to_document())
    emit("finished", summary=summary)
    return summary


FLOOR_EVENT = "floor"
"""Journal event of an iteration whose box blocks every compensator (:mod:`setmem_hil.model.mu_floor`)."""


def polished(outcome: SafeguardOutcome, tune, previous_design: str) -> SafeguardOutcome:
    """The goal is reached: tune the kept compensator further on the box it was analysed on
    (``tune(box, warm_start)``) and keep the result only if its certified mu-bar is lower."""
    analysis = tune(outcome.analysis_model, (outcome.analysis.controller, kept_design_of(outcome, previous_design)))
    if not certified_value(analysis) < outcome.certified_mu:
        return outcome
    branch = "new-design" if outcome.branch == "new-design" else "expanded"
    tried = {**outcome.tried, "final-tuning": float(analysis.mu_peak)}
    return replace(outcome, analysis=analysis, branch=branch, mu_peak=float(analysis.mu_peak), tried=tried,
                   certified_mu=certified_value(analysis))


def kept_design_of(outcome: SafeguardOutcome, previous_design: str) -> str:
    """The design that made the compensator eq. 5.12 kept: the previous one's when it kept that."""
    if outcome.branch == "previous-controller":
        return previous_design
    return "robust" if getattr(outcome.analysis, "design", "h2") == "robust" else "h2"


UNPRODUCTIVE_REGION_EVENT = "left-out"
"""Journal event of a frequency region left out of the candidates (:mod:`setmem_hil.design.unproductive_region`)."""

BATCH_EVENT = "batch"
"""Journal event of an iteration that chose several frequencies (``[input_design] per_iteration``)."""


def _same_choice(a: float | None, b: float | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)


__all__ = [
    "CampaignReplayError",
    "CampaignSummary",
    "EXACT_RESOLVE_OUTER_ITERATIONS",
    "IterationSummary",
    "candidate_noise_bound",
    "kept_design_of",
    "next_frequency",
    "run_campaign",
]
