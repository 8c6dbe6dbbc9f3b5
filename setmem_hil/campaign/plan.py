"""Thesis Algorithm 5.1 as a plan: the iterative identification / control / experiment loop.

:func:`thesis_plan` is a generator of requests (:mod:`setmem_hil.campaign.messages`) that an
engine performs (:class:`setmem_hil.run.engine.RunEngine`); it holds no journal, replay,
resume or live-view code. It measures the procedure's initial frequencies, then repeats:

2. identify the parameter intervals from all data so far, never loosening the previous bounds
   (eq. 5.4-5.5; the result is also intersected with them);
3. design the compensator (H2, or tuned to the mixed-mu bound: ``[design] method``) and compute
   mu-bar with the monotone safeguard (eq. 5.8-5.12, :mod:`setmem_hil.design.safeguard`), so
   the reported mu-bar never increases;
4. stop when mu-bar, certified on the whole band, is below the goal, or when the experiment
   budget is spent;
5-7. choose the next frequency with the procedure's strategy (:mod:`setmem_hil.campaign.next_input`;
   ``"mu"`` is eq. 5.3 via :func:`setmem_hil.design.input_design.choose_input`), measure it, and go on.

**A region that keeps disappointing** (section 6.3.4's trap): after three consecutive
single-frequency iterations in one region that each lowered mu-bar by less than a quarter of
the improvement predicted for them, that region is left out of the candidates for the rest of
the campaign (:mod:`setmem_hil.design.unproductive_region`; event ``left-out``). It depends only
on the mu-bar values and choices, so a replay leaves out the same regions.

**Model hook.** After every identification the plan hands the iteration's interval model to the
experiment (:class:`~setmem_hil.campaign.messages.InformModel`), so later dwells fit their
transients with the narrowed poles. A replay repeats the same identifications in the same order:
the experiment is in the same state at the first new dwell as in an uninterrupted run.

**Pause points.** The plan declares them (:class:`~setmem_hil.run.engine.Checkpoint`): before
every dwell, and before a multisine record. The engine runs the plan's numerics with
single-threaded BLAS (its ``compute``). Nothing the loop chooses depends on the wall clock or a
global RNG.

The experiment is only read here (its calibration scales, predicted bounds and dwell plans);
everything that acts on it goes through the engine.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from typing import Any, Generator

import numpy as np

from setmem_hil.campaign.loop_steps import goal_certified, identify_sensors, kept_design_of, polished, sensors_document
from setmem_hil.campaign.messages import ITERATION_RECORD, NOTE, Checkpoint, Emit, InformModel, Measure, StoredData
from setmem_hil.campaign.next_input import batch_frequencies, identify_settings, next_frequency
from setmem_hil.campaign.summary import CampaignSummary, IterationSummary
from setmem_hil.design.input_design import InputChoice
from setmem_hil.design.safeguard import SafeguardOutcome, safeguarded_design
from setmem_hil.design.strategies import check_strategy
from setmem_hil.design.unproductive_region import RUN, Outcome, describe, predicted_improvement, unproductive_region
from setmem_hil.errors import InconsistentDataError
from setmem_hil.identification.calibration_scale import measured_scale_prior, plant_bounds
from setmem_hil.io.procedure import Procedure
from setmem_hil.model.experiment import CalibrationScaledExperiment, Measurement
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.mu_floor import floor_modes, floor_sentence
from setmem_hil.robust.robust_design import FINAL_TUNING

__all__ = ["thesis_plan", "EXACT_RESOLVE_EVENT", "FLOOR_EVENT", "UNPRODUCTIVE_REGION_EVENT", "BATCH_EVENT", "WITNESS_EVENT"]

EXACT_RESOLVE_EVENT = "exact-resolve"
"""Event holding, as JSON, the candidates re-identified exactly at an iteration and their
improvement (the choice is the best of these; the report's figure 6-14 shows them)."""
FLOOR_EVENT = "floor"
"""Event of an iteration whose box blocks every compensator (:mod:`setmem_hil.model.mu_floor`)."""
WITNESS_EVENT = "witness"
"""Event holding, as JSON, the iteration's witness (issue 62): ``{"k", "fits", "misfit",
"reach_ratio_max", "reach_ratio_per_mode", "shaved_slabs"}``, and a ``warning`` where no parameter point of the box was
found to fit every point (its modes are then not verified)."""
UNPRODUCTIVE_REGION_EVENT = "left-out"
"""Event of a frequency region left out of the candidates (:mod:`setmem_hil.design.unproductive_region`)."""
BOX_UNCHANGED_RTOL = 1e-6
"""An iteration whose box moved less than this (relative to each interval's width) keeps the
compensator without tuning it again (the robust design only; :func:`_box_unchanged`)."""
BATCH_EVENT = "batch"
"""Event of an iteration that chose several frequencies (``[input_design] per_iteration``)."""


def thesis_plan(procedure: Procedure, experiment: Any, *, seed: int | None = None, strategy: str | None = None,
                design: str | None = None, floor_aware: bool | None = None) -> Generator[Any, Any, CampaignSummary]:
    """Algorithm 5.1 until mu-bar < goal or the budget is spent (see the module docstring).

    ``strategy`` and ``design`` override the procedure's; ``floor_aware`` ranks the candidates
    that remove a floor first (default: with the robust design only, so ``--design h2`` stays the
    thesis's loop bit for bit)."""
    loop = LoopSettings.of(procedure, experiment, seed, strategy, design, floor_aware)
    state = yield from _starting_data(loop)  # step 1: the initial experiments
    while True:
        step = yield from _identify(loop, state)  # step 2: eq. 5.4-5.5
        outcome, kept = _design_and_analyse(loop, state, step.model)  # step 3: eq. 5.8-5.12
        yield from _announce(loop, state, step, outcome, kept)
        yield from _leave_out_unproductive_region(state, outcome)  # section 6.3.4's trap
        state.reached = goal_certified(outcome, loop.procedure.goal)  # step 4: stop?
        spent = state.n_added >= loop.procedure.goal.max_experiments
        choice = None if state.reached or spent else _choose(loop, state, step, outcome)  # steps 5-6
        yield from _record(loop, state, step, outcome, kept, choice)
        if choice is None:
            return _summary(loop, state)
        yield from _measure_choice(loop, state, step, outcome, choice)  # step 7


@dataclass(frozen=True)
class LoopSettings:
    """What stays fixed through the loop. ``procedure`` is the one the data are identified with
    (with calibration scales: the prior in the sensors' scale); ``plant_procedure`` as given."""

    procedure: Procedure
    plant_procedure: Procedure
    experiment: Any
    seed: int
    strategy: str
    method: str
    floor_aware: bool
    scales: tuple | None
    gain: tuple[float, float] | None

    @classmethod
    def of(cls, procedure: Procedure, experiment: Any, seed, strategy, design, floor_aware) -> "LoopSettings":
        # the sensors' calibration: one scale per output, on the residues (calibration_scale); the
        # analysis holds the control output's as one common gain on the plant
        scales = tuple(experiment.calibration_scales) if isinstance(experiment, CalibrationScaledExperiment) else None
        method = design or procedure.design_method
        measured_procedure = procedure if scales is None else replace(procedure, prior=measured_scale_prior(procedure.prior, scales[0]))
        return cls(measured_procedure, procedure, experiment, procedure.seed if seed is None else int(seed),
                   check_strategy(strategy or procedure.input_design.strategy), method,
                   (method == "robust") if floor_aware is None else bool(floor_aware),
                   scales, None if scales is None else (1.0 / scales[0][1], 1.0 / scales[0][0]))

    def robust_analysis(self, model, **options):
        from setmem_hil.robust.analysis import ROBUST_CERTIFICATE_RTOL, analyze_robust_performance

        return analyze_robust_performance(model, self.procedure.weights, gain=self.gain, certificate_rtol=ROBUST_CERTIFICATE_RTOL, **options)

    def analyzer(self, state: "LoopState"):
        """``analyze(model, controller)`` for the safeguard: the thesis's H2 design, or the robust
        design warm-started from the H2 design or the compensator kept last, the better."""
        from setmem_hil.robust.analysis import analyze_robust_performance

        def analyze(model, controller):
            if self.method == "h2":
                return analyze_robust_performance(model, self.procedure.weights, controller=controller, gain=self.gain)
            if controller is not None:
                return self.robust_analysis(model, controller=controller)
            previous = state.previous_outcome
            warm = None if previous is None else (previous.analysis.controller, state.rows[-1].design)
            return self.robust_analysis(model, design="robust", warm_start=warm)

        return analyze


@dataclass
class LoopState:
    """What the loop carries from one iteration to the next."""

    measured: list[Measurement]
    k: int = 1
    n_added: int = 0
    reached: bool = False
    previous_model: Any = None
    previous_sensor_models: Any = None
    previous_outcome: SafeguardOutcome | None = None
    rows: list[IterationSummary] = field(default_factory=list)
    outcomes: list[Outcome] = field(default_factory=list)  # predicted and achieved (section 6.3.4's trap)
    left_out: list[tuple[float, float]] = field(default_factory=list)
    last_experiment: tuple[float | None, float] | None = None  # (frequency, or None for several; predicted)


@dataclass(frozen=True)
class Identified:
    """Step 2's result: the identification, the intersected model, every output's model."""

    result: Any
    model: Any
    sensor_models: Any
    data: FrequencyData
    floor: tuple[int, ...]  # modes whose box blocks every compensator (setmem_hil.model.mu_floor)
    floor_evidence: tuple = ()  # per floor mode, whether the data hold it (identification.floor_evidence)


def measure_points(procedure: Procedure, omegas, iteration: int, role: str, done: int):
    """The frequencies one after the other (``[dwell] signal = "sine"``), each after a pause point,
    or in one multisine record after one; ``done`` measurements were taken before."""
    request = Measure(tuple(float(w) for w in omegas), iteration, role, record=procedure.dwell_signal == "multisine")
    if request.record and len(request.omegas_rad_s) > 1:
        yield Checkpoint(f"measurement {done + 1}")
        return list((yield request))
    measured: list[Measurement] = []
    for w in request.omegas_rad_s:
        yield Checkpoint(f"measurement {done + len(measured) + 1}")
        measured += yield replace(request, omegas_rad_s=(w,))
    return measured


def _document(name: str, info: dict, k: int, **check) -> Emit:
    """A document of iteration ``k``: a replay marks it (stored already) and checks ``check``."""
    return Emit(name, info, key=("iteration", k), check=check)


def _starting_data(loop: LoopSettings):
    stored = yield StoredData()
    if stored is not None:  # a stopped run continued with a changed procedure: its data from the start
        return LoopState(list(stored.measured), k=stored.next_iteration, n_added=stored.n_added)
    measured = yield from measure_points(loop.procedure, loop.procedure.initial_omegas_rad_s, 0, "initial", 0)
    return LoopState(list(measured))


def _identify(loop: LoopSettings, state: LoopState):
    data = FrequencyData.from_measurements(state.measured)
    sensor_models = None
    try:
        if state.measured[0].others:  # several sensors: shared poles, the control output's model drives the rest
            result, sensor_models = identify_sensors(state.measured, loop.plant_procedure, state.previous_sensor_models, loop.scales)
        else:
            from setmem_hil.identification.algorithm import identify

            result = identify(data, loop.procedure.prior, previous=state.previous_model, settings=identify_settings())
    except InconsistentDataError as exc:
        yield _document(NOTE, {"kind": "inconsistent-data", "message": f"iteration {state.k}: {exc}"}, state.k)
        raise
    witness = getattr(result, "witness", None)
    if witness is not None:
        yield _document(NOTE, {"kind": WITNESS_EVENT, "message": _witness_message(state.k, result)}, state.k)
    model = result.model if state.previous_model is None else result.model.intersect(state.previous_model)
    yield InformModel(model, sensor_models)  # later dwells model their transients with these poles
    floor = floor_modes(model)
    return Identified(result, model, sensor_models, data, floor, _floor_evidence(floor, data, model, result, sensor_models))


def _floor_sentences(step: Identified) -> list[str]:
    """The floor's sentences, each with the data's verdict where it was checked."""
    if step.floor_evidence:
        return [e.sentence() for e in step.floor_evidence]
    return [floor_sentence(m) for m in step.floor]


def _floor_evidence(floor: tuple[int, ...], data: FrequencyData, model, result, sensor_models) -> tuple:
    """Each floor mode checked against the data (one output; with several sensors the floor plant
    must fit every output at once, which is not built: no verdict, the sentence as before)."""
    if not floor or sensor_models is not None:
        return ()
    from setmem_hil.identification.floor_evidence import floor_evidence

    residuals = getattr(result, "residuals", None) or {}
    return tuple(floor_evidence(data.omega_rad_s, data.response, data.bound, model.lower, model.upper, mode, residuals)
                 for mode in floor)


def _witness_message(k: int, result) -> str:
    """The witness note's message: JSON, with a sentence where no point was found to fit."""
    ratios = result.reach_ratio
    doc = {"k": k, "fits": result.witness.fits, "misfit": round(float(result.witness.misfit), 6),
           "reach_ratio_max": None if ratios is None or not np.isfinite(ratios).any() else round(float(np.nanmax(ratios)), 4),
           "reach_ratio_per_mode": _per_mode_widest(ratios),
           "shaved_slabs": None if result.shaved is None else result.shaved.slabs}
    if not result.witness.fits:
        doc["warning"] = f"iteration {k}: no parameter point of the box was found to fit every point: {result.witness.describe_misfit()}"
    return json.dumps(doc)


def _per_mode_widest(ratios) -> list | None:
    """Each mode's widest interval over the witnesses' reach (None for a mode with no finite
    ratio: every parameter fixed). An upper bound of the ratio to the exact set (issue 62 item 6)."""
    if ratios is None:
        return None
    rows = np.atleast_2d(np.asarray(ratios, dtype=float))
    return [None if not np.isfinite(row).any() else round(float(np.nanmax(row)), 4) for row in rows]


def _design_and_analyse(loop: LoopSettings, state: LoopState, model) -> tuple[SafeguardOutcome, str]:
    previous_design = state.rows[-1].design if state.rows else "h2"
    if _box_unchanged(loop, state, model):
        return replace(state.previous_outcome, branch="previous-controller", tried={"box unchanged, kept": state.previous_outcome.mu_peak}), \
            previous_design
    outcome = safeguarded_design(model, state.previous_outcome, loop.analyzer(state))
    if loop.method == "robust" and goal_certified(outcome, loop.procedure.goal):  # the delivered compensator: more margin
        outcome = polished(outcome, lambda box, warm: loop.robust_analysis(box, design="robust", warm_start=warm, tuning=FINAL_TUNING),
                           previous_design)
    return outcome, kept_design_of(outcome, previous_design)


def _box_unchanged(loop: LoopSettings, state: LoopState, model) -> bool:
    """The robust design only: an experiment that moved no interval endpoint by more than
    :data:`BOX_UNCHANGED_RTOL` of its width keeps the compensator and its certified mu-bar
    without tuning again (20 s of tuning for nothing, iteration after iteration, when a strategy
    measures where nothing is learnt). Still guaranteed: the new box lies inside the previous one
    (the bounds are intersected), so the previous bound holds for every plant of it. The H2 loop
    stays the thesis's, bit for bit."""
    previous = state.previous_model
    if loop.method != "robust" or state.previous_outcome is None or previous is None or state.measured[0].others:
        return False
    width = np.maximum(previous.upper - previous.lower, np.finfo(float).tiny)
    moved = np.maximum(np.abs(model.lower - previous.lower), np.abs(model.upper - previous.upper)) / width
    return bool(np.all(moved <= BOX_UNCHANGED_RTOL))


def _outputs_document(loop: LoopSettings, step: Identified):
    return None if step.sensor_models is None else sensors_document(loop.procedure, step.sensor_models, loop.scales)


def _announce(loop: LoopSettings, state: LoopState, step: Identified, outcome: SafeguardOutcome, kept: str):
    """The iteration's document (before the choice, which takes a while): what it found, for the
    displays, and the objects the stores lay out (the plant's bounds: with calibration scales, the
    model's interval hull widened by them)."""
    plant = step.model if loop.scales is None else plant_bounds(step.model, loop.scales[0])
    yield Emit("iteration", dict(k=state.k, n_points=len(state.measured), mu_peak=outcome.mu_peak,
                                 mu_peak_omega=float(outcome.analysis.mu_peak_omega), safeguard=outcome.branch, design=kept,
                                 floor_modes=step.floor, floor_sentences=_floor_sentences(step), rig_s=float(sum(m.rig_s for m in state.measured)),
                                 mu_peak_certified=outcome.certified, outputs=_outputs_document(loop, step),
                                 identification=step.result, data=step.data, model=step.model, plant=plant, gain=loop.gain,
                                 analysis=outcome.analysis))


def _leave_out_unproductive_region(state: LoopState, outcome: SafeguardOutcome):
    """Section 6.3.4's trap: after ``RUN`` disappointing single-frequency experiments in one region,
    that region is left out of the candidates from now on (it changes later choices)."""
    if state.last_experiment is None or state.previous_outcome is None:
        return
    state.outcomes.append(Outcome(state.last_experiment[0], state.last_experiment[1], state.previous_outcome.mu_peak - outcome.mu_peak))
    region = unproductive_region(state.outcomes)
    if region is not None:
        state.left_out.append(region)
        message = f"iteration {state.k}: {describe(region, state.outcomes[-RUN:])}"
        yield _document(NOTE, {"kind": UNPRODUCTIVE_REGION_EVENT, "message": message, "k": state.k, "region": region}, state.k)
        state.outcomes.clear()


def _choose(loop: LoopSettings, state: LoopState, step: Identified, outcome: SafeguardOutcome) -> InputChoice:
    floor = step.floor if loop.floor_aware else ()
    return next_frequency(loop.strategy, state.k, state.n_added, loop.procedure, step.result, step.data, outcome, loop.experiment,
                          state.measured, loop.seed, sensor_models=step.sensor_models, left_out=tuple(state.left_out),
                          floor_modes=floor)


def _record(loop: LoopSettings, state: LoopState, step: Identified, outcome: SafeguardOutcome, kept: str, choice: InputChoice | None):
    """The iteration's choice (the stores pair it with the iteration's document), its notes, and
    its row of the summary."""
    k, analysis, floor = state.k, outcome.analysis, step.floor
    next_omega = None if choice is None else choice.next_omega_rad_s
    yield _document(ITERATION_RECORD, {"k": k, "choice": choice}, k, next_omega=next_omega)
    if floor:
        yield _document(NOTE, {"kind": FLOOR_EVENT, "message": f"iteration {k}: {'; '.join(_floor_sentences(step))}"}, k)
    if choice is not None and np.size(choice.resolved_omega_rad_s):
        resolved = {"k": k, "omega_rad_s": [float(w) for w in choice.resolved_omega_rad_s],
                    "improvement": [None if not math.isfinite(v) else float(v) for v in choice.resolved_improvement]}
        yield _document(NOTE, {"kind": EXACT_RESOLVE_EVENT, "message": json.dumps(resolved)}, k)
    if outcome.branch != "new-design":
        tried = ", ".join(f"{b} {v:.4f}" for b, v in outcome.tried.items())
        yield _document(NOTE, {"kind": "safeguard", "message": f"iteration {k}: eq. 5.12 branch {outcome.branch} (mu-bar {tried})"}, k)
    state.rows.append(IterationSummary(  # its compute time is the engine's clock (the runner fills it in)
        k=k, n_points=len(state.measured), mu_peak=float(outcome.mu_peak), mu_peak_omega=float(analysis.mu_peak_omega),
        next_omega=next_omega, safeguard=outcome.branch, basis="" if choice is None else choice.basis,
        mu_peak_certified=bool(outcome.certified), mu_certified_intervals=int(getattr(analysis, "mu_certified_intervals", 0)),
        design=kept, floor_modes=floor, certified_mu=float(outcome.certified_mu),
    ))


def _measure_choice(loop: LoopSettings, state: LoopState, step: Identified, outcome: SafeguardOutcome, choice: InputChoice):
    """Step 7: measure the chosen frequency (with ``per_iteration``, several), then go on."""
    p, k = loop.procedure, state.k
    batch = [choice.next_omega_rad_s]
    per_iteration = min(p.input_design.per_iteration, p.goal.max_experiments - state.n_added)
    if per_iteration > 1:
        batch = batch_frequencies(batch[0], loop.strategy, k, state.n_added, p, step.result, step.data, outcome, loop.experiment,
                                  state.measured, loop.seed, per_iteration, tuple(state.left_out))
        if len(batch) > 1:
            yield _document(NOTE, {"kind": BATCH_EVENT, "message": f"iteration {k}: " + ", ".join(f"{w:.9g}" for w in batch) + " rad/s"}, k)
    state.last_experiment = (batch[0] if len(batch) == 1 else None, predicted_improvement(choice))
    for w in batch:
        yield Emit("chosen", {"k": k, "next_omega": w})
    added = yield from measure_points(p, batch, k, "added", len(state.measured))
    state.measured.extend(added)
    state.n_added += len(added)
    state.rows[-1] = replace(state.rows[-1], rig_s=float(sum(m.rig_s for m in added)))
    state.previous_model, state.previous_outcome, state.previous_sensor_models = step.model, outcome, step.sensor_models
    state.k += 1


def _summary(loop: LoopSettings, state: LoopState) -> CampaignSummary:
    """The campaign's summary (its clocks are the engine's: the runner fills them in)."""
    goal = loop.procedure.goal
    return CampaignSummary(
        reached_goal=bool(state.reached), final_mu_peak=state.rows[-1].mu_peak, experiments_added=state.n_added,
        iterations=tuple(state.rows), strategy=loop.strategy, seed=loop.seed,
        goal_mu=float(goal.mu_target), max_experiments=int(goal.max_experiments), stop_reason="goal" if state.reached else "budget",
        rig_s=float(sum(m.rig_s for m in state.measured)),
    )
