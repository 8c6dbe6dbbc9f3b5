"""Choice of the next input (thesis section 4.1, 4.3 and 5.2-5.4; Algorithm 5.1 steps 5-7).

At iteration ``k`` the candidates are unit sinusoids at log-spaced frequencies (section 6.3.2).
For each candidate we predict the interval widths ``delta_i`` after measuring there
(:mod:`setmem_hil.design.input_effects`, eq. 4.47-4.53) and score it with the first-order expansion of
eq. (4.3)/(5.3), ``sum_i d mu-bar / d delta_i * E{delta_i reduction | u}``.

**Sensitivity convention.** :func:`setmem_hil.robust.analysis.analyze_robust_performance`
returns ``s_i = -d mu_peak / d eps`` where uncertainty ``i``'s normalised size shrinks by
``(1 - eps)^2`` (``M -> A M A``, Lemma 2.2). A predicted width ``delta_new`` therefore
corresponds to ``eps_i = 1 - sqrt(delta_new / delta_old)`` and the predicted improvement is
``sum_i s_i eps_i`` (to first order equal to eq. 5.3, since ``d delta / d eps = -2 delta_old``).

**Exact re-solve.** The approximation ranks all candidates; the best few (``exact_resolve_top``)
are re-identified with the certainty-equivalent measurement appended (eq. 4.53 with the real
conic problems of chapter 3, section 4.3.2's "solve the convex optimization problem for only
those inputs which have the best improvements") and the choice is made on that. A re-solve
that reports the predicted point inconsistent (the box midpoint need not be feasible) keeps its
approximate score.

**The floor (issue 38).** While a mode's box holds an undamped, zero-residue plant
(:mod:`setmem_hil.model.mu_floor`) no compensator reaches mu-bar < 1, whatever the sensitivities
of today's peak promise. Given ``floor_modes``, a candidate is weighed by the floors it removes
first (its predicted box, and its exact re-solve, no longer hold them), by its improvement
second: the candidates that bound a floor's mode rank ahead of every one that does not.

**Fallback (section 5.4.2).** When every estimate is zero (the nominal point would cut no
bound at any candidate), candidates are ranked by how close they come to cutting one: the
sensitivity-weighted sum over parameters of the larger of the two sides' ``|r(x_b)| / C``.
While floors remain and no candidate is predicted to remove one, the candidate in a floor
mode's band furthest from every measured point is taken (our choice, issue 47): at once for the
floor modes identified in a group (the one-mode predictions cannot see a jointly identified pair,
so what they promise elsewhere is no reason to leave the floor: the two-plane cantilever, whose
loop otherwise kept measuring beside its first pair while the floors held on the others); for the
others when nothing promises to improve mu-bar by more than ``NEGLIGIBLE_IMPROVEMENT``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from setmem_hil.errors import InconsistentDataError, SolverError
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.identification.algorithm import IdentifySettings, identify, identify_outputs
from setmem_hil.design.input_effects import InputEffects, estimate_input_effects
from setmem_hil.model.modal_model import PARAM_NAMES, IntervalModel, near_resonance
from setmem_hil.model.mu_floor import floor_mask
from setmem_hil.io.procedure import InputDesignSettings

SCORING = ("mu", "max-reduction")


@dataclass(frozen=True)
class InputChoice:
    """Outcome of one input-design step.

    Attributes
    ----------
    next_omega_rad_s : float
        Frequency chosen for the next experiment.
    candidate_omega_rad_s : numpy.ndarray
        All candidates of this iteration.
    estimated_improvement : numpy.ndarray
        Approximate predicted improvement per candidate (figure 6-14): ``sum_i s_i eps_i`` for
        the ``"mu"`` scoring, the total normalised width reduction for ``"max-reduction"``.
    basis : str
        ``"estimate"`` (eq. 5.3) or ``"closeness"`` (section 5.4.2 fallback).
    resolved_omega_rad_s, resolved_improvement : numpy.ndarray
        The candidates re-identified exactly and their improvement from the re-solve (NaN when
        the re-solve failed and the approximate score was kept).
    """

    next_omega_rad_s: float
    candidate_omega_rad_s: np.ndarray
    estimated_improvement: np.ndarray
    basis: str
    resolved_omega_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    resolved_improvement: np.ndarray = field(default_factory=lambda: np.zeros(0))


def n_candidates(k: int, settings: InputDesignSettings) -> int:
    """Number of candidates at iteration ``k`` (1-based): ``base + per_iteration * (k - 1)``.

    Section 6.3.2 says "500 + 25k at the kth iteration" but also that the first choice
    (figure 6-14) is among 500 sinusoids; we count from 500 at the first iteration.
    """
    if k < 1:
        raise ValueError(f"iteration k: expected >= 1, found {k}")
    return int(settings.candidates_base + settings.candidates_per_iteration * (k - 1))


def candidate_frequencies(k: int, settings: InputDesignSettings = InputDesignSettings()) -> np.ndarray:
    """Log-spaced candidate frequencies of iteration ``k`` (section 6.3.2, eq. 5.16's dense limit).

    Growing the count every iteration makes the union of the candidate sets dense in the band,
    as section 5.4.2 requires.
    """
    settings = settings.resolved()  # the thesis band when none is given (the runner resolves it)
    lo = float(settings.candidate_omega_min_rad_s)
    hi = float(settings.candidate_omega_max_rad_s)
    if not (0 < lo < hi and np.isfinite(hi)):
        raise ValueError(f"candidate band: expected 0 < omega_min < omega_max, found [{lo:g}, {hi:g}] rad/s")
    return np.geomspace(lo, hi, n_candidates(k, settings))


def sensitivity_matrix(sensitivities: Mapping[str, float], n_modes: int) -> np.ndarray:
    """``(n_modes, 4)`` array from the ``'<param>_<mode>'`` dict (modes from 1); absent -> 0."""
    s = np.zeros((n_modes, 4))
    for key, value in sensitivities.items():
        name, _, mode = key.rpartition("_")
        if name in PARAM_NAMES and mode.isdigit() and 1 <= int(mode) <= n_modes:
            v = float(value)
            s[int(mode) - 1, PARAM_NAMES.index(name)] = v if np.isfinite(v) else 0.0
    return s


def improvement_from_widths(width_old: np.ndarray, width_new: np.ndarray, weights: np.ndarray, scoring: str = "mu") -> np.ndarray:
    """Predicted improvement for predicted widths ``width_new`` (``(..., n_modes, 4)``).

    ``"mu"``: ``sum_i s_i (1 - sqrt(delta_new / delta_old))`` (eq. 5.3 in the sensitivity
    convention above). ``"max-reduction"``: ``sum_i w_i (1 - delta_new / delta_old)``, the total
    normalised interval reduction. Parameters with zero or non-finite old width contribute 0.
    """
    if scoring not in SCORING:
        raise ValueError(f"scoring: expected one of {SCORING}, found {scoring!r}")
    old = np.asarray(width_old, dtype=float)
    new = np.asarray(width_new, dtype=float)
    ok = np.isfinite(old) & (old > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(ok, np.clip(new / np.where(ok, old, 1.0), 0.0, 1.0), 1.0)
    ratio = np.where(np.isfinite(ratio), ratio, 1.0)
    reduction = 1.0 - (np.sqrt(ratio) if scoring == "mu" else ratio)
    return np.sum(np.asarray(weights, dtype=float) * reduction, axis=(-2, -1))


def closeness_score(effects: InputEffects, weights: np.ndarray) -> np.ndarray:
    """Section 5.4.2 ranking: ``sum_i w_i max_side min(|r(x_b)| / C, 1)`` per candidate."""
    close = np.nan_to_num(effects.closeness, nan=0.0)
    close = np.minimum(close, 1.0).max(axis=-1)  # (N, m, 4)
    return np.sum(np.asarray(weights, dtype=float)[None] * close, axis=(-2, -1))


def approximate_scores(
    model: IntervalModel,
    optimizers: np.ndarray,
    omega_rad_s: np.ndarray,
    noise_bound: np.ndarray,
    weights: np.ndarray,
    scoring: str = "mu",
) -> tuple[np.ndarray, np.ndarray, str, InputEffects]:
    """Approximate improvement of every candidate and the ranking score actually used.

    Returns ``(estimated_improvement, ranking_score, basis, effects)``; ``ranking_score`` is the
    estimate unless every estimate is zero, then the closeness score (section 5.4.2).
    """
    effects = estimate_input_effects(model, optimizers, omega_rad_s, noise_bound)
    estimate = improvement_from_widths(model.width, effects.width, weights, scoring)
    if np.any(estimate > 0):
        return estimate, estimate, "estimate", effects
    return estimate, closeness_score(effects, weights), "closeness", effects


def top_indices(score: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` best scores, best first; ties go to the lower frequency index."""
    order = np.lexsort((np.arange(score.size), -score))
    return order[: max(0, int(count))]


@dataclass(frozen=True)
class OtherOutputs:
    """Several sensors (issue 25): every output's data, prior, name, current model and the bound
    expected at each candidate; index 0 is the control output (the one ``choose_input`` scores).

    With it, an exact re-solve adds a predicted point to *every* output (eq. 4.53 per output:
    that output's model midpoint at the candidate, with that output's own expected bound) and
    re-identifies them with shared poles: a dwell reads every sensor, and the other sensors'
    points narrow the control output's poles too.
    """

    datas: tuple[FrequencyData, ...]
    priors: tuple
    names: tuple[str, ...]
    models: tuple[IntervalModel, ...]
    bounds: tuple[np.ndarray, ...]

    def predicted_control_model(self, index: int, omega_rad_s: float, settings) -> IntervalModel:
        """The control output's model after a dwell at candidate ``index`` (``omega_rad_s``)."""
        w = np.array([omega_rad_s])
        augmented = [data.appended(FrequencyData(w, model.midpoint.frequency_response(w), [float(bound[index])]))
                     for data, model, bound in zip(self.datas, self.models, self.bounds)]
        trial = identify_outputs(augmented, list(self.priors), list(self.names), previous=list(self.models), settings=settings)
        return trial.models[0]


def choose_input(
    result,
    data: FrequencyData,
    prior,
    omega_rad_s: np.ndarray,
    noise_bound: np.ndarray,
    weights: np.ndarray,
    *,
    scoring: str = "mu",
    exact_resolve_top: int = 5,
    identify_settings=None,
    cost_s: np.ndarray | None = None,
    other_outputs: OtherOutputs | None = None,
    floor_modes: tuple[int, ...] = (),
) -> InputChoice:
    """Algorithm 5.1 steps 6-7: rank the candidates and pick the next input.

    Parameters
    ----------
    result : setmem_hil.identification.algorithm.IdentificationResult
        Identification of the current data (its ``model`` and ``optimizers`` are used).
    data : FrequencyData
        The measurements behind ``result`` (for the exact re-solves).
    prior : setmem_hil.model.prior.Prior
        The prior used for the identification.
    omega_rad_s, noise_bound : numpy.ndarray
        Candidate frequencies and the total error bound expected at each.
    weights : numpy.ndarray
        ``(n_modes, 4)``: mu-sensitivities for ``"mu"``, ones on the free parameters for
        ``"max-reduction"``.
    scoring : {"mu", "max-reduction"}
    exact_resolve_top : int
        How many of the best approximate candidates to re-identify exactly (0: none).
    identify_settings : setmem_hil.identification.algorithm.IdentifySettings, optional
        Settings of the exact re-solves.
    cost_s : numpy.ndarray, optional
        Rig seconds a dwell at each candidate is expected to take. Given, candidates are ranked
        by improvement *per second* (approximate scores to pick the ones re-identified exactly,
        then the exact improvements); ``estimated_improvement`` stays the improvement itself.
    other_outputs : OtherOutputs, optional
        Several sensors: the exact re-solves predict every output's point (see there).
    floor_modes : tuple of int
        1-based modes whose box holds the floor: candidates removing it rank first (module doc).

    Returns
    -------
    InputChoice
    """
    model = result.model
    omega = np.asarray(omega_rad_s, dtype=float)
    R = np.asarray(noise_bound, dtype=float)
    estimate, score, basis, effects = approximate_scores(model, result.optimizers, omega, R, weights, scoring)
    per_second = np.ones_like(omega) if cost_s is None else 1.0 / np.maximum(np.asarray(cost_s, dtype=float), 1e-9)
    floors = np.asarray(floor_modes, dtype=int) - 1
    removed = _floors_removed(effects.lower, effects.upper, floors)
    ranking = _with_floors_first(score * per_second, removed)
    top = top_indices(ranking, exact_resolve_top)
    resolved = np.full(top.size, np.nan)
    removed_exactly = removed[top].copy()
    if top.size:
        settings = identify_settings if identify_settings is not None else IdentifySettings()
        g_nominal = model.midpoint.frequency_response(omega[top])  # certainty equivalence, eq. 4.53
        for n, idx in enumerate(top):
            extra = FrequencyData([omega[idx]], [g_nominal[n]], [R[idx]])
            try:
                if other_outputs is None:
                    trial_model = identify(data.appended(extra), prior, previous=model, settings=settings).model
                else:
                    trial_model = other_outputs.predicted_control_model(int(idx), float(omega[idx]), settings)
            except (InconsistentDataError, SolverError):
                continue
            new_width = np.minimum(trial_model.width, model.width)
            resolved[n] = float(improvement_from_widths(model.width, new_width, weights, scoring))
            removed_exactly[n] = _floors_removed(trial_model.lower[None], trial_model.upper[None], floors)[0]
    # final ranking: exact improvement where available, the approximate score breaking ties
    exact_key = _with_floors_first(np.where(np.isnan(resolved), estimate[top], resolved) * per_second[top], removed_exactly)
    if top.size and np.any(exact_key > 0):
        best = top[np.lexsort((np.arange(top.size), -ranking[top], -exact_key))[0]]
    else:
        best = top[0] if top.size else int(top_indices(ranking, 1)[0])
    promised = max(float(np.nanmax(estimate, initial=0.0)), float(np.nanmax(resolved, initial=0.0)))
    blind = _grouped(floors, getattr(result, "groups", ()))
    if floors.size and not np.any(removed > 0) and not np.any(removed_exactly > 0):
        if blind.size:
            best = _filling_floor_bands(model, omega, data.omega_rad_s, blind, default=best)
        elif promised < NEGLIGIBLE_IMPROVEMENT:
            best = _filling_floor_bands(model, omega, data.omega_rad_s, floors, default=best)
    return InputChoice(
        next_omega_rad_s=float(omega[best]),
        candidate_omega_rad_s=omega,
        estimated_improvement=estimate,
        basis=basis,
        resolved_omega_rad_s=omega[top],
        resolved_improvement=resolved,
    )


NEGLIGIBLE_IMPROVEMENT = 1e-4
"""A predicted mu-bar improvement below this is no reason to pick a candidate while a floor holds
(the two-plane cantilever's best was 8e-6, at 0.1 rad/s, against mu-bar 2.1)."""


def _grouped(floors: np.ndarray, groups) -> np.ndarray:
    """The floor modes (0-based) that were identified in a group of several modes: chapter 4's
    one-mode predictions cannot see what a measurement does to them (their optimizers are the
    split's), so no promised improvement elsewhere is a reason to leave them holding the floor
    (while any floor holds, mu-bar stays >= 1 whatever else narrows)."""
    jointly = {k for group in groups if len(group) > 1 for k in group}
    return np.array([k for k in floors if int(k) in jointly], dtype=int)


def _filling_floor_bands(model: IntervalModel, omega: np.ndarray, measured: np.ndarray, floors: np.ndarray,
                         default: int) -> int:
    """The candidate in a floor mode's band (its box's ``sqrt(a0)`` range; when no candidate lies
    there, widened by its largest half-power half-width ``a1 / 2``) furthest, in log-frequency,
    from every measured point; or ``default`` when no candidate lies in such a band.

    Our fallback where chapter 4's predictions promise nothing and no candidate is predicted to
    remove a floor: a close pair identified together is not predicted by the one-mode effects
    (its optimizers belong to the split), so every score is zero and the ranking would fall to the
    lowest candidate, far from any mode (the two-plane cantilever asked for 0.1 rad/s again and
    again). Filling the floor modes' bands is what lets the group search tell the pair apart."""
    for bandwidths in (0.0, 0.5):
        in_band = near_resonance(omega, model.lower[floors], model.upper[floors], bandwidths)
        if in_band.any():
            break
    if not in_band.any():
        return default
    measured = np.asarray(measured, dtype=float)
    measured = measured[measured > 0]
    if measured.size == 0:
        gap = np.ones(omega.size)
    else:
        gap = np.min(np.abs(np.log(omega[:, None] / measured[None, :])), axis=1)
    return int(np.flatnonzero(in_band)[np.argmax(gap[in_band])])


def _floors_removed(lower: np.ndarray, upper: np.ndarray, floors: np.ndarray) -> np.ndarray:
    """How many of the floor modes (0-based) each predicted box ``(N, n_modes, 4)`` no longer holds."""
    if floors.size == 0:
        return np.zeros(np.shape(lower)[0])
    return np.sum(~floor_mask(lower, upper)[:, floors], axis=1).astype(float)


def _with_floors_first(score: np.ndarray, removed: np.ndarray) -> np.ndarray:
    """``score`` shifted so that removing more floors always ranks higher (ties: the score)."""
    if not np.any(removed > 0):
        return score
    step = 1.0 + float(np.max(np.abs(np.nan_to_num(score)), initial=0.0))
    return score + removed * step


def uniform_weights(model: IntervalModel) -> np.ndarray:
    """Weight 1 on every free parameter: the ``"max-reduction"`` baseline ignores mu."""
    return np.where(model.fixed, 0.0, 1.0)


__all__ = [
    "InputChoice",
    "SCORING",
    "approximate_scores",
    "candidate_frequencies",
    "choose_input",
    "closeness_score",
    "improvement_from_widths",
    "n_candidates",
    "sensitivity_matrix",
    "top_indices",
    "uniform_weights",
]
