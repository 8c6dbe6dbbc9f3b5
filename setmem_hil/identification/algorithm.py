"""Guaranteed set-membership identification of a modal model (thesis chapter 3).

Algorithm 3.1 (multiple modes): each mode is identified as a one-mode problem (eq. 3.11) whose
error bound is the data's bound plus the other modes' worst-case mismatch (Lemma 3.1,
:mod:`setmem_hil.identification.mode_mismatch`), iterating to a fixed point. Algorithm 3.2 (one mode): the
convex embedding of eq. (3.26) bounds every parameter by conic programming
(:mod:`setmem_hil.identification.one_mode_solver`), repeated while the bounds on ``a0, a1`` improve, with the
``(a0, a1)`` box partitioned (Lemmas 3.2-3.4, :mod:`setmem_hil.identification.partitioning`) so that the
embedding's conservatism ratio gamma is at most the prior's target, unless more than
``max_partitions`` pieces would be needed.

Schedule (our choice where the thesis leaves it open, following section 6.2.1): passes without
partitioning until the bounds stop improving, then passes with partitioning wherever it is
affordable, until they stop improving too. Modes are updated in turn (Gauss-Seidel), each with
the latest bounds of the others. Every bound is intersected with the previous one, so bounds
never loosen (eq. 5.4-5.5), and the start is guaranteed (:mod:`setmem_hil.identification.residue_bootstrap`).
"""

from __future__ import annotations

import itertools
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from setmem_hil.identification.embedding import conservatism_ratio, embedding_bound, embedding_residual, redundant_points
from setmem_hil.errors import InconsistentDataError, InputFormatError
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import A0, A1, B0, B1, PARAM_NAMES, IntervalModel
from setmem_hil.identification.mode_group import GroupProvedEmpty, GroupSettings, close_groups, identify_group, piece_hulls
from setmem_hil.identification.mode_mismatch import mode_mismatch_bounds
from setmem_hil.identification.one_mode_solver import OneModeProblem
from setmem_hil.identification.partition_union import partition_union
from setmem_hil.identification.partitioning import PartitionPlan, minimal_partition, partition_boxes
from setmem_hil.model.prior import Prior
from setmem_hil.identification.residual_terms import bound_residual, residual_midpoint_response, residual_mismatch
from setmem_hil.identification.residue_bootstrap import bootstrap_residue_bounds
from setmem_hil.identification.shaving import ShaveReport, inner_extent, proved_empty, reach_ratios, within_cost_rule
from setmem_hil.identification.shaving import shave as shave_box
from setmem_hil.identification.witness import Witness, find_witness, residual_response

POLISH_BOXES = 48  # boxes the final all-modes contraction may use (24 left the far mode of the 1 % pair at 5x noise 2.1x the exact set, stop 54; 48: 1.8x)
# ... and with a mode outside every group, whose bound the pair's b1 cut serves (stop 61: a 0.5 % pair's
# far mode 2.20 -> 1.38 with 240; 240 for a campaign whose six modes are all in pairs moved its first
# iterations' mu-bar from 1.91 / 1.76 to 2.43 / 1.92)
POLISH_BOXES_LONE_MODE = 240
POLISH_B1_SHARE = 0.25  # the polish cuts a grouped mode's b1 first while it is wider than this share of the polished box's
POLISH_PIECES = 256  # boxes from the groups' last leaves that start the polish, at most (their hulls; one per group in every combination)
POLISH_POINTS = 400  # points that polish uses in every box (more: the subset in coarse boxes; a far mode's few resonant points decide it)

__all__ = [
    "IdentifySettings",
    "IdentificationResult",
    "MultiOutputResult",
    "identify",
    "identify_outputs",
    "mode_mismatch_bounds",
    "embedding_bound",
    "embedding_residual",
]


@dataclass(frozen=True)
class IdentifySettings:
    """Iteration limits of Algorithms 3.1/3.2.

    ``tolerance`` is the relative shrink of an interval (width) that counts as an improvement.
    """

    max_outer_iterations: int = 40
    max_inner_iterations: int = 3
    tolerance: float = 1e-3
    partition: bool = True
    groups: bool = True  # closely spaced modes identified together where the split cannot narrow (issue 47)
    group_rounds: int = 2
    group_boxes: int = GroupSettings.max_boxes  # boxes per stage of a group's search
    polish_pieces: int = POLISH_PIECES  # boxes from the groups' leaves that start the final contraction, at most (0: its hull)
    # boxes the final contraction may use beyond its pieces; None: POLISH_BOXES, or POLISH_BOXES_LONE_MODE
    # with a mode outside every group. More boxes are not narrower by construction (the second pass starts
    # from the first's answer; a box found settled against the witnesses is kept uncontracted): on a 0.5 %
    # same-sign pair at five times the noise, 1,000 took the far mode's b1 1.65 -> 1.49 of the exact set but
    # the upper mode's a1 1.37 -> 1.65, in about 4.6 times the time (stop 62)
    polish_boxes: int | None = None
    # the final contraction's divided-form points to second order (mode_group.second_order_group); None:
    # where a mode is outside every group (measured there: stop 63), not where every mode is grouped
    polish_second_order: bool | None = None
    # a witness (a point checked to fit every point, :mod:`setmem_hil.identification.witness`) sought
    # in the final box; without one no mode is verified (issue 62)
    witness: bool = True
    # every interval wider than its witnesses' reach shaved to the data's limit
    # (:mod:`setmem_hil.identification.shaving`, issue 62); needs ``witness``
    shave: bool = True


