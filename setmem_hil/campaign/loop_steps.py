"""The pieces of one pass of Algorithm 5.1 that the plan (:mod:`setmem_hil.campaign.plan`)
composes: several sensors' identification, the stopping test, the kept design and its final
tuning, and the journal's forms of the compensator and of every output's bounds. Pure
functions: no I/O, no experiment."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from setmem_hil.campaign.next_input import identify_settings
from setmem_hil.design.safeguard import SafeguardOutcome, certified_value
from setmem_hil.identification.calibration_scale import measured_scale_prior, plant_bounds
from setmem_hil.io.procedure import Procedure
from setmem_hil.model.experiment import Measurement
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["controller_matrices", "goal_certified", "identify_sensors", "kept_design_of", "polished", "sensors_document"]


def identify_sensors(measured: list[Measurement], procedure: Procedure, previous, scales=None):
    """Several sensors (issue 25): every output's data in one identification with shared poles
    (:func:`~setmem_hil.identification.algorithm.identify_outputs`). Returns the control output
    as a one-output result (the analysis, the H2 design and the input design use it; the other
    outputs have tightened its poles) and every output's model, for the next iteration."""
    from setmem_hil.identification.algorithm import identify_outputs

    datas = [FrequencyData.from_measurements(measured, output=k) for k in range(1 + len(measured[0].others))]
    priors = [procedure.prior if scales is None else measured_scale_prior(procedure.prior, scales[k]) for k in range(len(datas))]
    multi = identify_outputs(datas, priors, list(procedure.backend.output_order()), previous=previous,
                             settings=identify_settings())
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
