"""Run a campaign: thesis Algorithm 5.1 (:mod:`setmem_hil.campaign.plan`) on the run engine
(:mod:`setmem_hil.run.engine`), stored by its subscribers (:mod:`setmem_hil.campaign.persistence`).

**Journal and resume (REPLAY).** Every measurement is written to the journal as soon as it is
taken (its raw record to ``raw.h5`` just before), every iteration's bounds, mu-bar,
sensitivities and candidate scores after it is computed. A campaign resumed from its journal
reruns the plan from the start: the engine serves each stored measurement instead of measuring
it again (its frequency must match: otherwise :class:`CampaignReplayError`) and checks each
stored iteration's choice; nothing stored is added twice. Before the first new dwell the
experiment's ``n_measured`` (if it has one) is set to the number of stored measurements, so the
simulated noise continues exactly. The same seed gives the same measurements and choices
serially, resumed or on Dask workers.

The names other modules import from here (the loop's pieces) are re-exported.
"""

from __future__ import annotations

import os
from dataclasses import replace
from typing import Callable

from setmem_hil.run.engine import Emit, RunEngine, RunStart
from setmem_hil.campaign.measurement_service import MeasurementService, register_measurements, stored_iterations
from setmem_hil.campaign.persistence import IterationClock, JournalWriter, RawRecordWriter
from setmem_hil.campaign.summary import CampaignSummary
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import Procedure
from setmem_hil.model.experiment import Experiment, OutputConfirmingExperiment

# The loop's pieces other modules import from here, loaded when first asked for: the run's journal
# is made from its ``start`` document, which must not wait for the loop's numerics to load.
_REEXPORTED = {
    "setmem_hil.campaign.loop_steps": ("controller_matrices", "goal_certified", "identify_sensors", "kept_design_of", "polished",
                                       "sensors_document"),
    "setmem_hil.campaign.next_input": ("EXACT_RESOLVE_OUTER_ITERATIONS", "batch_frequencies", "candidate_noise_bound", "dwell_seconds",
                                       "next_frequency", "other_outputs"),
    "setmem_hil.campaign.plan": ("BATCH_EVENT", "EXACT_RESOLVE_EVENT", "FLOOR_EVENT", "UNPRODUCTIVE_REGION_EVENT", "WITNESS_EVENT"),
    "setmem_hil.campaign.summary": ("IterationSummary",),
    "setmem_hil.errors": ("CampaignReplayError",),
}


def __getattr__(name: str):
    import importlib

    for module, names in _REEXPORTED.items():
        if name in names:
            return getattr(importlib.import_module(module), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


ProgressFn = Callable[..., None]


def run_campaign(
    procedure: Procedure,
    experiment: Experiment,
    journal: Journal | JournalWriter | str | os.PathLike | None = None,
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
    journal : Journal, path or JournalWriter, optional
        Receives every measurement immediately and every iteration (its raw records go to
        ``raw.h5`` beside it), written from the run's documents
        (:class:`~setmem_hil.campaign.persistence.JournalWriter`). An open journal's contents are
        replayed (resume) and it stays open; a path makes a new journal from the run's ``start``
        document, closed when the run ends. ``finish(summary)`` is called at the end unless the
        run was already finished.
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
        ``"note"`` (kind, message; kind ``"left-out"`` also k and region: a region left out of the
        candidates, :mod:`setmem_hil.design.unproductive_region`), ``"chosen"`` (k, next_omega) and
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
    writer = journal if isinstance(journal, JournalWriter) or journal is None else JournalWriter(journal)
    clock = writer.clock if writer is not None else IterationClock()  # the writer feeds its clock
    subscribers: list = [clock] if writer is None else [RawRecordWriter(writer.run_dir), writer]  # the stores first
    if progress is not None:
        subscribers.append(progress)
    history = None if writer is None else writer.journal  # a resumed run's journal; None for a new one
    planned = procedure.max_measurements
    engine = RunEngine(subscribers, control=control, stored={} if continue_stored else stored_iterations(history),
                       make_safe=_confirm_output_off(experiment), safe_state="every exciter output confirmed off",
                       source=str(writer.path) if writer is not None else "journal")
    service = register_measurements(engine, MeasurementService(experiment, history=history, total=planned, continue_stored=continue_stored))
    plan = _thesis_plan(procedure, experiment, seed=seed, strategy=strategy, design=design, floor_aware=floor_aware)
    arguments = dict(procedure=procedure.name, strategy=strategy or procedure.input_design.strategy,
                     design=design or procedure.design_method, floor_aware=floor_aware, continue_stored=continue_stored,
                     backend=procedure.backend.kind, procedure_text=_procedure_text(procedure))
    try:
        return engine.run(_finished(plan, service, engine, clock), RunStart("thesis-algorithm-5.1", arguments,
                                                                             procedure.seed if seed is None else int(seed), planned))
    finally:
        if writer is not None and not isinstance(journal, (Journal, JournalWriter)):  # made here from a path: closed here
            writer.close()


def _thesis_plan(procedure: Procedure, experiment: Experiment, **options):
    """Algorithm 5.1 (:func:`setmem_hil.campaign.plan.thesis_plan`), its numerics loaded once the
    run has started (after its ``start`` document: the journal exists within a second)."""
    from setmem_hil.campaign.plan import thesis_plan

    return (yield from thesis_plan(procedure, experiment, **options))


def _procedure_text(procedure: Procedure) -> str:
    """The text a new journal stores (what a resume and the report read): the file's own, else the
    procedure written out."""
    if procedure.source_text:
        return procedure.source_text
    from setmem_hil.io.procedure_file import format_procedure

    return format_procedure(procedure)


def _finished(plan, service: MeasurementService, engine: RunEngine, clock: IterationClock):
    """The plan, then its summary (with how many stored measurements were served, and the
    engine's clocks: the run's wall time, each iteration's computation) as the ``finished``
    document that marks the journal finished."""
    summary = yield from plan
    timed = tuple(replace(row, compute_s=clock.by_iteration.get(row.k, (0.0, 0.0))[0],
                          compute_cpu_s=clock.by_iteration.get(row.k, (0.0, 0.0))[1]) for row in summary.iterations)
    summary = replace(summary, replayed_measurements=service.replayed, iterations=timed, wall_s=engine.elapsed_s)
    yield Emit("finished", {"summary": summary})
    return summary


def _confirm_output_off(experiment):
    return experiment.confirm_output_off if isinstance(experiment, OutputConfirmingExperiment) else None


__all__ = ["CampaignSummary", "run_campaign", *sorted(name for names in _REEXPORTED.values() for name in names)]