@dataclass(frozen=True)
class IdentificationResult:
    """Interval model and diagnostics; see ARCHITECTURE.md for every field."""

    model: IntervalModel
    embedding_gamma: np.ndarray
    mismatch_ratio: np.ndarray
    iterations: int
    n_solves: int
    partitions: tuple[tuple[int, int], ...]
    effective_bound: np.ndarray
    embedding_bound: np.ndarray
    optimizers: np.ndarray
    partitioned: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    verified: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    unverified_reason: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()  # why gamma exceeds the target, per mode where it does
    residuals: dict = field(default_factory=dict)  # enabled residual terms: name -> (lo, hi)
    groups: tuple[tuple[int, ...], ...] = ()  # 0-based modes identified together (issue 47); others alone
    witness: Witness | None = None  # the best point found, checked on the model (fits or not); None: not sought
    # each interval's width over the witnesses' reach after shaving, (n_modes, 4), nan where fixed or
    # unreached (an upper bound of its width over the exact set's extent); None: no witness fits
    reach_ratio: np.ndarray | None = None
    shaved: ShaveReport | None = None  # what shaving did; None: not run

    def group_of(self, i: int) -> tuple[int, ...]:
        """The modes (0-based) mode ``i`` was identified with, itself included."""
        return next((grp for grp in self.groups if i in grp), (i,))

    def to_document(self) -> dict:
        """The identify RESULT.json dict (public contract); each mode also gets ``group``, the
        1-based modes it was identified with (``[i]`` when alone)."""
        from setmem_hil.io.result_file import result_document

        doc = result_document(
            self.model, self.embedding_gamma, self.mismatch_ratio, self.iterations,
            n_solves=int(self.n_solves), partitions=[list(p) for p in self.partitions],
            verified=[bool(v) for v in self.verified], unverified_reason=list(self.unverified_reason),
            conservatism_notes=list(self.notes), residuals=self.residuals or None,
        )
        for i, mode in enumerate(doc["modes"]):
            mode["group"] = [k + 1 for k in self.group_of(i)]
            if self.reach_ratio is not None:
                mode["reach_ratio"] = {name: float(r) for name, r in zip(PARAM_NAMES, self.reach_ratio[i]) if np.isfinite(r)}
        if self.witness is not None:
            doc["witness"] = self.witness.to_document()
        if self.shaved is not None:
            doc["shaving"] = {"slabs": self.shaved.slabs, "proved_empty": self.shaved.emptied, "seconds": round(self.shaved.seconds, 3)}
        return doc


def _band_centres(prior: Prior) -> np.ndarray:
    return np.array([np.sqrt(m.omega_min * m.omega_max) for m in prior.modes])


def _assign_points_to_modes(prior: Prior, omega: np.ndarray) -> np.ndarray:
    """Index of the mode whose prior band centre is nearest each point in log frequency."""
    centres = _band_centres(prior)
    return np.argmin(np.abs(np.log(omega[:, None] / centres[None, :])), axis=1)


class _SolveCounter:
    """Counts conic solves across the per-pass problems (for the benchmark)."""

    def __init__(self):
        self.n_solves = 0


def output_columns(k: int) -> list[int]:
    """Columns ``(a1, a0, b1_k, b0_k)`` of output ``k`` in a mode's joint parameter vector."""
    return [A1, A0, 2 + 2 * k, 3 + 2 * k]


def _redundant(omega, g, E, lo, hi, output) -> np.ndarray:
    """:func:`redundant_points` of each output on its own columns."""
    if output is None:
        return redundant_points(omega, g, E, lo, hi)
    out = np.zeros(omega.size, dtype=bool)
    for k in np.unique(output):
        sel, cols = output == k, output_columns(int(k))
        out[sel] = redundant_points(omega[sel], g[sel], E[sel], lo[cols], hi[cols])
    return out


def _one_mode_pass(omega_all: np.ndarray, g_mode: np.ndarray, E: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                   prior: Prior, allow_partition: bool, settings: IdentifySettings, mode_index: int,
                   counter: _SolveCounter, output: np.ndarray | None = None, names: tuple[str, ...] = ()):
    """Algorithm 3.2 on one mode: returns (lo, hi, argmin, argmax, gamma, plan).

    ``g_mode`` is the data with the other modes' midpoint estimates subtracted (eq. 3.11) and
    ``E`` the matching error bound; points with an infinite bound carry no information. With
    several outputs, ``output`` gives each point's output and ``lo, hi`` are the joint
    ``(a1, a0, b1_1, b0_1, ...)`` (shared poles, issue 25).
    """
    n_params = lo.size
    usable = np.isfinite(E) & ~_redundant(omega_all, g_mode, E, lo, hi, output)
    if not usable.any():
        return lo, hi, np.full((n_params, n_params), np.nan), np.full((n_params, n_params), np.nan), np.inf, PartitionPlan(1, 1), ()
    omega, E_used = omega_all[usable], E[usable]
    problem = OneModeProblem(omega, g_mode[usable], lo, hi, None if output is None else output[usable])
    argmin = np.full((n_params, n_params), np.nan)
    argmax = np.full((n_params, n_params), np.nan)
    gamma, plan = np.inf, PartitionPlan(1, 1)
    for _ in range(settings.max_inner_iterations):
        plan = None
        if allow_partition:
            plan = minimal_partition(prior.gamma, lo[A0], hi[A0], lo[A1], hi[A1], prior.max_partitions)
        if plan is None:
            plan = PartitionPlan(1, 1)
        edges = partition_boxes(plan, lo[A0], hi[A0], lo[A1], hi[A1])
        boxes = []
        for a0_lo, a0_hi, a1_lo, a1_hi in edges:
            box_lo, box_hi = lo.copy(), hi.copy()
            box_lo[A0], box_hi[A0], box_lo[A1], box_hi[A1] = a0_lo, a0_hi, a1_lo, a1_hi
            boxes.append((embedding_bound(omega, E_used, a0_lo, a0_hi, a1_hi), box_lo, box_hi))
        # the union over the boxes, a pole's objective solved only where it can move the union
        union = partition_union(problem, boxes, np.asarray(problem.free, dtype=bool), (A1, A0))
        new_lo, new_hi, certificates, unverified = union.lower.copy(), union.upper.copy(), union.certificates, union.unverified
        found = np.isfinite(union.lower)
        argmin[found], argmax[found] = union.argmin[found], union.argmax[found]
        gamma = max([1.0] + [conservatism_ratio(omega, *edges[b]) for b in union.feasible])
        if not np.all(np.isfinite(new_lo)):
            counter.n_solves += problem.n_solves
            # diagnose on every informative point, inactive ones included: the point at fault may
            # sit where this mode's constraint is slack (it corrupted another mode's bounds)
            finite = np.isfinite(E)
            w_f, g_f, E_f = omega_all[finite], g_mode[finite], E[finite]
            out_f = None if output is None else output[finite]
            full = OneModeProblem(w_f, g_f, lo, hi, out_f)
            sol = full.bound_box(embedding_bound(w_f, E_f, lo[A0], hi[A0], hi[A1]), lo, hi)
            certs = [sol.certificate] if not sol.feasible else certificates
            _raise_inconsistent(w_f, g_f, E_f, lo, hi, certs, mode_index, out_f, names, prior)
        new_lo, new_hi = np.maximum(lo, new_lo), np.minimum(hi, new_hi)
        new_hi = np.maximum(new_lo, new_hi)
        improved = _improved(lo[[A1, A0]], hi[[A1, A0]], new_lo[[A1, A0]], new_hi[[A1, A0]], settings.tolerance)
        lo, hi = new_lo, new_hi
        if not improved:
            break
    counter.n_solves += problem.n_solves
    return lo, hi, argmin, argmax, gamma, plan, tuple(unverified)


