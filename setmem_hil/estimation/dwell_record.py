"""A sampled dwell's raw record (kind ``sine-dwell``): the window the points were fitted from and
everything the fit used, and :func:`dwell_points`, which computes the points from it. The sine
dwell (:class:`setmem_hil.drivers.sine_dwell.SineDwellExperiment`) computes every point through
:func:`dwell_points`, so ``setmem-hil reprocess`` runs the same code on the stored record.

Datasets: ``t_s``, ``force``, ``response`` (the control output's channel), ``others`` (the other
outputs' channels, one row each): the settled window as the sensor delivered it (volts or the
sensor's units, after its scale and offset), and the model the transients were fitted with
(``model_lower``/``model_upper``, or ``model_values`` for a point model). Attributes: the
dwell settings, the plan (one sine or a multisine's lines), the attempt and extension counts, the
dwell's seconds so far, ``|W1|`` at each line (``extra_bound``), the pole tracker's state
before the dwell, and each line's instrument terms
(:class:`~setmem_hil.estimation.instrument_terms.InstrumentTerms`; none for a rig without them).
An instrument's own record as read (codes, scale, offset) is kept beside these by its sensor
under ``instrument_*`` names.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.dwell_estimate import DwellPlan, DwellResult, DwellSettings, MultisinePlan, PoleTracker, estimate_multisine
from setmem_hil.estimation.instrument_terms import InstrumentTerms, apply_instrument_terms
from setmem_hil.estimation.sine_fit import DampedPole
from setmem_hil.model.experiment import Measurement, RawRecord
from setmem_hil.model.modal_model import IntervalModel, ModalParameters

__all__ = ["DwellInputs", "corrected_points", "dwell_points", "dwell_record", "inputs_from_record", "results_from_inputs"]

SINE_DWELL = "sine-dwell"
"""Raw-record kind of a sampled sine dwell (:func:`dwell_record`, recomputed by :func:`dwell_points`)."""



@dataclass(frozen=True)
class DwellInputs:
    """Everything :func:`~setmem_hil.estimation.dwell_estimate.estimate_multisine` used for one
    settled window, plus each line's instrument terms."""

    settings: DwellSettings
    model: Any
    tracker_state: tuple
    extra_bound: tuple[tuple[float, float], ...] | None
    plan: DwellPlan | MultisinePlan
    t_s: np.ndarray
    force: np.ndarray
    response: np.ndarray
    others: tuple[np.ndarray, ...]
    attempt: int
    dwell_s: float
    extensions: int
    terms: tuple[InstrumentTerms, ...] | None = None


@dataclass(frozen=True)
class _Block:
    t_s: np.ndarray
    force: np.ndarray
    response: np.ndarray
    others: tuple[np.ndarray, ...] = ()


def results_from_inputs(inputs: DwellInputs) -> list[DwellResult] | None:
    """The window's dwell results (None: its halves disagree, not settled)."""
    tracker = PoleTracker()
    for index, sigma, omega_d, cov in inputs.tracker_state:
        tracker.update(int(index), DampedPole(float(sigma), float(omega_d)), np.asarray(cov, dtype=float))
    table = None if inputs.extra_bound is None else dict(inputs.extra_bound)
    extra = None if table is None else (lambda w: table[float(w)])
    block = _Block(inputs.t_s, inputs.force, inputs.response, inputs.others)
    return estimate_multisine(inputs.settings, inputs.model, tracker, extra, inputs.plan, block, inputs.attempt, inputs.dwell_s,
                              inputs.extensions)


def corrected_points(results: list[DwellResult], terms: tuple[InstrumentTerms, ...] | None) -> list[Measurement]:
    """Each result's point with its line's instrument terms (converted to receptance)."""
    if terms is None:
        return [r.measurement for r in results]
    return [apply_instrument_terms(r.measurement, abs(r.force_fit.phasor), t) for r, t in zip(results, terms)]


def dwell_record(inputs: DwellInputs, instrument: Mapping[str, np.ndarray] | None = None, rig: str = "") -> RawRecord:
    """The raw record of ``inputs`` (see the module docstring); ``instrument``: the sensor's own
    record as read (codes, scale, offset...), stored as ``instrument_<name>``."""
    datasets = {"t_s": inputs.t_s, "force": inputs.force, "response": inputs.response,
                "others": np.array(inputs.others).reshape(len(inputs.others), inputs.t_s.size), **_model_datasets(inputs.model)}
    datasets.update({f"instrument_{k}": np.asarray(v) for k, v in (instrument or {}).items()})
    multisine = isinstance(inputs.plan, MultisinePlan)
    attrs = {"rig": rig, "settings": dataclasses.asdict(inputs.settings), "plan": dataclasses.asdict(inputs.plan),
             "plan_kind": "multisine" if multisine else "sine", "attempt": int(inputs.attempt), "dwell_s": float(inputs.dwell_s),
             "extensions": int(inputs.extensions), "tracker_state": [list(s) for s in inputs.tracker_state],
             "extra_bound": None if inputs.extra_bound is None else [list(p) for p in inputs.extra_bound],
             "instrument_terms": None if inputs.terms is None else [t.to_document() for t in inputs.terms]}
    return RawRecord(SINE_DWELL, datasets, attrs)


def dwell_points(record: RawRecord) -> list[Measurement]:
    """The points of a ``sine-dwell`` record (the dwell's own computation, see the module docstring)."""
    inputs = inputs_from_record(record)
    results = results_from_inputs(inputs)
    if results is None:
        raise DataQualityError("the stored window does not settle (its halves disagree beyond their uncertainty)")
    return corrected_points(results, inputs.terms)


def inputs_from_record(record: RawRecord) -> DwellInputs:
    d, a = record.datasets, record.attrs
    plan_doc = dict(a["plan"])
    if a["plan_kind"] == "multisine":
        plan = MultisinePlan(**{**plan_doc, "omegas_rad_s": tuple(plan_doc["omegas_rad_s"])})
    else:
        plan = DwellPlan(**plan_doc)
    terms = None if a["instrument_terms"] is None else tuple(InstrumentTerms.from_document(t) for t in a["instrument_terms"])
    extra = None if a["extra_bound"] is None else tuple((float(w), float(v)) for w, v in a["extra_bound"])
    others = tuple(np.asarray(row) for row in np.asarray(d["others"]))
    return DwellInputs(DwellSettings(**a["settings"]), _model_from(d), tuple(tuple(s) for s in a["tracker_state"]), extra, plan,
                       np.asarray(d["t_s"]), np.asarray(d["force"]), np.asarray(d["response"]), others, int(a["attempt"]),
                       float(a["dwell_s"]), int(a["extensions"]), terms)


def _model_datasets(model) -> dict:
    if isinstance(model, IntervalModel):
        return {"model_lower": model.lower, "model_upper": model.upper}
    if isinstance(model, ModalParameters):
        return {"model_values": model.values, "model_residuals": np.array([model.lower_residual, model.upper_residual])}
    return {}


def _model_from(d: Mapping[str, np.ndarray]):
    if "model_lower" in d:
        return IntervalModel(np.asarray(d["model_lower"]), np.asarray(d["model_upper"]))
    if "model_values" in d:
        lower_residual, upper_residual = (float(x) for x in d["model_residuals"])
        return ModalParameters(np.asarray(d["model_values"]), lower_residual, upper_residual)
    return None

