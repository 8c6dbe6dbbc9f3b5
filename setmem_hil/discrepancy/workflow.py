"""Discrepancy workflow: where model and data disagree, what is missing, add it, show the gap shrink.

**Where.** The normalised residual of each point, ``rho_i = |g_i - G(j omega_i)| / R_i``, is the
set-membership condition of eq. (3.8) divided by its bound: ``rho_i <= 1`` at every point means
the model is consistent with the data. Against an interval model we take the best point of its
box (:func:`setmem_hil.discrepancy.fit.fit_minimax`), so ``max rho <= 1`` iff some member of
the model explains every point. When the identification is infeasible there is no identified
model; the "model built from the prior" is then a robust (soft-L1) least-squares fit inside the
prior's box, which leaves a localised discrepancy where it is (a minimax fit would spread it
over every resonance); the smallest worst residual over the prior's box is reported as well
(``best_fit_in_prior_max_normalized_residual``, the exact-structure inflation factor).
Disagreement bands are the runs of consecutive frequencies with ``rho_i > 1``. Consistency of the identification itself: :func:`setmem_hil.identification.algorithm.identify`
failing (``InconsistentDataError``) is evidence of a missing effect; we report the smallest
bound inflation factor with which it succeeds (bisection).

**What.** Each candidate of :mod:`setmem_hil.discrepancy.effects` (``none``, ``time_delay``,
``first_order_lag``, ``feedthrough``, ``extra_mode``) is fitted jointly with the modal
parameters inside the prior's box, giving its best worst residual ``rho_c``. Selection rule:

    among candidates with ``rho_c <= threshold`` (1: consistent within the bound),
    minimise ``score_c = k_c + rho_c / threshold``

with ``k_c`` the number of added parameters (0, 1, 1, 1, 3 or 4): a penalty of one per
parameter, which outweighs any difference of residual among consistent candidates, so the
fewest parameters win and the residual breaks ties. One refinement: a first-order lag whose
fitted corner ``1 / tau`` lies above the measured band is, inside the band, a delay of ``tau``
(its magnitude loss is second order), so when a delay is also consistent the delay is named
(and the delay is refitted from the lag's ``tau`` if its own fit missed that equivalent).
If no candidate is consistent the answer is ``unexplained``: no name is forced.

**Add and show.** The chosen effect goes into the model structure and the model is
re-identified (:func:`setmem_hil.discrepancy.reidentify.reidentify_with_effect`); before/after
figures and (with :mod:`setmem_hil.discrepancy.plot`) a plot.

The workflow never modifies its inputs; campaigns call :func:`check_discrepancy` after an
identification and store the report (they never change the model silently).

REPORT.json (public contract keys first, extra keys allowed): ``disagreement_bands``,
``effects`` (``[]`` for none; ``[{"name": "unexplained", ...}]`` when nothing fits), ``before``
and ``after`` (``max_normalized_residual``, ``feasible``; ``before`` adds
``bound_inflation_factor``, ``best_fit_in_prior_max_normalized_residual``,
``n_points_over_bound``; ``after`` adds ``bound_inflation_for_effect_interval``), then
``decision``, ``candidates`` (every fitted candidate's residual, parameter count and
parameters), ``rule`` and ``model_after`` (the re-identified model in the identify result
format with an ``effect`` entry).

Example
-------
>>> from setmem_hil.io.procedure import thesis_beam_prior
>>> from setmem_hil.sim_backends.hidden_effects import draw_hidden_effect_case
>>> case = draw_hidden_effect_case("feedthrough", seed=4)
>>> report = discrepancy_from_prior(case.data, thesis_beam_prior())  # doctest: +SKIP
>>> report.decision, report.after["max_normalized_residual"] <= 1.0  # doctest: +SKIP
('feedthrough', True)
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from setmem_hil.io.atomic_file import json_safe
from setmem_hil.discrepancy.effects import (
    CandidateFit, ModalBox, fit_candidate, fit_none, initial_modal_estimate,
)
from setmem_hil.discrepancy.progress import Progress, say
from setmem_hil.errors import InconsistentDataError, InputFormatError
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.prior import ModePrior, Prior

ONE_PARAMETER_EFFECTS = ("time_delay", "first_order_lag", "feedthrough", "residual_mass")
EFFECT_ALIASES = {"feedthrough": ("residual_flexibility",)}
"""A constant added to the receptance is the upper residual (residual flexibility of the modes above
the band) of modal-analysis practice: one candidate, reported under both names."""
AMBIGUITY_MARGIN = 0.05
"""Two consistent candidates with the same number of added parameters whose worst normalised
residuals differ by less than this (in units of the threshold) explain the data equally well."""


@dataclass(frozen=True)
class DiscrepancySettings:
    """Settings of the discrepancy workflow.

    Attributes
    ----------
    threshold : float
        A structure is consistent with the data when its worst normalised residual is at most
        this (1: within the bound, eq. 3.8).
    inflation_steps : int
        Bisection steps for the smallest bound inflation factor that makes the identification
        feasible (0: skip).
    interval_steps : int
        Bisection steps per side for the set-membership interval of a one-parameter effect.
    extra_mode_margin : float
        Relative half-width of the natural-frequency band given to an added mode in the prior.
    fit_all : bool
        Fit every candidate for the report even when fewer would decide.
    reidentify : bool
        Re-identify with the chosen effect (False: report the fits only).
    """

    threshold: float = 1.0
    inflation_steps: int = 6
    interval_steps: int = 6
    extra_mode_margin: float = 0.1
    fit_all: bool = False
    reidentify: bool = True


@dataclass(frozen=True)
class DiscrepancyReport:
    """Outcome of the workflow; :meth:`to_document` is the REPORT.json of the public contract.

    Attributes
    ----------
    decision : str
        ``"none"``, an effect name, or ``"unexplained"``.
    disagreement_bands : tuple of (float, float)
        Frequency ranges (rad/s, first and last measured point) where the model's normalised
        residual exceeds 1.
    effects : tuple of dict
        ``{"name", "params", "evidence"}`` (empty for ``none``).
    before, after : dict
        ``max_normalized_residual`` and ``feasible`` (plus extra figures) without and with the
        effect.
    candidates : dict
        Per fitted candidate: ``max_normalized_residual``, ``n_added_params``, ``params``.
    data : FrequencyData
    old_fit : CandidateFit
        Best point of the given (or identified) model on the data.
    new_fit : CandidateFit or None
        The chosen structure's fit (None for ``none`` and ``unexplained``).
    new_model : dict or None
        The re-identified model (identify result format, plus the effect's interval).
    """

    decision: str
    disagreement_bands: tuple
    effects: tuple
    before: dict
    after: dict
    candidates: dict
    data: FrequencyData
    old_fit: CandidateFit
    new_fit: CandidateFit | None = None
    new_model: dict | None = None
    rule: str = field(default="")

    def to_document(self) -> dict:
        """``{"disagreement_bands", "effects", "before", "after", ...}`` (extra keys allowed)."""
        return _jsonable({
            "disagreement_bands": [[float(a), float(b)] for a, b in self.disagreement_bands],
            "effects": [dict(e) for e in self.effects],
            "before": dict(self.before),
            "after": dict(self.after),
            "decision": self.decision,
            "candidates": self.candidates,
            "rule": self.rule,
            "model_after": self.new_model,
        })


RULE_TEXT = (
    "candidates with worst normalised residual <= threshold are consistent; among them the "
    "smallest score = added parameters + residual / threshold wins; a first-order lag with its "
    "corner above the band yields to a consistent time delay; another consistent candidate with as many "
    "parameters within 0.05 threshold of the winner: ambiguous (both named, with the frequency that separates "
    "them most); no consistent candidate: unexplained"
)


_jsonable = json_safe  # the one sanitiser: non-finite floats become null, numpy values plain Python


def disagreement_bands(omega_rad_s: np.ndarray, normalized_residual: np.ndarray, level: float = 1.0) -> tuple:
    """Runs of consecutive frequencies (sorted) with ``rho > level`` as ``(first, last)`` pairs."""
    order = np.argsort(omega_rad_s)
    w = np.asarray(omega_rad_s)[order]
    over = np.asarray(normalized_residual)[order] > level
    bands = []
    k = 0
    while k < w.size:
        if over[k]:
            j = k
            while j + 1 < w.size and over[j + 1]:
                j += 1
            bands.append((float(w[k]), float(w[j])))
            k = j + 1
        else:
            k += 1
    return tuple(bands)


def prior_from_model(model: IntervalModel, widen: float = 0.1, zeta_max: float = 0.5) -> Prior:
    """A prior around a given (possibly zero-width) model, for ``--model`` runs.

    Natural-frequency range of each mode: the model's ``sqrt(a0)`` interval widened by
    ``widen`` (relative) on each side; ``zeta_max`` as the thesis's section 6.1 prior (or the
    model's own largest damping ratio if larger); ``b1`` fixed where the model fixes it, else
    free; ``b0`` free.
    """
    modes = []
    for lo, hi in zip(model.lower, model.upper):
        w_lo = np.sqrt(max(lo[1], 0.0)) * (1.0 - widen)
        w_hi = np.sqrt(max(hi[1], 0.0)) * (1.0 + widen)
        if w_lo <= 0:
            raise InputFormatError("model", "a0", f"expected positive a0 bounds, found [{lo[1]:g}, {hi[1]:g}]")
        z = max(zeta_max, hi[0] / (2.0 * np.sqrt(lo[1])))
        extra = {"b1_min": float(lo[2]), "b1_max": float(lo[2])} if lo[2] == hi[2] else {}
        modes.append(ModePrior(float(w_lo), float(w_hi), float(min(z, 10.0)), **extra))
    modes.sort(key=lambda m: m.omega_min)
    return Prior(tuple(modes))


def _prior_box(prior: Prior, data: FrequencyData, start: np.ndarray | None) -> ModalBox:
    ib = prior.initial_bounds()
    if start is None:
        start = initial_modal_estimate(data, ib.lower, ib.upper)
    return ModalBox(ib.lower, ib.upper, start)


def _identify_feasible(data: FrequencyData, prior: Prior, cheap: bool = False):
    """``(feasible, result or None, message)`` of :func:`identify` on ``data``."""
    from setmem_hil.identification.algorithm import IdentifySettings, identify

    # the cheap checks ask consistency (the witness), not the tightest box: no shaving (issue 62)
    settings = IdentifySettings(max_outer_iterations=2, partition=False, shave=False) if cheap else IdentifySettings()
    try:
        return True, identify(data, prior, settings=settings), ""
    except InconsistentDataError as exc:
        return False, None, str(exc)
    except InputFormatError as exc:  # residues not boundable from these data
        return False, None, str(exc)


def bound_inflation_factor(data: FrequencyData, prior: Prior, upper: float, steps: int = 6,
                           known_infeasible: bool = False, progress: Progress | None = None) -> float:
    """Smallest ``k`` (to bisection precision, from above) with ``identify`` feasible on bounds ``k R``.

    ``upper`` must be a factor known (or expected) to be feasible, e.g. the best exact fit's
    worst normalised residual (the structure then meets eq. 3.8 with bound ``upper R``, hence
    the embedding of eq. 3.26, which relaxes it). Returns ``inf`` if even ``upper`` fails.
    Bisection is geometric; the identification uses cheap settings (two passes, no
    partitioning: a looser relaxation, so the factor is never overstated by that choice).
    """
    def ok(k):
        say(progress, f"bound inflation: identifying with the bounds x{k:.4g}")
        return _identify_feasible(FrequencyData(data.omega_rad_s, data.response, k * data.bound), prior, cheap=True)[0]

    if not known_infeasible and ok(1.0):
        return 1.0
    hi = max(float(upper), 1.0) * 1.05
    if not ok(hi):
        hi *= 2.0
        if not ok(hi):
            return float("inf")
    lo = 1.0
    for _ in range(steps):
        mid = np.sqrt(lo * hi)
        if ok(mid):
            hi = mid
        else:
            lo = mid
    return float(hi)


def choose_effect(fits: dict[str, CandidateFit], threshold: float, omega_top: float) -> str:
    """Apply the selection rule (module docstring) to fitted candidates; ``"unexplained"`` if none fits."""
    consistent = {n: f for n, f in fits.items() if f.max_normalized_residual <= threshold}
    if not consistent:
        return "unexplained"
    lag = consistent.get("first_order_lag")
    if lag is not None and "time_delay" in consistent:
        tau = lag.params.get("tau", 0.0)
        if tau <= 0 or 1.0 / tau > omega_top:
            consistent = {n: f for n, f in consistent.items() if n != "first_order_lag"}
    return min(consistent, key=lambda n: consistent[n].n_added_params + consistent[n].max_normalized_residual / threshold)


def ambiguous_alternative(fits: dict[str, CandidateFit], decision: str, threshold: float, omega_top: float) -> str | None:
    """The candidate that explains the data as well as ``decision`` does, if one does."""
    chosen = fits.get(decision)
    if chosen is None or decision in ("none", "unexplained"):
        return None
    rivals = [f for n, f in fits.items() if n not in (decision, "none") and f.max_normalized_residual <= threshold
              and f.n_added_params == chosen.n_added_params
              and abs(f.max_normalized_residual - chosen.max_normalized_residual) < AMBIGUITY_MARGIN * threshold]
    if decision == "time_delay":  # a lag with its corner above the band is, in band, this delay (rule above)
        rivals = [f for f in rivals if not (f.name == "first_order_lag" and (f.params.get("tau", 0.0) <= 0
                                                                              or 1.0 / f.params["tau"] > omega_top))]
    return min(rivals, key=lambda f: f.max_normalized_residual).name if rivals else None


def discriminating_frequency(data: FrequencyData, a: CandidateFit, b: CandidateFit) -> float:
    """The frequency (rad/s) where the two fitted structures differ most relative to the error bound
    a measurement there is expected to have (bounds interpolated log-log, held outside the data)."""
    w = data.omega_rad_s
    grid = np.geomspace(w.min() / 1.5, w.max() * 1.5, 2000)
    order = np.argsort(w)
    bound = np.exp(np.interp(np.log(grid), np.log(w[order]), np.log(np.maximum(data.bound[order], 1e-300))))
    gap = np.abs(a.response(grid) - b.response(grid)) / bound
    return float(grid[int(np.argmax(gap))])


def _refit_delay_from_lag(data: FrequencyData, box: ModalBox, fits: dict, threshold: float, top: float) -> None:
    """A consistent lag with its corner above the band is, in band, a delay of the same ``tau``:
    if the delay fit missed that, fit the delay again from the lag's ``tau`` and modes."""
    from setmem_hil.discrepancy.effects import fit_time_delay

    lag, delay = fits.get("first_order_lag"), fits.get("time_delay")
    if lag is None or delay is None or lag.max_normalized_residual > threshold or delay.max_normalized_residual <= threshold:
        return
    tau = lag.params.get("tau", 0.0)
    if tau > 0 and 1.0 / tau > top:
        again = fit_time_delay(data, box, lag.theta[: 4 * box.n_modes], tau_starts=(tau,))
        if again.max_normalized_residual < delay.max_normalized_residual:
            fits["time_delay"] = again


def _fit_candidates(data: FrequencyData, box: ModalBox, settings: DiscrepancySettings) -> tuple[dict, str]:
    """Fit in order of added parameters, stopping at the first level with a consistent candidate."""
    none = fit_none(data, box)
    fits = {"none": none}
    top = float(np.max(data.omega_rad_s))
    levels = (ONE_PARAMETER_EFFECTS, ("extra_mode",))
    decision = choose_effect(fits, settings.threshold, top)
    for level in levels:
        if decision != "unexplained" and not settings.fit_all:
            break
        for name in level:
            fits[name] = fit_candidate(name, data, box, none)
        _refit_delay_from_lag(data, box, fits, settings.threshold, top)
        if decision == "unexplained":
            decision = choose_effect(fits, settings.threshold, top)
    return fits, decision


def _candidate_summary(fits: dict) -> dict:
    return {
        n: {"max_normalized_residual": f.max_normalized_residual, "n_added_params": f.n_added_params, "params": f.params}
        for n, f in fits.items()
    }


def check_discrepancy(
    data: FrequencyData,
    model: IntervalModel | None,
    prior: Prior | None,
    settings: DiscrepancySettings = DiscrepancySettings(),
    identification_feasible: bool | None = None,
    progress: Progress | None = None,
) -> DiscrepancyReport:
    """Run the discrepancy workflow on data against a model (campaign hook; inputs untouched).

    Parameters
    ----------
    data : FrequencyData
        Measured response and bounds (eq. 3.7).
    model : IntervalModel or None
        The identified (or given simulation) model; zero widths allowed. None when the
        identification was infeasible (the prior's box is then used for "before").
    prior : Prior or None
        The prior the model was identified with; derived from ``model`` when None
        (:func:`prior_from_model`).
    settings : DiscrepancySettings
    identification_feasible : bool, optional
        Whether the identification behind ``model`` succeeded. Default: ``model is not None``
        when a prior is given; for a model without prior, whether some member of its box is
        consistent with the data (worst normalised residual <= 1).
    progress : callable, optional
        ``progress(text)`` before each long step (the bound inflation's trials, the candidates'
        fits, the re-identification), for a display: on real data the workflow takes minutes.

    Returns
    -------
    DiscrepancyReport
    """
    if model is None and prior is None:
        raise InputFormatError("discrepancy", "", "expected a model or a prior, found neither")
    given_prior = prior is not None
    if prior is None:
        prior = prior_from_model(model)
    if model is not None and model.n_modes != prior.n_modes:
        raise InputFormatError("discrepancy", "model", f"expected {prior.n_modes} modes as in the prior, found {model.n_modes}")

    # before: the best point of the model's box (or of the prior's box without a model)
    if model is not None:
        old = fit_none(data, ModalBox(model.lower, model.upper, model.midpoint.values))
    else:  # no identified model: the robust fit in the prior's box localises the disagreement
        old = fit_none(data, _prior_box(prior, data, None), robust=True)
    if identification_feasible is None:
        identification_feasible = (model is not None) if given_prior else bool(old.max_normalized_residual <= 1.0)
    bands = disagreement_bands(data.omega_rad_s, old.normalized_residual)

    box = _prior_box(prior, data, old.modal.values)
    say(progress, "fitting the candidate effects")
    fits, decision = _fit_candidates(data, box, settings)
    none = fits["none"]
    before = {
        "max_normalized_residual": old.max_normalized_residual,
        "feasible": bool(identification_feasible),
        "best_fit_in_prior_max_normalized_residual": none.max_normalized_residual,
        "n_points_over_bound": int(np.sum(old.normalized_residual > 1.0)),
    }
    if not identification_feasible and settings.inflation_steps > 0:
        before["bound_inflation_factor"] = bound_inflation_factor(
            data, prior, none.max_normalized_residual, settings.inflation_steps, known_infeasible=given_prior, progress=progress)
    elif identification_feasible:
        before["bound_inflation_factor"] = 1.0

    report = DiscrepancyReport(
        decision=decision, disagreement_bands=bands, effects=(), before=before, after=dict(before),
        candidates=_candidate_summary(fits), data=data, old_fit=old, rule=RULE_TEXT,
    )
    if decision == "none":
        after = {"max_normalized_residual": none.max_normalized_residual, "feasible": bool(identification_feasible)}
        if not identification_feasible or model is None:
            after["feasible"] = _identify_feasible(data, prior)[0]
        return replace(report, after=after)
    if decision == "unexplained":
        return replace(report, effects=(_unexplained_effect(fits, settings),))
    rival = ambiguous_alternative(fits, decision, settings.threshold, float(np.max(data.omega_rad_s)))
    if rival is not None:
        return replace(report, effects=(_ambiguous_effect(data, fits[decision], fits[rival], settings),))
    return _report_with_effect(report, data, prior, fits, decision, settings, given_prior, identification_feasible, progress)


def _unexplained_effect(fits: dict, settings: DiscrepancySettings) -> dict:
    """No candidate brings the data within their bounds: said, and the model left unchanged."""
    none = fits["none"]
    best = min((f for n, f in fits.items() if n != "none"), key=lambda f: f.max_normalized_residual, default=none)
    evidence = (
        f"no candidate is consistent with the data: worst normalised residual {none.max_normalized_residual:.3g} "
        f"without an effect; best candidate {best.name} {best.max_normalized_residual:.3g} "
        f"(threshold {settings.threshold:g}); the model is left unchanged"
    )
    return {"name": "unexplained", "params": {}, "evidence": evidence}


def _ambiguous_effect(data: FrequencyData, a, b, settings: DiscrepancySettings) -> dict:
    """Two candidates explain the data equally: the frequency that separates them most is named."""
    w = discriminating_frequency(data, a, b)
    evidence = (f"{a.name} and {b.name} both explain the data (worst normalised residuals "
                f"{a.max_normalized_residual:.3g} and {b.max_normalized_residual:.3g}, threshold {settings.threshold:g}) "
                f"with the same number of added parameters; a measurement at {w:.6g} rad/s "
                f"({w / (2 * np.pi):.6g} Hz) separates them most; the model is left unchanged")
    return {"name": "ambiguous", "candidates": [a.name, b.name], "discriminating_omega": w, "evidence": evidence}


def _report_with_effect(report: DiscrepancyReport, data: FrequencyData, prior: Prior, fits: dict, decision: str,
                        settings: DiscrepancySettings, given_prior: bool, identification_feasible: bool,
                        progress: Progress | None = None) -> DiscrepancyReport:
    """The chosen effect: its parameters (re-identified with it, when asked), the evidence, the gap after."""
    before, none = report.before, fits["none"]
    chosen = fits[decision]
    after = {"max_normalized_residual": chosen.max_normalized_residual, "feasible": None}
    new_model = None
    params = dict(chosen.params)
    if settings.reidentify:
        from setmem_hil.discrepancy.reidentify import reidentify_with_effect

        re = reidentify_with_effect(data, prior, chosen, settings, progress)
        after["feasible"] = re.feasible
        if re.message:
            after["identification_message"] = re.message
        after["bound_inflation_for_effect_interval"] = re.max_bound_inflation
        new_model = re.document
        if re.param_intervals:
            params.update({f"{k}_interval": list(v) for k, v in re.param_intervals.items()})
    others = ", ".join(
        f"{n} {f.max_normalized_residual:.3g} ({f.n_added_params} p.)" for n, f in fits.items() if n not in ("none", decision)
    )
    evidence = (
        f"worst normalised residual {none.max_normalized_residual:.3g} without an effect (best point in the prior), "
        f"{chosen.max_normalized_residual:.3g} with {decision} ({chosen.n_added_params} added parameter"
        f"{'s' if chosen.n_added_params != 1 else ''}); other candidates: {others or 'not needed'}; "
        f"{'identification' if given_prior else 'model consistency'} {'feasible' if identification_feasible else 'infeasible'} before"
        + (f" (bounds must be inflated x{before['bound_inflation_factor']:.3g})" if not identification_feasible and 'bound_inflation_factor' in before else "")
        + (f", {'feasible' if after['feasible'] else 'infeasible'} after" if after["feasible"] is not None else "")
    )
    lag = fits.get("first_order_lag")
    if decision == "time_delay" and lag is not None and lag.max_normalized_residual <= settings.threshold:
        corner = 1.0 / lag.params["tau"] if lag.params.get("tau", 0.0) > 0 else float("inf")
        evidence += (f"; a first-order lag also fits, but its corner ({corner:.3g} rad/s) lies above the band, "
                     "where a lag acts as a delay")
    effect = {"name": decision, "params": params, "evidence": evidence}
    if decision in EFFECT_ALIASES:  # the same term under its modal-analysis name
        effect["aliases"] = list(EFFECT_ALIASES[decision])
    return replace(report, effects=(effect,), after=after, new_fit=chosen, new_model=new_model)


def discrepancy_from_prior(data: FrequencyData, prior: Prior, settings: DiscrepancySettings = DiscrepancySettings(),
                           progress: Progress | None = None) -> DiscrepancyReport:
    """Identify with ``prior`` first (``--prior``), then :func:`check_discrepancy`."""
    say(progress, f"identifying {prior.n_modes} mode(s) from the prior")
    feasible, result, _ = _identify_feasible(data, prior)
    return check_discrepancy(data, result.model if feasible else None, prior, settings, identification_feasible=feasible,
                             progress=progress)