def _gamma_note(i: int, gamma: float, plan: PartitionPlan, lo, hi, prior: Prior, settings: IdentifySettings) -> str:
    """Why mode ``i``'s embedding ratio exceeds the target, or ``""`` when it does not."""
    if not gamma > prior.gamma:
        return ""
    head = f"mode {i + 1}: gamma {gamma:.3g} > target {prior.gamma:g}: "
    if not settings.partition:
        return head + "partitioning disabled"
    if lo[A1] <= 0.0:
        return head + "the a1 lower bound is 0 (damping not bounded away from zero by the data), so no finite partition exists (Assumption 3.1)"
    need = minimal_partition(prior.gamma, lo[A0], hi[A0], lo[A1], hi[A1], 10 * prior.max_partitions)
    if need is None:
        return head + f"more than {10 * prior.max_partitions} partitions would be needed (max_partitions = {prior.max_partitions})"
    if need.count > prior.max_partitions:
        return head + f"{need.n0} x {need.n1} = {need.count} partitions needed > max_partitions = {prior.max_partitions}"
    return head + f"partition {plan.n0} x {plan.n1} ran on bounds that have shrunk since (run again with these bounds as previous)"


def _effective_bound(R: np.ndarray, mismatch: np.ndarray, mode: int) -> np.ndarray:
    """``E_i = R + sum_{k != i} |g_hat_k - g_k|_max`` (right side of eq. 3.11)."""
    others = np.delete(mismatch, mode, axis=0)
    return R + others.sum(axis=0)


def _improved(lo, hi, new_lo, new_hi, tol) -> bool:
    width = np.maximum(hi - lo, 1e-300)
    return bool(np.any((hi - lo) - (new_hi - new_lo) > tol * width))


def _by_band(omega: np.ndarray, prior: Prior | None, mode_index: int) -> str:
    """``"w1, w2 rad/s"``, with the points in another mode's prior band marked as such: the
    one-mode problem of mode i subtracts the other modes' models at every point, so a point near
    mode 5 can make mode 6's problem fail (a user once read such a message as mode 6's fault)."""
    omega = np.sort(np.asarray(omega, dtype=float))
    if prior is None:
        return ", ".join(f"{w:.6g}" for w in omega) + " rad/s"
    owner = _assign_points_to_modes(prior, omega)
    parts = []
    for m in dict.fromkeys(owner.tolist()):
        pts = ", ".join(f"{w:.6g}" for w in omega[owner == m])
        parts.append(pts + (f" (mode {m + 1}'s band)" if m != mode_index else ""))
    return "; ".join(parts) + " rad/s"


def _raise_inconsistent(omega, g, E, lo, hi, certificates: list, mode_index: int, output=None, names: tuple[str, ...] = (),
                        prior: Prior | None = None):
    """Name the points in the infeasibility certificate, and those whose removal alone helps
    (with several outputs: which output each point belongs to)."""
    weight = np.zeros(omega.size)
    for cert in certificates:
        if cert is not None and cert.size == omega.size and np.max(cert) > 0:
            weight = np.maximum(weight, cert / np.max(cert))
    involved = np.flatnonzero(weight > 1e-3) if np.any(weight > 1e-3) else np.arange(omega.size)
    suspects = []
    C = embedding_bound(omega, E, lo[A0], hi[A0], hi[A1])
    for j in involved:  # leave-one-out over the certificate's points (a handful of solves)
        keep = np.arange(omega.size) != j
        if keep.any() and OneModeProblem(omega[keep], g[keep], lo, hi, None if output is None else output[keep]).is_feasible(C[keep], lo, hi):
            suspects.append(omega[j])
    if output is None:
        where = f"the data points at omega = {_by_band(omega[involved], prior, mode_index)}"
    else:
        groups = []
        for k in np.unique(output[involved]):
            pts = np.sort(omega[involved][output[involved] == k])
            groups.append(f"output {names[k] if k < len(names) else k + 1} at omega = {_by_band(pts, prior, mode_index)}")
        where = "the data points of " + "; ".join(groups) + " (the outputs cannot share this mode's poles)"
    hint = ""
    if suspects:
        after = ("(other modes may still fail: --reject-outliers finds every such point in one run)" if output is None
                 else "(the sensors disagree there: check their bounds and calibration)")
        hint = ("; removing the point at " + _by_band(suspects, prior, mode_index).replace(", ", " or ")
                + f" alone restores consistency of mode {mode_index + 1} {after}")
    raise InconsistentDataError(
        f"mode {mode_index + 1}: no parameters within the prior fit {where} "
        f"within their error bounds{hint} (check those measurements and bounds, or widen the prior)",
        omegas_rad_s=np.sort(omega[involved]),
        mode_index=mode_index,
        suspects_rad_s=suspects,
    )


