"""Robust-performance analysis of an interval model: H2 design, mu-bar and mu-sensitivities.

Public entry point :func:`analyze_robust_performance` (see ARCHITECTURE.md, issue 3):

1. the uncertain plant at the interval midpoints with rank-one parametric uncertainty
   (eq. 6.2-6.12), the weights and the augmented plant (eq. 6.13-6.23);
2. the H2 compensator for it (section 6.3.1), unless one is given (the campaign's monotone
   safeguard, eq. 5.12, evaluates an old compensator on a new model);
3. the mixed-mu upper bound (Definition 2.2) on a frequency grid (default 200 log-spaced points
   from 0.1 to 1000 rad/s) and a lower bound to report the gap. Every frequency gets a Newton
   solve of :func:`~setmem_hil.robust.mixed_mu.mixed_mu_upper` to ``tol = 1e-4`` (pass 1); then every
   frequency whose pass-1 value is within 3 % of the largest is solved again to ``1e-7``, until
   no pass-1 value (each an upper bound on its precise value) exceeds the largest precise one,
   so the peak is the precise maximum over the grid. The peak is then refined with 2 x 6 extra
   frequencies between its neighbours. Every value reported is ``sqrt(lambda_max)`` at explicit
   scalings, hence a true upper bound; pass-1 values are within ~1e-4 of optimal in our tests.
   The lower bound searches real-block vertices at the 8 highest frequencies and the real
   blocks' interior at the highest (elsewhere the real blocks are left at zero, still a valid
   lower bound). Then the whole band of the
   grid is **certified** (:mod:`~setmem_hil.robust.mu_certificate`, issue 27): the scalings of
   the grid points, each tested on whole frequency intervals with a Hamiltonian eigenvalue test,
   prove ``mu-bar(w) <= mu_peak (1 + 1e-4)`` at every frequency of the band; where they cannot,
   new points are solved, and a peak the grid missed raises ``mu_peak``;
4. the mu-sensitivities at the peak (steps 1-5 of 4.2.2), ``s_i = -d mu_peak / d eps`` for
   shrinking uncertainty ``i`` by ``(1 - eps)^2``; across several frequencies attaining the peak
   the smallest decrease is taken (4.2.2).

Sign convention: positive feedback ``u = K y`` (thesis footnote 3 of 6.3.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from setmem_hil.io.atomic_file import json_safe
from setmem_hil.robust.augmented_plant import augmented_plant
from setmem_hil.robust.h2_design import design_h2_controller, h2_controller_for_plant
from setmem_hil.robust.mixed_mu import MixedMuBound, MuStructure, mixed_mu_upper
from setmem_hil.robust.mu_certificate import CERTIFICATE_RTOL, certify_band
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.robust.mu_lower_bound import mixed_mu_lower
from setmem_hil.robust.mu_sensitivity import beta_derivatives
from setmem_hil.robust.robust_design import DESIGN_METHODS
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

__all__ = ["RobustAnalysis", "analyze_robust_performance", "design_h2_controller", "default_omega_grid", "grid_bounds", "certify_grid",
           "time_scaled_controller"]

PEAK_TIE_RTOL = 1e-6  # frequencies within this of the peak count as attaining it (4.2.2)
FAST_TOL, FAST_MAX_ITER = 1e-4, 60  # pass 1 over the grid
PRECISE_TOL, PRECISE_MAX_ITER = 1e-7, 100  # pass 2 near the peak and the refinement points
LOWER_SEARCH_POINTS = 8  # frequencies (highest upper bound) given the vertex lower-bound search
LOWER_INTERIOR_POINTS = 1  # ... and of those, the highest given the interior search too (issue 38)
PEAK_WINDOW = 0.03  # pass-1 values within 3 % of the pass-1 maximum are solved precisely
ROBUST_CERTIFICATE_RTOL = 3e-3  # the robust design's certificate level over its peak (flat peaks: see the parameter)


def _merge(bound: MixedMuBound, idx: np.ndarray, better: MixedMuBound) -> MixedMuBound:
    """Replace entries ``idx`` of ``bound`` by ``better`` where ``better`` is lower (both valid)."""
    take = better.beta <= bound.beta[idx]
    fields = {}
    for name in ("beta", "d", "g", "eigenvalues", "eigenvectors"):
        arr = getattr(bound, name).copy()
        arr[idx[take]] = getattr(better, name)[take]
        fields[name] = arr
    return MixedMuBound(**fields)


def default_omega_grid() -> np.ndarray:
    """200 log-spaced frequencies from 0.1 to 1000 rad/s."""
    return np.logspace(-1.0, 3.0, 200)


@dataclass(frozen=True)
class RobustAnalysis:
    """Result of :func:`analyze_robust_performance`.

    Attributes
    ----------
    mu_peak : float
        Peak of the mixed-mu upper bound over every frequency evaluated (grid, refinement and the
        certificate's points); ``inf`` if the nominal closed loop is unstable.
    mu_peak_omega : float
        Frequency (rad/s) of the peak.
    mu_lower_peak : float
        Peak of the lower bound (the gap to ``mu_peak`` is reported, never hidden).
    omega : np.ndarray
        Frequencies (rad/s), ascending: the grid plus the refinement points.
    mu, mu_lower : np.ndarray
        Upper bound (valid at every frequency: evaluated at explicit scalings) and lower bound.
    sensitivities : dict
        ``'<param>_<mode>' -> s_i >= 0`` (modes from 1; fixed parameters absent).
    controller : control.StateSpace
        Compensator, positive feedback ``u = K y``.
    controller_order : int
    design : str
        Which design made ``controller``: ``"h2"`` (section 6.3.1), ``"robust"`` (tuned to the
        mixed-mu bound, :mod:`~setmem_hil.robust.robust_design`) or ``"given"`` (passed in).
    """

    mu_peak: float
    mu_peak_omega: float
    mu_lower_peak: float
    omega: np.ndarray
    mu: np.ndarray
    mu_lower: np.ndarray
    sensitivities: dict[str, float]
    controller: Any = field(repr=False)
    controller_order: int = 0
    mu_peak_certified: bool = False
    mu_certified_level: float = math.inf
    mu_certified_intervals: int = 0
    mu_peak_grid: float = math.nan
    design: str = "h2"

    @property
    def certified_mu(self) -> float:
        """The certified bound over the whole band (``mu_peak (1 + 1e-4)``); ``inf`` when the
        band could not be certified: the value the campaign's stopping test uses."""
        return float(self.mu_certified_level) if self.mu_peak_certified else math.inf

    def to_document(self) -> dict[str, Any]:
        """The ANALYSIS.json dict; non-finite values (unstable nominal loop) become ``null``."""

        return {
            "mu_peak_certified": bool(self.mu_peak_certified),
            "mu_certified_level": json_safe(float(self.mu_certified_level)),
            "mu_certified_intervals": int(self.mu_certified_intervals),
            "mu_peak_grid": json_safe(float(self.mu_peak_grid)),
            "mu_peak": json_safe(float(self.mu_peak)),
            "mu_peak_omega": float(self.mu_peak_omega),
            "mu_lower_peak": json_safe(float(self.mu_lower_peak)),
            "omega": [float(w) for w in self.omega],
            "mu": json_safe([float(m) for m in self.mu]),
            "sensitivities": {k: float(v) for k, v in self.sensitivities.items()},
            "controller_order": int(self.controller_order),
        }


def _refine_points(omega: np.ndarray, mu: np.ndarray, n_points: int) -> np.ndarray:
    k = int(np.argmax(mu))
    lo = omega[max(k - 1, 0)]
    hi = omega[min(k + 1, omega.size - 1)]
    pts = np.logspace(np.log10(lo), np.log10(hi), n_points + 2)[1:-1]
    return np.setdiff1d(pts, omega)


def analyze_robust_performance(
    model: IntervalModel,
    weights: Weights = THESIS_WEIGHTS,
    omega_rad_s=None,
    controller=None,
    gain: tuple[float, float] | None = None,
    design: str = "h2",
    warm_start=None,
    tuning=None,
    certificate_rtol: float = CERTIFICATE_RTOL,
) -> RobustAnalysis:
    """mu-bar peak, its lower bound and the mu-sensitivities of an interval model.

    Parameters
    ----------
    model : IntervalModel
        Parameter intervals; the nominal plant is at the midpoints, each non-fixed parameter
        is a real uncertainty ``|q_i| <= 1`` (eq. 6.2-6.12).
    weights : Weights
        ``W_1``, ``W_2`` (eq. 6.1, 6.13); ``W_2`` with its extra pole is used throughout.
    omega_rad_s : array_like, optional
        Frequency grid; default :func:`default_omega_grid`. The grid is refined around its peak.
    controller : control.StateSpace, optional
        Compensator to evaluate (``u = K y``); by default the H2 design for the midpoint.
    gain : (float, float), optional
        A common gain interval on the whole plant (the sensors' calibration: the model was
        identified as measured): one more real uncertainty, ``gain`` among the sensitivities
        (:func:`~setmem_hil.robust.uncertain_plant.uncertain_plant`).
    design : {"h2", "robust"}
        Without ``controller``: ``"h2"`` analyses the H2 design (the thesis); ``"robust"`` tunes a
        compensator of the same order to the mixed-mu bound (issue 38,
        :mod:`~setmem_hil.robust.robust_design`), starting from the H2 design or ``warm_start``,
        whichever has the lower peak, and keeps the tuned one only if its certified peak is no
        higher than its start's.
    warm_start : (controller, str), optional
        With ``design="robust"``: the previous iteration's compensator (rad/s) and the design that
        made it, a second start for the tuning.
    tuning : TuningSettings, optional
        Effort of the robust design.
    certificate_rtol : float
        The band certificate's level over the largest evaluated bound
        (:func:`~setmem_hil.robust.mu_certificate.certify_band`). A compensator tuned to the bound
        flattens mu-bar at its peaks, where ``1e-4`` can take seconds of solves or not close at
        all; the campaign's robust design certifies at :data:`ROBUST_CERTIFICATE_RTOL`.

    Returns
    -------
    RobustAnalysis

    Examples
    --------
    >>> from setmem_hil.model.modal_model import IntervalModel
    >>> from setmem_hil.sim_backends.beam import beam_parameters
    >>> r = analyze_robust_performance(IntervalModel.point(beam_parameters().truncated(3)))
    >>> 0.85 < r.mu_peak < 1.0
    True

    Notes
    -----
    **Any frequency scale.** The problem is solved in normalised time ``s_n = s / T`` with
    ``T = weights.reference_frequency_rad_s()`` (model, weights, grid and controller scaled;
    frequencies scaled back on return), and in normalised magnitude (plant and W1 divided by
    ``M = weights.reference_magnitude()``, the controller multiplied back). Rescaling time changes nothing physical, so a structure
    at 50 Hz with time-scaled weights gets the mu-bar, sensitivities and peak frequency (times
    ``S``) of the same structure at 1 rad/s; without it the H2 Riccati equations and the mu
    solver meet matrices with entries 1e8 apart. For the thesis weights ``T = 1`` exactly and
    nothing is scaled. The default grid is 200 log-spaced points over ``[0.1, 1000] T``, plus 25
    points around every modelled mode outside that range (so no mode is ever off the grid).
    """
    T = weights.reference_frequency_rad_s()
    M = weights.reference_magnitude()
    if not (math.isfinite(T) and T > 0.0 and math.isfinite(M) and M > 0.0):
        raise ValueError(f"weights: reference frequency {T!r} rad/s (from W2) and magnitude {M!r} (from W1) must be positive")
    if design not in DESIGN_METHODS:
        raise ValueError(f"design: expected one of {', '.join(DESIGN_METHODS)}, found {design!r}")
    robust = None if controller is not None or design != "robust" else (warm_start, tuning)
    if T == 1.0 and M == 1.0:
        return _analyze_normalised(model, weights, omega_rad_s, controller, gain, robust, certificate_rtol)
    if controller is not None and not hasattr(controller, "A"):
        import control

        controller = control.ss(controller)
    if robust is not None and robust[0] is not None:
        robust = ((time_scaled_controller(robust[0][0], 1.0 / T, M), robust[0][1]), tuning)
    result = _analyze_normalised(
        model.time_scaled(1.0 / T).magnitude_scaled(1.0 / M),
        weights.time_scaled(1.0 / T).magnitude_scaled(1.0 / M),
        None if omega_rad_s is None else np.asarray(omega_rad_s, dtype=float) / T,
        None if controller is None else time_scaled_controller(controller, 1.0 / T, M),
        gain,  # a gain on the whole plant: the same in any time or magnitude unit
        robust,
        certificate_rtol,
    )
    return RobustAnalysis(
        mu_peak=result.mu_peak,
        mu_peak_omega=result.mu_peak_omega * T,
        mu_lower_peak=result.mu_lower_peak,
        omega=result.omega * T,
        mu=result.mu,
        mu_lower=result.mu_lower,
        sensitivities=result.sensitivities,
        controller=time_scaled_controller(result.controller, T, 1.0 / M),
        controller_order=result.controller_order,
        mu_peak_certified=result.mu_peak_certified,
        mu_certified_level=result.mu_certified_level,
        mu_certified_intervals=result.mu_certified_intervals,
        mu_peak_grid=result.mu_peak_grid,
        design=result.design,
    )


def _settled(model: IntervalModel, weights: Weights, robust):
    """The robust design's inputs in normalised units cut to a fixed count of significant digits
    (:mod:`setmem_hil.numerics.settled_digits`): the box outwards (a box holding the given one, so
    the mu-bar found still bounds it), the weights and the warm start's matrices to the nearest.
    The design is a nonsmooth descent whose path a change of 1e-13 in the box moved by 1e-3 of
    mu-bar; the same structure at another frequency scale arrives here with rounding differences
    only, and must make the same design (issue 47: 1 rad/s and 50 Hz within 1e-3)."""
    import control

    from setmem_hil.numerics.settled_digits import cut_nearest, cut_outwards

    lower, upper = cut_outwards(model.lower, model.upper)
    cut = {name: tuple(float(c) for c in cut_nearest(getattr(weights, name)))
           for name in ("w1_num", "w1_den", "w2_num", "w2_den")}
    if weights.w2_extra_pole_rad_s:
        cut["w2_extra_pole_rad_s"] = float(cut_nearest(weights.w2_extra_pole_rad_s))
    warm_start, tuning = robust
    if warm_start is not None:
        K = warm_start[0]  # a state space (the design reads its A)
        K = control.ss(*(cut_nearest(np.asarray(m, dtype=float)) for m in (K.A, K.B, K.C, K.D)))
        warm_start = (K, warm_start[1])
    return IntervalModel(lower, upper), replace(weights, **cut), (warm_start, tuning)


def time_scaled_controller(K, factor: float, gain: float = 1.0):
    """``K'(s) = gain K(s / factor)``: state space ``(factor A, factor B, gain C, gain D)``."""
    import control

    return control.ss(np.asarray(K.A) * factor, np.asarray(K.B) * factor, np.asarray(K.C) * gain, np.asarray(K.D) * gain)


def default_grid_for(model: IntervalModel) -> np.ndarray:
    """:func:`default_omega_grid` plus 25 points around each mode outside it (normalised units)."""
    grid = default_omega_grid()
    wn = np.sqrt(np.maximum(0.5 * (model.lower[:, 1] + model.upper[:, 1]), 0.0))
    outside = wn[(wn > 0) & ((wn < grid[0]) | (wn > grid[-1]))]
    if outside.size == 0:
        return grid
    extra = [np.geomspace(w / 1.5, w * 1.5, 25) for w in outside]
    return np.unique(np.concatenate([grid, *extra]))


def _analyze_normalised(model: IntervalModel, weights: Weights, omega_rad_s, controller, gain=None, robust=None,
                        certificate_rtol: float = CERTIFICATE_RTOL) -> RobustAnalysis:
    """:func:`analyze_robust_performance` of a problem already in normalised time; ``robust``:
    ``(warm_start, tuning)`` for the robust design, None otherwise."""
    if robust is not None:
        model, weights, robust = _settled(model, weights, robust)
    plant = augmented_plant(uncertain_plant(model, gain), weights, design_w2=True)
    if controller is not None and not hasattr(controller, "A"):
        import control

        controller = control.ss(controller)  # e.g. a TransferFunction
    omega = default_grid_for(model) if omega_rad_s is None else np.sort(np.asarray(omega_rad_s, dtype=float).ravel())
    if omega.size == 0 or np.any(~np.isfinite(omega)) or np.any(omega < 0):
        raise ValueError("omega_rad_s: expected finite non-negative frequencies")
    if robust is not None:
        return _with_floor_lower_bound(_robust_design_analysis(plant, omega, *robust, certificate_rtol), model, gain, plant)
    K = h2_controller_for_plant(plant) if controller is None else controller
    result = _with_floor_lower_bound(_analyze_controller(plant, K, omega, certificate_rtol), model, gain, plant)
    return result if controller is None else replace(result, design="given")


def _with_floor_lower_bound(result: RobustAnalysis, model: IntervalModel, gain, plant) -> RobustAnalysis:
    """The floor's own perturbation as a lower bound (:mod:`setmem_hil.model.mu_floor`).

    Where mode ``m``'s box holds ``a1 = b1 = b0 = 0`` and ``w^2`` lies in its ``a0`` interval, the
    real blocks ``q(a1_m), q(b1_m), q(b0_m)`` at those values, ``q(a0_m)`` at ``a0 = w^2`` and every
    other block at 0 make ``I - M(j w) Delta`` singular: ``M Delta`` has the eigenvalue 1. It is
    checked (a real eigenvalue, to 1e-8) before it counts, so the bound stays one that is attained.
    The generic search (:func:`~setmem_hil.robust.mu_lower_bound.mixed_mu_lower`) rarely finds this
    interior point. Without a common gain only (with one, the residues' blocks are rescaled)."""
    from setmem_hil.model.modal_model import A0, A1, B0, B1, PARAM_NAMES
    from setmem_hil.model.mu_floor import floor_modes

    floors = floor_modes(model)
    if gain is not None or not floors or not math.isfinite(result.mu_peak):
        return result
    names = list(plant.names)
    mid, half = model.midpoint.values, 0.5 * model.width
    lower = np.array(result.mu_lower, dtype=float)
    cl = plant.closed_loop(result.controller)
    for mode in floors:
        i = mode - 1
        a0_lo, a0_hi = model.lower[i, A0], model.upper[i, A0]
        inside = (result.omega**2 >= a0_lo) & (result.omega**2 <= a0_hi) & (lower < 1.0)
        if not inside.any():
            continue
        q = np.zeros((int(inside.sum()), plant.n_real + plant.n_complex))
        for j, value in ((A1, 0.0), (B1, 0.0), (B0, 0.0)):
            key = f"{PARAM_NAMES[j]}_{mode}"
            if key in names:
                q[:, names.index(key)] = (value - mid[i, j]) / half[i, j]
        key = f"{PARAM_NAMES[A0]}_{mode}"
        if key in names:
            q[:, names.index(key)] = (result.omega[inside] ** 2 - mid[i, A0]) / half[i, A0]
        if np.any(np.abs(q) > 1.0 + 1e-12):
            continue
        lam = np.linalg.eigvals(cl.frequency_response(result.omega[inside]) * q[:, None, :])
        real = (np.abs(lam.imag) <= 1e-8 * np.abs(lam)) & (lam.real > 0.0)
        found = np.where(real, lam.real, 0.0).max(axis=1)
        lower[np.flatnonzero(inside)] = np.maximum(lower[inside], found)
    return replace(result, mu_lower=lower, mu_lower_peak=float(max(result.mu_lower_peak, lower.max())))


def _robust_design_analysis(plant, omega: np.ndarray, warm_start, tuning, rtol: float) -> RobustAnalysis:
    """Tune from the H2 design (and the warm start), analyse, keep the better certified design.

    When the analysis (grid refinement, certificate) finds mu-bar above the tuned peak at
    frequencies the tuning did not see, they join its frequency set and the tuning goes on from
    where it stopped (at most ``tuning.rounds`` rounds)."""
    from setmem_hil.robust.robust_design import TuningSettings, tune_compensator

    K_h2 = h2_controller_for_plant(plant)
    starts, labels = [K_h2], ["h2"]
    if warm_start is not None and np.asarray(warm_start[0].A).shape == np.asarray(K_h2.A).shape:
        starts.append(warm_start[0])
        labels.append(str(warm_start[1]))
    settings = tuning or TuningSettings()
    frequencies, best, start = omega, None, None
    for _ in range(settings.rounds):
        try:
            tuned = tune_compensator(plant, starts, frequencies, settings)
        except ValueError:  # no start stabilises the nominal loop: the H2 analysis says so (mu-bar inf)
            return _analyze_controller(plant, K_h2, omega, rtol)
        if start is None:
            start = (starts[tuned.start_index], labels[tuned.start_index], tuned.start_peak)
        if not tuned.improved:
            break
        result = replace(_analyze_controller(plant, tuned.controller.to_statespace(), omega, rtol), design="robust")
        if best is None or result.mu_peak < best.mu_peak:
            best = result
        missed = result.omega[result.mu > tuned.peak * (1.0 + 1e-6)]
        if missed.size == 0:
            break
        frequencies = np.union1d(frequencies, missed)
        starts, labels = [tuned.controller, *starts], ["robust", *labels]
    if best is not None and best.mu_peak <= start[2] * (1.0 + 1e-9):
        return best
    # nothing tuned, or the certificate found a peak between the tuning's frequencies: the start if better
    fallback = replace(_analyze_controller(plant, start[0], omega, rtol), design=start[1])
    return best if best is not None and best.mu_peak <= fallback.mu_peak else fallback


def _analyze_controller(plant, K, omega: np.ndarray, certificate_rtol: float = CERTIFICATE_RTOL) -> RobustAnalysis:
    """Grid, refinement, certificate, lower bound and sensitivities of one compensator."""
    order = int(np.asarray(K.A).shape[0]) if np.asarray(K.A).size else 0
    structure = MuStructure(plant.n_real, plant.n_complex)
    cl = plant.closed_loop(K)
    if np.max(np.linalg.eigvals(cl.A).real) >= 0.0:
        inf = np.full(omega.size, np.inf)
        return RobustAnalysis(
            mu_peak=math.inf,
            mu_peak_omega=float(omega[0]),
            mu_lower_peak=math.inf,
            omega=omega,
            mu=inf,
            mu_lower=inf.copy(),
            sensitivities={name: 0.0 for name in plant.names},
            controller=K,
            controller_order=order,
            mu_peak_grid=math.inf,
        )
    omegas, mats, bounds = grid_bounds(cl, structure, omega)
    peak_grid = float(max(b.beta.max() for b in bounds))
    certificate = certify_grid(cl, structure, omegas, bounds, certificate_rtol)
    n_grid = sum(b.beta.size for b in bounds)  # the grid and its refinement, before the certificate's points
    omegas.extend(certificate.omegas)
    mats.extend(certificate.matrices)
    bounds.extend(certificate.bounds)
    # flatten (frequency, matrix, bound index) for the peak search
    all_w = np.concatenate(omegas)
    all_mu = np.concatenate([b.beta for b in bounds])
    src = [(i, j) for i, b in enumerate(bounds) for j in range(b.beta.size)]
    M_all = np.concatenate(mats)
    # lower bound: real blocks at zero everywhere (cheap); the full search near the peak
    lower = mixed_mu_lower(M_all, structure, search_real=False).beta
    top = np.argsort(all_mu)[-LOWER_SEARCH_POINTS:]
    highest = np.arange(top.size) >= top.size - LOWER_INTERIOR_POINTS  # the real blocks' interior too, where the gap matters most
    lower[top] = np.maximum(lower[top], mixed_mu_lower(M_all[top], structure, interior=highest).beta)
    peak = float(all_mu.max())
    attaining = np.flatnonzero(all_mu >= peak * (1.0 - PEAK_TIE_RTOL))
    sens = np.full(plant.n_real, np.inf)
    for k in attaining:
        i, j = src[k]
        dbeta = beta_derivatives(mats[i][j], bounds[i], j)[: plant.n_real]
        sens = np.minimum(sens, np.maximum(-dbeta, 0.0))
    if plant.n_real == 0:
        sens = np.zeros(0)
    order_idx = np.argsort(all_w, kind="stable")
    # where the peak is: the grid's, unless the certificate found a larger value beyond the
    # tie tolerance (its points near the grid's peak tie with it to rounding, and must not move
    # the reported frequency by 1e-9 from one time scale to another)
    k_peak = int(np.argmax(all_mu[:n_grid]))
    if all_mu.max() > all_mu[k_peak] * (1.0 + PEAK_TIE_RTOL):
        k_peak = int(np.argmax(all_mu))
    return RobustAnalysis(
        mu_peak=peak,
        mu_peak_omega=float(all_w[k_peak]),
        mu_lower_peak=float(lower.max()),
        omega=all_w[order_idx],
        mu=all_mu[order_idx],
        mu_lower=lower[order_idx],
        sensitivities={name: float(s) for name, s in zip(plant.names, sens)},
        controller=K,
        controller_order=order,
        mu_peak_certified=bool(certificate.certified),
        mu_certified_level=float(certificate.level),
        mu_certified_intervals=int(certificate.n_intervals),
        mu_peak_grid=peak_grid,
    )


def grid_bounds(cl, structure: MuStructure, omega: np.ndarray) -> tuple[list, list, list]:
    """mu-bar on the grid, precise where the peak can be, then refined twice around the peaks:
    the frequencies, the closed loop's matrices and the bounds, one entry per pass."""
    Mw = cl.frequency_response(omega)
    # pass 1: every grid point, a shorter Newton run (valid bounds, ~1e-4 from optimal)
    bound = mixed_mu_upper(Mw, structure, tol=FAST_TOL, max_iter=FAST_MAX_ITER)
    # pass 2: precise solves wherever the peak can be, until every value not solved precisely
    # (each one an upper bound on its precise value) lies below the largest precise value
    precise = np.zeros(omega.size, dtype=bool)
    while True:
        level = (1.0 - PEAK_WINDOW) * bound.beta.max()
        cand = np.flatnonzero(~precise & (bound.beta >= level))
        if cand.size == 0:
            break
        bound = _merge(bound, cand, mixed_mu_upper(Mw[cand], structure, tol=PRECISE_TOL, max_iter=PRECISE_MAX_ITER))
        precise[cand] = True
    mats, bounds = [Mw], [bound]
    omegas = [omega]
    mu = bound.beta
    if omega.size >= 3:
        w_all = omega
        for n_pts in (6, 6):
            extra = _refine_points(w_all, mu, n_pts)
            if extra.size == 0:
                break
            Me = cl.frequency_response(extra)
            be = mixed_mu_upper(Me, structure, tol=PRECISE_TOL, max_iter=PRECISE_MAX_ITER)
            mats.append(Me)
            bounds.append(be)
            omegas.append(extra)
            w_all = np.concatenate([w_all, extra])
            mu = np.concatenate([mu, be.beta])
            order_idx = np.argsort(w_all)
            w_all, mu = w_all[order_idx], mu[order_idx]
    return omegas, mats, bounds


def certify_grid(cl, structure: MuStructure, omegas: list, bounds: list, rtol: float = CERTIFICATE_RTOL):
    """:func:`certify_band` over the band of the grid, from every solved point's scalings."""
    from setmem_hil.robust.mu_certificate import BandCertificate

    w = np.concatenate(omegas)
    if w.max() <= w.min():  # a one-point "band": its bound is exact there
        peak = float(max(b.beta.max() for b in bounds))
        return BandCertificate(certified=True, level=peak, peak=peak, n_intervals=0, n_scalings=0)
    merged = MixedMuBound(**{name: np.concatenate([getattr(b, name) for b in bounds])
                             for name in ("beta", "d", "g", "eigenvalues", "eigenvectors")})
    return certify_band(cl, structure, (float(w.min()), float(w.max())), w, merged, rtol=rtol)