def identify(data: FrequencyData, prior: Prior, previous: IntervalModel | None = None,
             settings: IdentifySettings = IdentifySettings()) -> IdentificationResult:
    """Guaranteed interval bounds on every modal parameter (Algorithms 3.1 and 3.2).

    Parameters
    ----------
    data : FrequencyData
        Measured ``g(j omega)`` and the absolute bound on each point's total error.
    prior : Prior
        A priori bounds (natural frequency, damping ratio, optional residue bounds), the target
        embedding ratio ``gamma`` and ``max_partitions``.
    previous : IntervalModel, optional
        Bounds from a previous iteration; the result lies inside them (eq. 5.4-5.5).
    settings : IdentifySettings

    Returns
    -------
    IdentificationResult

    Raises
    ------
    InconsistentDataError
        When no parameters in the prior box fit the data (names the frequencies involved).
    InputFormatError
        When residues cannot be bounded from the data and the prior gives no residue bounds.

    Examples
    --------
    >>> from setmem_hil.io.procedure import thesis_beam_prior
    >>> from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment
    >>> from setmem_hil.model.frequency_data import FrequencyData
    >>> beam = SimulatedBeamExperiment(seed=1)
    >>> data = FrequencyData.from_measurements(beam.measure_many([0.99, 1.0, 1.01, 6.2, 6.27, 6.33, 17.4, 17.55, 17.7]))
    >>> result = identify(data, thesis_beam_prior())
    >>> bool(result.model.contains(beam.modelled_truth).all())
    True
    """
    box = prior.initial_bounds()
    if previous is not None:
        if previous.lower.shape != box.lower.shape:
            raise InputFormatError("previous bounds", "", f"expected {box.n_modes} modes, found {previous.n_modes}")
        box = box.intersect(previous)
    res = {name: prior.residuals.bounds(name) for name in prior.residuals.enabled}
    if res:
        box, res = bootstrap_residue_bounds(data, box, res)
    else:
        box = bootstrap_residue_bounds(data, box)
    lo, hi = box.lower.copy(), box.upper.copy()
    n = box.n_modes
    counter = _SolveCounter()
    optimizers = np.full((n, 4, 2, 4), np.nan)
    gammas = np.full(n, np.inf)
    plans = [PartitionPlan(1, 1)] * n
    last_unverified: list[tuple[str, ...]] = [()] * n
    R = data.bound
    iterations = _outer_loop([data], lo, hi, res, prior, settings, counter, optimizers, gammas, plans, last_unverified, ())
    groups = []
    if settings.groups and n > 1:
        groups = close_groups(mode_mismatch_bounds(IntervalModel(lo, hi), data.omega_rad_s), data.bound,
                              _assign_points_to_modes(prior, data.omega_rad_s), _band_centres(prior),
                              np.array([m.zeta_max for m in prior.modes]))
    group_unverified: dict[int, str] = {}
    group_pieces: dict[tuple, tuple] = {}
    for _ in range(settings.group_rounds if groups else 0):
        for group in groups:
            group_pieces[tuple(group)] = _identify_group_in_place(
                data, lo, hi, res, list(group), prior, counter, group_unverified, GroupSettings(max_boxes=settings.group_boxes))
        iterations += _outer_loop([data], lo, hi, res, prior, settings, counter, optimizers, gammas, plans, last_unverified, ())
    if groups:
        _polish_every_mode(data, lo, hi, res, prior, counter, group_unverified, groups, group_pieces, settings)
    for i, reason in group_unverified.items():
        last_unverified[i] = tuple(last_unverified[i]) + (reason,)
    witness = ratios_to_reach = shaved = None
    if settings.witness:
        # closely spaced modes were bounded together by the groups and the polish (within 1.17 of the
        # exact set on the close-mode benchmark, issue 47); their slabs are costly (a pair's
        # relaxation is loose on coarse boxes: 6 -> 57 s on one test's pairs): shaving is for the
        # separated modes that the split alone bounded
        witness, ratios_to_reach, shaved = _witnessed_and_shaved(data, lo, hi, res, shave=settings.shave and not groups,
                                                                 hints=_optimizer_hints(optimizers, lo, hi))
        if not witness.fits:
            last_unverified = [tuple(u) + ("no parameter point of the box was found to fit every point: "
                                           + witness.describe_misfit(),) for u in last_unverified]

    model = IntervalModel(lo, hi)
    mismatch = mode_mismatch_bounds(model, data.omega_rad_s)
    E_all = np.array([_effective_bound(R, mismatch, i) + residual_mismatch(res, data.omega_rad_s) for i in range(n)])
    C_all = np.array([embedding_bound(data.omega_rad_s, E_all[i], lo[i, A0], hi[i, A0], hi[i, A1]) for i in range(n)])
    ratios = _mismatch_ratios(prior, data, E_all)
    notes = tuple(_gamma_note(i, gammas[i], plans[i], lo[i], hi[i], prior, settings) for i in range(n))
    fixed = model.fixed
    optimizers[fixed[:, :, None, None].repeat(2, axis=2).repeat(4, axis=3)] = np.nan
    return IdentificationResult(
        model=model,
        embedding_gamma=gammas,
        mismatch_ratio=ratios,
        iterations=iterations,
        n_solves=counter.n_solves,
        partitions=tuple((p.n0, p.n1) for p in plans),
        effective_bound=E_all,
        embedding_bound=C_all,
        optimizers=optimizers,
        partitioned=np.array([p.count > 1 for p in plans]),
        verified=np.array([not u for u in last_unverified], dtype=bool),
        unverified_reason=tuple("; ".join(u) for u in last_unverified),
        notes=tuple(note for note in notes if note),
        residuals={name: (float(a), float(b)) for name, (a, b) in res.items()},
        groups=tuple(tuple(grp) for grp in groups),
        witness=witness,
        reach_ratio=ratios_to_reach,
        shaved=shaved,
    )


def _polish_every_mode(data, lo, hi, res, prior, counter, unverified: dict, groups, group_pieces: dict,
                       settings: IdentifySettings) -> None:
    """After the groups' rounds: every mode contracted together (:func:`_polish`), in place."""
    # every mode together, from the box reached: a contraction that removes the rest of the
    # split's conservatism (a far mode's box bounded by the pair's mismatch); no deep search.
    # Then once more from the groups' last leaves (a few hulls along each pair's set), which
    # keep how a pair's parameters go together; it starts from the first one's box, so it can
    # only narrow it.
    grouped = tuple(sorted({k for group in groups for k in group}))
    pairs = tuple(tuple(group) for group in groups if len(group) == 2)
    lone_mode = len(grouped) < lo.shape[0]
    budget = settings.polish_boxes
    if budget is None:
        budget = POLISH_BOXES_LONE_MODE if lone_mode else POLISH_BOXES
    second_order = lone_mode if settings.polish_second_order is None else settings.polish_second_order
    _polish(data, lo, hi, res, prior, counter, unverified, grouped, pairs, budget, second_order)
    pieces = polish_pieces(group_pieces, lo, hi, settings.polish_pieces)
    if pieces:
        _polish(data, lo, hi, res, prior, counter, unverified, grouped, pairs, budget, second_order, pieces)


def _optimizer_hints(optimizers: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
    """Models to start a witness search from when its own starts found none: the box's midpoint
    with one mode replaced by Algorithm 3.2's solver point at one of that mode's bounds (inside the
    mode's embedding, so near its feasible set), each mode in turn."""
    mid = 0.5 * (lo + hi)
    hints = []
    for p in range(optimizers.shape[1]):
        for side in range(2):
            for i in range(optimizers.shape[0]):
                x = optimizers[i, p, side]
                if np.all(np.isfinite(x)):
                    h = mid.copy()
                    h[i] = np.clip(x, lo[i], hi[i])
                    hints.append(h)
    return hints


def _witnessed_and_shaved(data: FrequencyData, lo: np.ndarray, hi: np.ndarray, res: dict, shave: bool = True, hints=()):
    """A witness of the box (:func:`witness.find_witness`), and where one fits, every interval
    shaved to the witnesses' reach (:func:`shaving.shave`, in place). Returns ``(witness,
    reach ratios or None, shave report or None)``.

    Without a witness the whole model's relaxation is asked whether the box is empty
    (:func:`shaving.proved_empty`): proved, it is an :class:`InconsistentDataError`; not proved, the
    result is returned unverified. Without ``shave`` (the setting off, or closely spaced modes
    bounded by their groups) and beyond the shaving's cost rule (:func:`shaving.within_cost_rule`)
    only the witness is sought. The reach is taken with the residual terms at the witness's
    values (its points truly fit);
    the shaving itself sees the data less the terms' midpoints with their mismatch added to the
    bound (as the polish does), so it stays guaranteed over the terms' whole intervals. ``hints``
    (:func:`_optimizer_hints`) are tried only when the search's own starts found no witness."""
    w = data.omega_rad_s
    witness = find_witness(w, data.response, data.bound, lo, hi, res)
    if not witness.fits and len(hints):
        # a thin feasible set (a lightly damped lone mode seen near its peak only) the centre and
        # the draws can miss: the solver's own points next (only then, so a witness found before stays)
        second = find_witness(w, data.response, data.bound, lo, hi, res, hints=hints, starts=len(hints) + 1)
        if second.misfit < witness.misfit:
            witness = second
    g_all, E_all = data.response - residual_midpoint_response(res, w), data.bound + residual_mismatch(res, w)
    if not witness.fits:
        if proved_empty(w, g_all, E_all, lo, hi):
            binding = np.array(witness.binding_omega_rad_s)
            raise InconsistentDataError(
                f"modes {', '.join(str(k + 1) for k in range(lo.shape[0]))} (together): no parameters within the prior fit "
                f"the data within their error bounds, proved for the whole model though each mode alone fits; "
                f"{witness.describe_misfit()} (check those measurements and bounds, or the model: a mode or effect missing?)",
                omegas_rad_s=np.sort(binding) if binding.size else w, mode_index=0,
            )
        return witness, None, None
    if not shave or not within_cost_rule(lo, hi, data.bound):
        return witness, None, None
    g_witness = data.response - residual_response(witness.residuals, w)
    inner_lo, inner_hi = inner_extent(w, g_witness, data.bound, lo, hi, witness.x)
    report = shave_box(w, g_all, E_all, lo, hi, inner_lo, inner_hi)
    lo[...], hi[...] = report.lower, np.maximum(report.lower, report.upper)
    return witness, reach_ratios(lo, hi, inner_lo, inner_hi), report


def _polish(data, lo, hi, res, prior, counter, unverified, grouped: tuple, pairs: tuple, budget: int,
            second_order: bool, pieces: tuple = ()) -> None:
    """Every mode contracted together (in place), in ``budget`` boxes beyond ``pieces``
    (``IdentifySettings.polish_boxes``), the ``pairs`` (the groups of two) lifted at the points they blur
    (:func:`mode_group._multiplied_modes`). A split cuts the parameter of a mode in ``grouped``
    (the groups' modes) widest against the witnesses' hull (:func:`mode_group._relatively_widest`);
    where a mode outside the groups sticks out furthest, first the widest b1 of a grouped mode while
    it is wider than ``POLISH_B1_SHARE`` of the polished box's
    (:func:`mode_group._wide_residue_slope`). With ``second_order`` the points in the divided form
    keep each mode's bilinear term (:func:`mode_group.second_order_group`, stop 63)."""
    _identify_group_in_place(data, lo, hi, res, list(range(lo.shape[0])), prior, counter, unverified,
                             GroupSettings(max_boxes=budget + len(pieces), search_points=POLISH_POINTS,
                                           subset_stage=False, contract_at_budget=True, split_among=grouped,
                                           cut_wide_b1=POLISH_B1_SHARE, lift_pairs=pairs, second_order=second_order),
                             pieces)


def polish_pieces(group_pieces: dict, lo: np.ndarray, hi: np.ndarray, most: int = POLISH_PIECES) -> tuple:
    """Boxes of every mode whose union holds every parameter in ``lo, hi`` that fits: each group's
    last leaves (``group_pieces``: group -> pieces, each certified to hold its part of the set)
    merged into at most ``most ** (1 / groups)`` hulls (:func:`mode_group.piece_hulls`), one from
    each group in every combination, the other modes at ``lo, hi``. Empty when no group left
    pieces, or when ``most`` leaves fewer than two per group (more than eight groups at 256)."""
    usable = {group: p for group, p in group_pieces.items() if p}
    per_group = int(most ** (1.0 / max(len(usable), 1)) + 1e-9)
    if not usable or per_group < 2:
        return ()
    # each group's hulls clipped to the box once (an empty one drops out), then every combination
    clipped = []
    for group, pieces in usable.items():
        rows = list(group)
        boxes = [(np.maximum(lo[rows], p_lo), np.minimum(hi[rows], p_hi)) for p_lo, p_hi in piece_hulls(pieces, per_group)]
        clipped.append((rows, [(b_lo, b_hi) for b_lo, b_hi in boxes if np.all(b_lo <= b_hi)]))
    combos = []
    for choice in itertools.product(*(boxes for _, boxes in clipped)):
        c_lo, c_hi = lo.copy(), hi.copy()
        for (rows, _), (p_lo, p_hi) in zip(clipped, choice):
            c_lo[rows], c_hi[rows] = p_lo, p_hi
        combos.append((c_lo, c_hi))
    return tuple(combos)


def _identify_group_in_place(data: FrequencyData, lo: np.ndarray, hi: np.ndarray, res: dict, group: list[int],
                             prior: Prior, counter: _SolveCounter, unverified: dict,
                             group_settings: GroupSettings = GroupSettings(), pieces: tuple = ()) -> tuple:
    """The group's modes bounded jointly (:mod:`setmem_hil.identification.mode_group`): the data
    minus every other mode's midpoint, the bound plus their worst-case mismatch (eq. 3.11 with the
    group in place of one mode); the result is intersected with ``lo, hi`` (never loosens).
    ``pieces`` (boxes of the group covering its feasible set) start the search. Returns the
    search's last leaves (:attr:`GroupResult.pieces`)."""
    current = IntervalModel(lo, hi)
    w = data.omega_rad_s
    mismatch = mode_mismatch_bounds(current, w)
    outside = [k for k in range(lo.shape[0]) if k not in group]
    estimates = current.midpoint.mode_responses(w)
    g_group = data.response - estimates[outside].sum(axis=0) - residual_midpoint_response(res, w)
    E = data.bound + mismatch[outside].sum(axis=0) + residual_mismatch(res, w)
    try:
        found = identify_group(w, g_group, E, lo[group], hi[group], group_settings, pieces)
    except GroupProvedEmpty:
        raise InconsistentDataError(
            f"modes {', '.join(str(k + 1) for k in group)} (identified together): no parameters within the prior fit the "
            f"data points at omega = {_by_band(w, prior, group[0])} within their error bounds "
            "(check those measurements and bounds, or widen the prior)",
            omegas_rad_s=w, mode_index=group[0],
        ) from None
    counter.n_solves += found.n_solves
    lo[group] = np.maximum(lo[group], found.lower)
    hi[group] = np.maximum(lo[group], np.minimum(hi[group], found.upper))
    for k in group:
        if found.verified:
            # every bound of this search is certified on a box that holds the data's set (an
            # earlier round's uncertified bound was kept as an outer bound), so its flag is spent
            unverified.pop(k, None)
        else:
            unverified[k] = f"group {[j + 1 for j in group]}: {found.unverified_reason}"
    return found.pieces


def _mismatch_ratios(prior: Prior, data: FrequencyData, E_all: np.ndarray) -> np.ndarray:
    """Per mode, the largest ``E_i / R`` over the points in that mode's band (section 3.2.3):
    how much the other modes' mismatch inflates the data's bound; 1 where a mode owns no point."""
    owner = _assign_points_to_modes(prior, data.omega_rad_s)
    ratios = np.ones(E_all.shape[0])
    for i in range(E_all.shape[0]):
        pts = (owner == i) & (data.bound > 0)
        if pts.any():
            ratios[i] = float(np.max(E_all[i, pts] / data.bound[pts]))
    return ratios


def _outer_loop(datas: list[FrequencyData], lo: np.ndarray, hi: np.ndarray, res: dict, prior: Prior,
                settings: IdentifySettings, counter: _SolveCounter, optimizers: np.ndarray, gammas: np.ndarray,
                plans: list, last_unverified: list, names: tuple[str, ...]) -> int:
    """Algorithm 3.1's passes, updating ``lo, hi`` (shape ``(n_modes, 2 + 2K)``) in place.

    One output is the thesis's algorithm. Several (issue 25): for mode ``i`` each output ``k``
    gives its own points, the data minus the other modes' midpoints *of that output* (eq. 3.11)
    and its own cross-mode mismatch, and all of them enter one conic program with the shared
    poles and each output's residues. Returns the number of passes.
    """
    n, several = lo.shape[0], len(datas) > 1
    iterations = 0
    allow_partition = False
    for _ in range(settings.max_outer_iterations):
        iterations += 1
        any_improved = False
        for i in range(n):
            parts = []
            for k, data in enumerate(datas):
                cols = output_columns(k)
                current = IntervalModel(lo[:, cols], hi[:, cols])
                E = _effective_bound(data.bound, mode_mismatch_bounds(current, data.omega_rad_s), i) + residual_mismatch(res, data.omega_rad_s)
                estimates = current.midpoint.mode_responses(data.omega_rad_s)
                g_mode = data.response - (estimates.sum(axis=0) - estimates[i]) - residual_midpoint_response(res, data.omega_rad_s)  # eq. (3.11)
                parts.append((data.omega_rad_s, g_mode, E))
            if several:
                omega = np.concatenate([w for w, _, _ in parts])
                g_mode = np.concatenate([g for _, g, _ in parts])
                E = np.concatenate([e for _, _, e in parts])
                output = np.concatenate([np.full(w.size, k) for k, (w, _, _) in enumerate(parts)])
            else:
                (omega, g_mode, E), output = parts[0], None
            new_lo, new_hi, amin, amax, gamma, plan, unverified = _one_mode_pass(
                omega, g_mode, E, lo[i], hi[i], prior, allow_partition and settings.partition,
                settings, i, counter, output, names,
            )
            any_improved |= _improved(lo[i], hi[i], new_lo, new_hi, settings.tolerance)
            lo[i], hi[i] = new_lo, new_hi
            optimizers[i, :, 0, :], optimizers[i, :, 1, :] = amin, amax
            gammas[i], plans[i] = gamma, plan
            last_unverified[i] = unverified
        for name in res:  # the residual terms (one output only): extra linear blocks (residual_terms)
            data = datas[0]
            current = IntervalModel(lo, hi)
            E_r = data.bound + mode_mismatch_bounds(current, data.omega_rad_s).sum(axis=0) + residual_mismatch(res, data.omega_rad_s, exclude=name)
            g_r = (data.response - current.midpoint.mode_responses(data.omega_rad_s).sum(axis=0)
                   - residual_midpoint_response(res, data.omega_rad_s, exclude=name))
            r_lo, r_hi = bound_residual(name, data.omega_rad_s, g_r, E_r, *res[name])
            any_improved |= _improved(np.array([res[name][0]]), np.array([res[name][1]]), np.array([r_lo]), np.array([r_hi]), settings.tolerance)
            res[name] = (r_lo, r_hi)
        if not any_improved:
            if allow_partition or not settings.partition:
                break
            allow_partition = True  # converged without partitioning: now partition where affordable
    return iterations


@dataclass(frozen=True)
class MultiOutputResult:
    """Intervals of a modal model seen by several outputs with shared poles (issue 25).

    Attributes
    ----------
    models : tuple of IntervalModel
        One per output, in the order given: the same ``a1, a0`` intervals (shared poles) and
        that output's ``b1, b0``.
    names : tuple of str
        The outputs' names.
    embedding_gamma, mismatch_ratio, verified, unverified_reason, notes, iterations, n_solves, partitions
        As in :class:`IdentificationResult`, per mode over all outputs (``mismatch_ratio`` the
        largest over the outputs; ``verified`` covers every bound of the mode).
    """

    models: tuple[IntervalModel, ...]
    names: tuple[str, ...]
    embedding_gamma: np.ndarray
    mismatch_ratio: np.ndarray
    iterations: int
    n_solves: int
    partitions: tuple[tuple[int, int], ...]
    verified: np.ndarray
    unverified_reason: tuple[str, ...]
    notes: tuple[str, ...] = ()
    optimizers: np.ndarray | None = None  # (n_modes, 2 + 2K, 2, 2 + 2K): the joint argmin/argmax

    def for_output(self, k: int) -> IdentificationResult:
        """Output ``k`` seen as a one-output result (its model, and the joint optimisers restricted
        to its parameters ``a1, a0, b1_k, b0_k``): what the input design of chapter 4 reads."""
        cols = output_columns(k)
        n = self.models[k].n_modes
        opt = np.full((n, 4, 2, 4), np.nan) if self.optimizers is None else self.optimizers[:, cols][:, :, :, cols]
        return IdentificationResult(
            model=self.models[k], embedding_gamma=self.embedding_gamma, mismatch_ratio=self.mismatch_ratio,
            iterations=self.iterations, n_solves=self.n_solves, partitions=self.partitions,
            effective_bound=np.zeros((n, 0)), embedding_bound=np.zeros((n, 0)), optimizers=opt,
            verified=self.verified, unverified_reason=self.unverified_reason, notes=self.notes,
        )

    @property
    def model(self) -> IntervalModel:
        """The first output's model (readers of one-output results keep working)."""
        return self.models[0]

    def to_document(self) -> dict:
        """RESULT.json: ``modes`` as for one output (the first output's residues) plus, per mode,
        ``"outputs": [{"name", "b1": [lo, hi], "b0": [lo, hi]}, ...]`` and top-level ``"outputs"``."""
        from setmem_hil.io.result_file import result_document

        doc = result_document(
            self.models[0], self.embedding_gamma, self.mismatch_ratio, self.iterations,
            n_solves=int(self.n_solves), partitions=[list(p) for p in self.partitions],
            verified=[bool(v) for v in self.verified], unverified_reason=list(self.unverified_reason),
            conservatism_notes=list(self.notes),
        )
        for i, mode in enumerate(doc["modes"]):
            mode["outputs"] = [{"name": name, "b1": [float(m.lower[i, B1]), float(m.upper[i, B1])],
                                "b0": [float(m.lower[i, B0]), float(m.upper[i, B0])]} for name, m in zip(self.names, self.models)]
        doc["outputs"] = list(self.names)
        return doc


def _check_poles_intersect(models: list[IntervalModel], datas: list[FrequencyData], prior: Prior, names: tuple[str, ...]) -> None:
    """Outputs identified alone whose pole intervals do not even intersect cannot share poles:
    exit 3 naming the mode, the two outputs, their intervals and the points in that mode's band."""
    for i in range(prior.n_modes):
        for col, what in ((A1, "a1 (damping)"), (A0, "a0 (natural frequency squared)")):
            lo = np.array([m.lower[i, col] for m in models])
            hi = np.array([m.upper[i, col] for m in models])
            k_lo, k_hi = int(np.argmax(lo)), int(np.argmin(hi))
            if lo[k_lo] <= hi[k_hi]:
                continue
            parts = []
            for k in (k_hi, k_lo):
                owner = _assign_points_to_modes(prior, datas[k].omega_rad_s)
                pts = datas[k].omega_rad_s[owner == i]
                parts.append(f"output {names[k]} ({what} in [{lo[k]:.6g}, {hi[k]:.6g}] from its points at omega = "
                             f"{', '.join(f'{w:.6g}' for w in pts)} rad/s)")
            raise InconsistentDataError(
                f"mode {i + 1}: the outputs cannot share poles: " + " and ".join(parts) + " do not intersect "
                "(check those sensors' bounds and calibration, or identify them apart)",
                omegas_rad_s=np.concatenate([datas[k].omega_rad_s for k in (k_hi, k_lo)]), mode_index=i,
            )


def identify_outputs(datas: list[FrequencyData], priors: list[Prior], names: list[str] | None = None,
                     previous: list[IntervalModel] | None = None,
                     settings: IdentifySettings = IdentifySettings()) -> MultiOutputResult:
    """Guaranteed intervals of a modal model from several outputs with shared poles (issue 25).

    Every mode's one-mode problem holds the shared ``(a1, a0)`` and one ``(b1, b0)`` pair per
    output; each output's points are cones of eq. (3.26) on its own residues, with that output's
    cross-mode mismatch (eq. 3.11). Partitioning (3.2.3), the certified bounds and the
    normalisation are those of one output; with one output this is :func:`identify`, bit for bit.

    Parameters
    ----------
    datas : list of FrequencyData
        One per output (frequencies may differ between outputs).
    priors : list of Prior
        One per output: the same modes (frequency and damping bands), each with that output's
        residue bounds.
    names : list of str, optional
        The outputs' names (default ``output 1``, ``output 2``...).
    previous : list of IntervalModel, optional
        Bounds from a previous iteration, one per output; the result lies inside them.

    Raises
    ------
    InconsistentDataError
        When the outputs cannot share poles within their bounds: names the mode, the outputs and
        the frequencies.
    InputFormatError
        Priors that disagree on the modes, or ``[residuals]`` terms with several outputs.
    """
    K = len(datas)
    names = tuple(names) if names else tuple(f"output {k + 1}" for k in range(K))
    if K == 0 or len(priors) != K or len(names) != K:
        raise InputFormatError("identify", "outputs", f"{K} data sets, {len(priors)} priors and {len(names)} names: expected one of each per output")
    if K == 1:
        single = identify(datas[0], priors[0], None if previous is None else previous[0], settings)
        return MultiOutputResult((single.model,), names, single.embedding_gamma, single.mismatch_ratio, single.iterations,
                                 single.n_solves, single.partitions, single.verified, single.unverified_reason, single.notes)
    prior = priors[0]
    for k, other in enumerate(priors[1:], start=2):
        if [(m.omega_min, m.omega_max, m.zeta_max) for m in other.modes] != [(m.omega_min, m.omega_max, m.zeta_max) for m in prior.modes]:
            raise InputFormatError("prior", f"output {k}", "the modes' frequency and damping bands must be the same for every output (shared poles)")
    if prior.residuals.enabled:
        raise InputFormatError("prior", "[residuals]", "residual terms with several outputs are not supported yet; identify the outputs one at a time")
    # start from each output identified alone: the joint set lies inside every one of them, so
    # the shared pole intervals can never end wider than the narrowest single-output interval
    # (the joint passes alone follow another path to their fixed point and may stop 1e-3 short)
    # (independent problems: threads, since the conic solver spends most of its time outside the
    # GIL; 1.6 s against 2.3 s for the public beam's two points on two cores)
    boxes, counter = [], _SolveCounter()
    with ThreadPoolExecutor(max_workers=max(1, min(K, os.cpu_count() or 1))) as pool:
        singles = [pool.submit(identify, data, p, None if previous is None else previous[k], settings)
                   for k, (data, p) in enumerate(zip(datas, priors))]
    for k, single in enumerate(singles):  # in output order: the first output that fails is named
        try:
            alone = single.result()
        except InconsistentDataError as exc:  # one sensor alone already contradicts the prior: say which
            raise InconsistentDataError(f"output {names[k]}: {exc}", omegas_rad_s=exc.omegas_rad_s, mode_index=exc.mode_index,
                                        suspects_rad_s=exc.suspects_rad_s) from None
        boxes.append(alone.model)
        counter.n_solves += alone.n_solves
    _check_poles_intersect(boxes, datas, prior, names)
    n = prior.n_modes
    lo = np.empty((n, 2 + 2 * K))
    hi = np.empty((n, 2 + 2 * K))
    lo[:, :2] = np.max([b.lower[:, :2] for b in boxes], axis=0)  # the poles: what every output allows
    hi[:, :2] = np.min([b.upper[:, :2] for b in boxes], axis=0)
    for k, b in enumerate(boxes):
        lo[:, 2 + 2 * k: 4 + 2 * k], hi[:, 2 + 2 * k: 4 + 2 * k] = b.lower[:, 2:], b.upper[:, 2:]
    P = 2 + 2 * K
    optimizers = np.full((n, P, 2, P), np.nan)
    gammas = np.full(n, np.inf)
    plans = [PartitionPlan(1, 1)] * n
    last_unverified: list[tuple[str, ...]] = [()] * n
    iterations = _outer_loop(list(datas), lo, hi, {}, prior, settings, counter, optimizers, gammas, plans, last_unverified, names)
    models = tuple(IntervalModel(lo[:, output_columns(k)], hi[:, output_columns(k)]) for k in range(K))
    owner_ratios = np.ones(n)
    for data, model in zip(datas, models):
        mismatch = mode_mismatch_bounds(model, data.omega_rad_s)
        E_all = np.array([_effective_bound(data.bound, mismatch, i) for i in range(n)])
        owner_ratios = np.maximum(owner_ratios, _mismatch_ratios(prior, data, E_all))
    notes = tuple(_gamma_note(i, gammas[i], plans[i], lo[i, output_columns(0)], hi[i, output_columns(0)], prior, settings) for i in range(n))
    return MultiOutputResult(
        models=models, names=names, embedding_gamma=gammas, mismatch_ratio=owner_ratios, iterations=iterations,
        n_solves=counter.n_solves, partitions=tuple((p.n0, p.n1) for p in plans),
        verified=np.array([not u for u in last_unverified], dtype=bool),
        unverified_reason=tuple("; ".join(u) for u in last_unverified), notes=tuple(note for note in notes if note),
        optimizers=optimizers,
    )
