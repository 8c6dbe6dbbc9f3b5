"""Closely spaced modes identified together: a certified branch-and-bound (thesis 7.2, our method).

Chapter 3 splits the multi-mode problem into one-mode problems (eq. 3.11): mode ``i`` is fitted
with its neighbours' responses treated as uncertainty bounded by their current boxes (Lemma 3.1).
When two modes are a few percent apart, each one's mismatch at the other's resonance exceeds the
data's bound, neither box shrinks, and the iteration stops at the prior (the thesis's first item of
future work, section 7.2: "identify the parameters of more than one mode at a time").

Here the modes of a group are bounded jointly. The parameters ``x`` are the group's
``(a1, a0, b1, b0)`` per mode; each point requires (eq. 3.10 for the group, the other modes'
mismatch already in ``E``)

    |g_j - sum_i N_i(j w_j) / D_i(j w_j)| <= E_j,   N_i = b1_i j w + b0_i,  D_i = -w^2 + a1_i j w + a0_i.

Relaxation of one box (mean-value form, our choice). Around the box centre ``c`` each mode's
term is its first-order Taylor expansion plus a remainder whose size has a closed form:

    N / D = N_c / D_c + dN / D_c - N_c dD / D_c^2 + R,   R = -(dN D_c - N_c dD) dD / (D D_c^2),

so ``|R| <= (|dN| |D_c| + |N_c| |dD|) |dD| / (min_box |D| |D_c|^2)`` with ``|dN|, |dD|`` their
largest values over the box and ``min |D|`` that of eq. (3.35). Every point becomes the affine
second-order cone ``|r_c + J (x - c)| <= E_j + rho_j`` (``rho_j`` the remainders summed over the
group): a convex outer set of the box's feasible set, whose bounds are certified by the conic
program's dual (:mod:`setmem_hil.identification.certified_cone_program`). A box proved empty by a
checked Farkas certificate is pruned; the others are contracted (bounds intersected, the
expansion re-centred) and split. The remainder shrinks with the square of the box, so the leaves'
bounds approach the linearised exact feasible set (:mod:`setmem_hil.identification.exact_set`) as
they get small.

Coarse boxes of a pair (our choice, issue 47): where that remainder exceeds the point's bound, the
pair's constraint multiplied through by both denominators (the embedding of eq. 3.26 over
``D_1 D_2``) is used instead, exactly: it is bilinear, so each product of a mode-1 parameter with a
mode-2 parameter is a variable of its own in its McCormick envelope (:func:`lifted_pair`). All the
points share the products, which is what prunes boxes whose pole ranges cover both resonances.
Kept as modal parameters plus products, not as the pair's quartic alone: the map from a quartic's
coefficients back to two close poles is ill-conditioned exactly where the modes crowd (a root's
sensitivity grows as the inverse of the poles' distance), and the branch-and-bound on the modal
parameters tightens the envelopes there.

The multiplied forms' right side (stop 59): ``E max_box |Q|`` (eq. 3.34, ``Q`` the multiplied
denominators) is loose to first order in the box; where tighter, ``|Q|`` is bounded instead by an
affine function of the parameters and products, tangent at the centre
(:mod:`setmem_hil.identification.magnitude_bound`), exact to second order.

Second order where it matters (stop 63, the polish where a mode is outside every group): a point in
the divided form keeps each mode's bilinear term ``dN dD / D_c^2`` exactly, the four products of a
mode's residue and pole deviations as shared variables in their McCormick envelopes
(:func:`second_order_group`); the remainder left is third order. A parameter the data fix far
more finely than their bound (a far mode's b1) is widened by any slack in the discs' radii, and
the first-order remainder of a close pair's wide residues at the far mode's lines was that slack.

Where to refine (our choice): best-first on how far a box sticks out of the hull of points checked
to fit (witnesses, :mod:`setmem_hil.identification.feasible_points`); a box within
``settle_fraction`` of that hull's width on every side is a leaf. The witnesses only steer the
search; the guarantee is the certified relaxations'.

Result: the hull of the surviving leaves; every parameter of the group that fits every point
within its bound (and the prior) lies inside it. A bound the solver could not certify keeps its
box's own bound (still an outer bound, only perhaps loose) and is flagged on that box; children
inherit the flags of the bounds they inherit. The answer is reported unverified only where a
flagged bound is the hull's own bound (our choice, stop 54: a flag on a box inside the hull
changes nothing reported, and whether a nearly empty box's solve ends ``PrimalInfeasible`` or
``AlmostPrimalInfeasible`` differs between machines). A flagged bound that sticks out of the
witnesses' hull is split further rather than kept as a leaf.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from setmem_hil.identification import feasible_points
from setmem_hil.identification.certified_cone_program import AffineConeProgram, ProductTerms
from setmem_hil.identification.embedding import denominator_max, denominator_min
from setmem_hil.identification.magnitude_bound import AffineMagnitudeBound, affine_magnitude_bound
from setmem_hil.model.modal_model import A0, A1, B0, B1, near_resonance
from setmem_hil.numerics.in_order_pool import run_in_order

_EPS = np.finfo(float).eps
UNUSABLE_RATIO = 50.0  # a point whose remainder exceeds this many bounds counts as unusable when choosing a split
# the second-order form only where the mean-value remainder is over this share of the bound: its products'
# dense columns made each solve of the 1,200 lines slower (7-8 s -> 10.5 s), and below it the disc's slack is
# a thousandth of the bound (stop 63: 59 of the 1,200 lines of the 3 % pair were above it, 1.5 above 1e-2)
SECOND_ORDER_FLOOR = 1e-3
NEGLIGIBLE_REST = 0.01  # in a group of three: one mode multiplied alone only where the others' remainders are below this share of the bound


@dataclass(frozen=True)
class GroupSettings:
    """Limits of the branch-and-bound (our choices, documented in docs/closely-spaced-modes.md).

    ``fine_ratio``: a leaf is fine when every used point's remainder is at most this fraction of its
    bound (then the relaxation is within about ``1 + fine_ratio`` of the exact set there).
    ``max_boxes``: boxes processed at most; past it the open boxes' hull is kept (still guaranteed).
    ``contraction_tolerance``: relative shrink of the box (any width) that counts as progress.
    ``settle_fraction``: a box that sticks out of the witnesses' hull (points checked to fit,
    :mod:`setmem_hil.identification.feasible_points`) by at most this fraction of the hull's width
    on every side is a leaf: no split can narrow the answer by more.
    ``tight_ratio``: a box whose remainders are all below this fraction of the bound is a leaf
    whatever the witnesses (its relaxation is within about ``1 + tight_ratio`` of the exact set).
    ``divided_ratio``: a point is written in the divided form only where its remainder is at most
    this fraction of its bound (the divided form inflates the point's disc by ``1 + remainder /
    bound``); elsewhere in the lifted (a pair) or mixed form. Until stop 57 it was 1: points with a
    remainder up to the bound had their discs up to doubled. A tenth: fewer boxes and narrower
    intervals on the benchmark but for one case (docs/closely-spaced-modes.md; 1,200 lines of the
    3 % pair 9.6 -> 5.9 s).
    ``contract_at_budget``: past ``max_boxes`` no box is split, and each open box is contracted
    once more before it becomes a leaf, instead of being kept as it stood (a half then holds its
    parent's extent in every parameter but the cut one). The answer can only narrow: every such
    leaf lies inside the box it replaces. Used by the final all-modes contraction (the polish,
    :mod:`setmem_hil.identification.algorithm`), where it costs a few contractions; in the group
    searches themselves it changed which boxes the later stages searched, and a campaign on the
    two-plane cantilever then chose differently and kept its floors longer (stop 57).
    """

    fine_ratio: float = 1.0
    settle_fraction: float = 0.15
    tight_ratio: float = 0.1
    divided_ratio: float = 0.1  # the divided form only where its remainder is at most this fraction of the bound
    max_boxes: int = 400
    max_contractions: int = 8
    contraction_tolerance: float = 0.02
    coarse_contraction_tolerance: float = 0.25
    max_depth: int = 40
    search_points: int = 160
    subset_stage: bool = True  # search a subset of the points first (the hull searched again with all)
    contract_at_budget: bool = False  # past max_boxes: each open box contracted once more, not kept as it stood
    affine_radius: bool = True  # the multiplied denominators' magnitude bounded affinely where tighter (stop 59)
    second_order: bool = False  # the divided form's points to second order (:func:`second_order_group`); the polish's, stop 63
    # the modes whose parameters a split may cut, the one widest against the witnesses' hull
    # (None: the remainders' rule, :func:`_split_dimension`); the polish's, stop 59
    split_among: tuple[int, ...] | None = None
    # with split_among: where a mode outside split_among sticks out furthest, first cut the widest
    # b1 of those modes while it is wider than this share of the searched box's (None: never); the
    # polish's, stop 61 (:func:`_wide_residue_slope`)
    cut_wide_b1: float | None = None
    # in a group of three or more, the close pairs (group-local modes) a point lifts rather than
    # multiplying one mode alone (:func:`_multiplied_modes`); the polish's, stop 61
    lift_pairs: tuple[tuple[int, int], ...] = ()
    workers: int = field(default_factory=lambda: min(2, os.cpu_count() or 1))


class GroupProvedEmpty(ValueError):
    """Every box of a group's search was proved empty by a checked certificate. Its own class:
    callers read it as a proof about the data, and no other error (a ValueError from a bug) may be
    read so (stop 67: a group of one mode raised one from an empty concatenation, and the data were
    called inconsistent although the truth fitted them)."""


@dataclass(frozen=True)
class GroupResult:
    """Bounds of a group's parameters, shape ``(m, 4)`` each, and the search's figures."""

    lower: np.ndarray
    upper: np.ndarray
    verified: bool
    unverified_reason: str
    boxes: int
    leaves: int
    pruned: int
    n_solves: int
    exhausted: bool  # max_boxes reached: the open boxes' hull was kept
    # the last stage's leaves, ``(lower, upper)`` of shape ``(m, 4)`` each: their union holds every
    # parameter that fits (the hull above loses how the modes' parameters go together); empty when
    # a leaf has an uncertified bound (it might not hold its part of the set)
    pieces: tuple = ()


GROUP_MISMATCH_RATIO = 1.0  # a neighbour's worst-case mismatch above the data's bound in a mode's band
OVERLAP_BANDWIDTHS = 3.0  # neighbours closer than this many of their widest admissible half-power bandwidths
MAX_GROUP_SEPARATION = 0.25  # ... and never further apart than this in ln(frequency) (a prior's zeta_max of 0.5)
MAX_GROUP_SIZE = 2  # the search's dimension is 4 per mode: longer chains are cut, the closest pairs first


def close_groups(mismatch: np.ndarray, bound: np.ndarray, owner: np.ndarray, centres: np.ndarray,
                 zeta_max: np.ndarray | None = None) -> list[tuple[int, ...]]:
    """Modes to identify together: neighbours in frequency whose worst-case mismatch (Lemma 3.1)
    exceeds the data's bound at some point of the other's band, after the one-mode iteration has
    reached its fixed point, and whose band centres are closer than ``OVERLAP_BANDWIDTHS`` of the
    wider of their admissible half-power bandwidths (``ln(w_k / w_i) <= 3 max(zeta_max)``, and at
    most ``MAX_GROUP_SEPARATION``: the thesis beam's prior allows zeta up to 0.5). There
    the split of eq. (3.11) treats the neighbour's whole resonance as uncertainty and cannot narrow
    either mode (our criterion for the thesis's 7.2). Modes further apart keep chapter 3's path
    whatever their data: with few points (a campaign's start) a neighbour's box can be wide, but
    then more data, not a joint search, narrows it; and modes many bandwidths apart are fitted well
    one at a time (the hammer test's 810, 851 and 900 Hz: 5 % apart, 4.4 bandwidths of its prior's
    zeta_max 0.0114; identified alone in 6 s, as a group in about a minute).

    Parameters
    ----------
    mismatch : (n, N)
        Each mode's worst-case mismatch at each point.
    bound : (N,)
        The data's bound.
    owner : (N,) int
        The mode whose band each point is in.
    centres : (n,)
        The modes' band centres (to order them in frequency).
    zeta_max : (n,), optional
        The prior's largest damping ratio per mode (default 0.05 for every mode).
    """
    order = [int(i) for i in np.argsort(centres)]
    positive = bound > 0
    linked = []
    for i, k in zip(order, order[1:]):
        zeta = 0.05 if zeta_max is None else max(float(zeta_max[i]), float(zeta_max[k]))
        if np.log(centres[k] / centres[i]) > min(OVERLAP_BANDWIDTHS * zeta, MAX_GROUP_SEPARATION):
            linked.append(False)
            continue
        ratio = 0.0
        for a, b in ((i, k), (k, i)):
            pts = (owner == a) & positive
            if pts.any():
                ratio = max(ratio, float(np.max(mismatch[b, pts] / bound[pts])))
        linked.append(ratio > GROUP_MISMATCH_RATIO)
    return _closest_first(order, linked, centres)


def _closest_first(order: list[int], linked: list[bool], centres: np.ndarray) -> list[tuple[int, ...]]:
    """Linked neighbours joined closest pair first, a group never above ``MAX_GROUP_SIZE``
    (issue 62 item 3: grouping by closeness, not by order). Walking a chain in frequency order cut
    a real pair: with 2-3, 3-4 and 4-5 linked and 3-4 the closest, it made (2, 3) and (4, 5).
    Links join neighbours only, so every group stays a run of consecutive modes."""
    group_of = {m: [m] for m in order}
    links = sorted((float(np.log(centres[order[j + 1]] / centres[order[j]])), j) for j, link in enumerate(linked) if link)
    for _, j in links:
        a, b = group_of[order[j]], group_of[order[j + 1]]
        if a is not b and len(a) + len(b) <= MAX_GROUP_SIZE:
            a.extend(b)
            for m in b:
                group_of[m] = a
    groups = {id(g): g for g in group_of.values() if len(g) > 1}
    return sorted((tuple(sorted(g)) for g in groups.values()), key=lambda g: centres[g[0]])


def _split_modes(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(-1, 4)


def _box_terms(omega_rad_s, lo, hi):
    """``w, j w``, the box's centre, half-width, lower and upper ends per mode, and the mode count."""
    w = np.asarray(omega_rad_s, dtype=float)
    lo, hi = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
    c = _split_modes(0.5 * (lo + hi))
    return w, 1j * w, c, _split_modes(0.5 * (hi - lo)), _split_modes(lo), _split_modes(hi), c.shape[0]


def _mode_at_centre(w, c_mode, h_mode, lo_mode, hi_mode):
    """One mode over its box: ``D_c, N_c, N_c / D_c, |D_c|`` at the centre, the largest ``|dN|,
    |dD|`` over the box and ``min_box |D|`` (eq. 3.35)."""
    D_c = (c_mode[A0] - w * w) + 1j * w * c_mode[A1]
    N_c = c_mode[B0] + 1j * w * c_mode[B1]
    dN = np.hypot(h_mode[B0], w * h_mode[B1])
    dD = np.hypot(h_mode[A0], w * h_mode[A1])
    d_min = denominator_min(w, lo_mode[A0], hi_mode[A0], lo_mode[A1])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        T_c = N_c / D_c
    return D_c, N_c, T_c, np.abs(D_c), dN, dD, d_min


def linearised_group(omega_rad_s, g, lo, hi, with_jacobian: bool = True):
    """The mean-value form of one box (module docstring), or for a mode at a point where it is
    tighter, the disc form: ``1 / D`` in the disc of centre ``1 / D_c`` and radius
    ``|dD| / (min |D| |D_c|)``, so ``N / D = N / D_c + R`` with ``|R| <= (|N_c| + |dN|) |dD| /
    (min |D| |D_c|)`` (no pole term in ``J``; smaller than the mean-value remainder when the box
    spans more than the distance to resonance, ``|dD| > |D_c|``).

    Parameters
    ----------
    omega_rad_s, g : arrays (N,)
    lo, hi : arrays (4 m,)
        The box, per mode ``(a1, a0, b1, b0)``.

    Returns
    -------
    r_c : complex (N,)
        ``g - sum_i N_i / D_i`` at the box centre.
    J : complex (N, 4 m)
        Derivative of the residual ``g - f(x)`` at the centre (``None`` without ``with_jacobian``).
    err : float array (N,)
        Rounding allowance of ``r_c``.
    rho : float array (N,)
        Rigorous bound of the remainder over the box (``inf`` where a denominator can vanish).
    """
    w, jw, c, h, L, H, m = _box_terms(omega_rad_s, lo, hi)
    r_c = np.asarray(g, dtype=complex).copy()
    J = np.zeros((w.size, 4 * m), dtype=complex) if with_jacobian else None
    rho = np.zeros(w.size)
    err = 8 * _EPS * np.abs(r_c)
    for i in range(m):
        D_c, N_c, T_c, abs_D, dN, dD, d_min = _mode_at_centre(w, c[i], h[i], L[i], H[i])
        r_c -= T_c
        err += 8 * _EPS * np.abs(T_c) * (1.0 + (c[i, A0] + w * w + w * c[i, A1]) / abs_D)
        # A centre pole a hair from a measured line overflows these (inf: the point bounds nothing)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            mean_value = (dN * abs_D + np.abs(N_c) * dD) * dD / (d_min * abs_D * abs_D)
            disc = (np.abs(N_c) + dN) * dD / (d_min * abs_D)
            use_disc = disc < mean_value
            term = np.where(use_disc, disc, mean_value)
            term = np.where(dD == 0, 0.0, np.where(d_min > 0, term, np.inf))
            rho += term * (1.0 + 1e-12)  # outward: the bound's own rounding
            if with_jacobian:
                # residual r = g - f: minus the derivative of N / D (no pole term where the disc is used)
                pole_term = N_c / (D_c * D_c)
                J[:, 4 * i + A1] = np.where(use_disc, 0.0, pole_term * jw)
                J[:, 4 * i + A0] = np.where(use_disc, 0.0, pole_term)
                J[:, 4 * i + B1] = -jw / D_c
                J[:, 4 * i + B0] = -1.0 / D_c
    # A point whose expansion is not finite is left to bound nothing (rho = inf): a NaN or inf in a
    # cone's row would reach the conic program (0 x inf where the disc form drops the pole term).
    broken = ~np.isfinite(r_c) | np.isnan(rho)
    if with_jacobian:
        broken |= ~np.all(np.isfinite(J), axis=1)
        J[broken] = 0.0
    r_c[broken], rho[broken], err[broken] = 0.0, np.inf, 0.0
    return r_c, J, err, rho


def second_order_group(omega_rad_s, g, lo, hi):
    """The divided form to second order (our choice, issue 47, stop 63): each mode's term with its
    bilinear part kept exactly, the products of the mode's own residue and pole deviations as
    variables shared by every point (relaxed by their McCormick envelopes, as in
    :func:`lifted_pair`). With ``n = dN`` and ``d = dD`` the deviations from the centre,

        N / D = N_c / D_c + n / D_c - N_c d / D_c^2 - n d / D_c^2 + R2,   R2 = N d^2 / (D_c^2 D),

    so ``|R2| <= (|N_c| + |dN|) |dD|^2 / (|D_c|^2 min_box |D|)``: smaller than the mean-value
    remainder of :func:`linearised_group` by about ``|dD| / |D_c|``. Why: a parameter the data fix
    far more finely than their bound (a far mode's b1, fixed to 3e-4 by 300 intersecting discs)
    is widened by any slack in the discs' radii, however small against the bound. Away from a
    close pair's resonance the pair's remainder is mostly ``n d``: its residues' wide boxes (each
    b1, b0 spans its prior; only their sums are fixed) times its poles' (stop 63, the 0.5 % same-sign
    pair at five times the noise: 3-8 % of the bound at the far mode's lines; with it set to zero
    there, a diagnostic, the far mode's b1 went from 1.65 to 1.35 of the exact set). As a variable
    shared by every point, ``n d`` is held by the data instead of inflating every disc.

    Where a mode's box spans more than the distance to resonance (the disc form of
    :func:`linearised_group` is tighter than ``R2``) that mode keeps the disc form there.

    Returns ``(r_c, J, err, rho, products)`` as :func:`linearised_group`, plus the product
    terms (``None`` when no product is used): the cone is ``|r_c + J (x - c) + K z| <= E + rho``.
    """
    w, jw, c, h, L, H, m = _box_terms(omega_rad_s, lo, hi)
    r_c = np.asarray(g, dtype=complex).copy()
    J = np.zeros((w.size, 4 * m), dtype=complex)
    rho = np.zeros(w.size)
    err = 8 * _EPS * np.abs(r_c)
    K_cols, pairs = [], []
    for i in range(m):
        D_c, N_c, T_c, abs_D, dN, dD, d_min = _mode_at_centre(w, c[i], h[i], L[i], H[i])
        r_c -= T_c
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            second = (np.abs(N_c) + dN) * dD * dD / (d_min * abs_D * abs_D)
            disc = (np.abs(N_c) + dN) * dD / (d_min * abs_D)
            use_disc = disc < second
            term = np.where(use_disc, disc, second)
            term = np.where(dD == 0, 0.0, np.where(d_min > 0, term, np.inf))
            rho += term * (1.0 + 1e-12)
            pole_term = N_c / (D_c * D_c)
            J[:, 4 * i + A1] = np.where(use_disc, 0.0, pole_term * jw)
            J[:, 4 * i + A0] = np.where(use_disc, 0.0, pole_term)
            J[:, 4 * i + B1] = -jw / D_c
            J[:, 4 * i + B0] = -1.0 / D_c
            # residual r = g - f gains + n d / D_c^2; n d in the normalised coordinates y
            inv_D2 = np.where(use_disc, 0.0, 1.0 / (D_c * D_c))
            coefficients = {(B0, A0): h[i, B0] * h[i, A0] + 0j, (B0, A1): jw * h[i, B0] * h[i, A1],
                            (B1, A0): jw * h[i, B1] * h[i, A0], (B1, A1): -(w * w) * h[i, B1] * h[i, A1]}
        err += 8 * _EPS * np.abs(T_c) * (1.0 + (c[i, A0] + w * w + w * c[i, A1]) / abs_D)
        for (p, q), coefficient in coefficients.items():
            column = coefficient * inv_D2
            if np.any(column != 0):
                K_cols.append(column)
                pairs.append((4 * i + p, 4 * i + q))
                err += 8 * _EPS * np.abs(column)
    K = np.array(K_cols).T if K_cols else np.zeros((w.size, 0), dtype=complex)
    broken = ~np.isfinite(r_c) | np.isnan(rho) | ~np.all(np.isfinite(J), axis=1) | ~np.all(np.isfinite(K), axis=1)
    J[broken], K[broken] = 0.0, 0.0
    r_c[broken], rho[broken], err[broken] = 0.0, np.inf, 0.0
    products = ProductTerms(K, np.array(pairs, dtype=int).reshape(-1, 2)) if K_cols else None
    return r_c, J, err, rho, products


def _product_remainder(centres: list, deviations: list) -> np.ndarray:
    """Bound of the terms of order >= 2 of ``prod_k (F_k,c + dF_k)`` given ``|F_k,c|`` and the
    largest ``|dF_k|``: ``prod (|F_c| + |dF|) - prod |F_c| - sum_k |dF_k| prod_{l != k} |F_l,c|``."""
    full = np.prod([a + d for a, d in zip(centres, deviations)], axis=0)
    zeroth = np.prod(centres, axis=0)
    first = sum(d * np.prod([a for l, a in enumerate(centres) if l != k], axis=0) if len(centres) > 1 else d
                for k, d in enumerate(deviations))
    return np.maximum(full - zeroth - first, 0.0)


def multiplied_group(omega_rad_s, g, lo, hi):
    """The group's constraint multiplied through by every denominator of the group (the thesis's
    embedding, eq. 3.26, for several modes at once):

        |g prod_i D_i - sum_i N_i prod_{k != i} D_k| <= E prod_i max_box |D_i|.

    The left side is multilinear in the modes' parameter blocks, so its first-order expansion at the
    box centre has a remainder bounded without any division (``_product_remainder``): unlike the
    divided form it stays finite at a resonance inside the box, which is where coarse boxes of
    close modes carry their information. Returns ``(P_c, J, err, rho, scale)``: the cone is
    ``|P_c + J (x - c)| <= scale E + rho``.
    """
    w, jw, c, h, L, H, m = _box_terms(omega_rad_s, lo, hi)
    g = np.asarray(g, dtype=complex)
    D = [(c[i, A0] - w * w) + jw * c[i, A1] for i in range(m)]
    N = [c[i, B0] + jw * c[i, B1] for i in range(m)]
    dD = [np.hypot(h[i, A0], w * h[i, A1]) for i in range(m)]
    dN = [np.hypot(h[i, B0], w * h[i, B1]) for i in range(m)]
    aD = [np.abs(d) for d in D]
    aN = [np.abs(n) for n in N]

    def prod_except(values, skip):
        out = np.ones(w.size, dtype=values[0].dtype)
        for k, v in enumerate(values):
            if k not in skip:
                out = out * v
        return out

    P_c = g * prod_except(D, ()) - sum(N[i] * prod_except(D, (i,)) for i in range(m))
    J = np.zeros((w.size, 4 * m), dtype=complex)
    for i in range(m):
        # d/d a0_i and d/d a1_i of g prod D - sum_k N_k prod_{l != k} D_l: D_i' = 1 and j w
        dP_dDi = g * prod_except(D, (i,)) - sum(N[k] * prod_except(D, (k, i)) for k in range(m) if k != i)
        J[:, 4 * i + A0] = dP_dDi
        J[:, 4 * i + A1] = dP_dDi * jw
        dP_dNi = -prod_except(D, (i,))
        J[:, 4 * i + B0] = dP_dNi
        J[:, 4 * i + B1] = dP_dNi * jw
    ag = np.abs(g)
    rho = _product_remainder([ag * np.ones_like(w)] + aD, [np.zeros_like(w)] + dD)
    for i in range(m):
        rho = rho + _product_remainder([aN[i]] + [aD[k] for k in range(m) if k != i],
                                       [dN[i]] + [dD[k] for k in range(m) if k != i])
    # rounding of the formed products: a few ulps of every term's size before cancellation
    # (a0 - w^2 cancels near resonance, so the terms are sized with a0 + w^2)
    big_D = [np.abs(c[i, A0]) + w * w + w * np.abs(c[i, A1]) for i in range(m)]
    err = 16 * (m + 1) * _EPS * (ag * prod_except(big_D, ()) + sum(aN[i] * prod_except(big_D, (i,)) for i in range(m)))
    scale = np.ones(w.size)
    for i in range(m):
        scale = scale * denominator_max(w, L[i, A0], H[i, A0], H[i, A1])
    return P_c, J, err, rho * (1.0 + 1e-12), scale


def _affine_factors(w, c_mode, h_mode):
    """``D = D_c + sum_p dD_p y_p`` and ``N = N_c + sum_p dN_p y_p`` of one mode over its box, in
    the normalised coordinates ``x = c + h y`` (``dD_p, dN_p``: shape ``(4, N)``)."""
    jw = 1j * w
    D_c = (c_mode[A0] - w * w) + jw * c_mode[A1]
    N_c = c_mode[B0] + jw * c_mode[B1]
    dD = np.zeros((4, w.size), dtype=complex)
    dN = np.zeros((4, w.size), dtype=complex)
    dD[A1], dD[A0] = jw * h_mode[A1], h_mode[A0]
    dN[B1], dN[B0] = jw * h_mode[B1], h_mode[B0]
    return D_c, dD, N_c, dN


def _product_of_affine(A_c, dA, B_c, dB):
    """``A(y_1) B(y_2)`` for ``A`` affine in the first mode's ``y_1`` and ``B`` in the second's:
    its constant, its linear coefficients on ``(y_1, y_2)`` (shape ``(N, 8)``) and its coefficients
    on the sixteen products ``y_1p y_2q`` (shape ``(N, 16)``, ``p`` major). Exact: no remainder."""
    linear = np.concatenate([B_c[None] * dA, A_c[None] * dB]).T
    bilinear = (dA[:, None, :] * dB[None, :, :]).reshape(16, -1).T
    return A_c * B_c, linear, bilinear


def lifted_pair(omega_rad_s, g, lo, hi):
    """A pair's multiplied constraint (the thesis's embedding, eq. 3.26, over ``D_1 D_2``) written
    exactly, with each product of the two modes' parameters as its own variable (our choice):

        |g D_1 D_2 - N_1 D_2 - N_2 D_1| <= E max_box |D_1| max_box |D_2|.

    The left side is bilinear: one factor from each mode. In the box's normalised coordinates
    ``x = c + h y`` it is ``r_c + J_y y + K z`` with ``z_pq = y_1p y_2q``, exact; the products are
    relaxed by their McCormick envelopes in the conic program
    (:class:`~setmem_hil.identification.certified_cone_program.ProductTerms`). Unlike the
    first-order expansion with a remainder (:func:`multiplied_group`), every point shares the
    same ``z``, so a coarse box whose pole ranges cover both resonances is still held by all the
    points together: in the pair's quartic coefficients, which the data fix well, the box's
    products must agree. This is what prunes the coarse boxes of a pair 1 % apart (one
    half-power bandwidth).

    Returns ``(r_c, J, err, scale, products)``: ``J`` per unit of ``x`` (as the other forms), the
    rounding allowance of the formed row, the factor ``max |D_1| max |D_2|`` of ``E``, and the
    products' coefficients (columns identically zero left out).
    """
    w, jw, c, h, L, H, m = _box_terms(omega_rad_s, lo, hi)
    if m != 2:
        raise ValueError(f"lifted_pair: a pair of modes, found {m}")
    g = np.asarray(g, dtype=complex)
    D1, dD1, N1, dN1 = _affine_factors(w, c[0], h[0])
    D2, dD2, N2, dN2 = _affine_factors(w, c[1], h[1])
    dd = _product_of_affine(D1, dD1, D2, dD2)
    nd = _product_of_affine(N1, dN1, D2, dD2)
    dn = _product_of_affine(D1, dD1, N2, dN2)
    r_c = g * dd[0] - nd[0] - dn[0]
    J_y = g[:, None] * dd[1] - nd[1] - dn[1]
    K = g[:, None] * dd[2] - nd[2] - dn[2]
    J = _per_unit_x(J_y, lo, hi)
    used = np.flatnonzero(np.any(K != 0, axis=0))
    pairs = np.array([(k // 4, 4 + k % 4) for k in used], dtype=int).reshape(-1, 2)
    # rounding: every coefficient is a sum of products of at most three factors, each below these
    # sizes over the box (a0 - w^2 cancels near resonance: sized with a0 + w^2)
    big_D = [np.abs(c[i, A0]) + h[i, A0] + w * w + w * (np.abs(c[i, A1]) + h[i, A1]) for i in range(2)]
    big_N = [np.abs(c[i, B0]) + h[i, B0] + w * (np.abs(c[i, B1]) + h[i, B1]) for i in range(2)]
    err = 64 * _EPS * (np.abs(g) * big_D[0] * big_D[1] + big_N[0] * big_D[1] + big_N[1] * big_D[0])
    scale = (denominator_max(w, L[0, A0], H[0, A0], H[0, A1]) * denominator_max(w, L[1, A0], H[1, A0], H[1, A1])
             * (1.0 + 1e-12))
    return r_c, J, err, scale, ProductTerms(K[:, used], pairs)


def _sub_box(lo, hi, modes):
    """The box of some of the group's modes (flat ``(4 k,)`` ends)."""
    cols = np.concatenate([np.arange(4 * i, 4 * i + 4) for i in modes]).astype(int)
    return np.asarray(lo, dtype=float)[cols], np.asarray(hi, dtype=float)[cols], cols


def denominator_bound(omega_rad_s, lo, hi, pairs, box_max) -> AffineMagnitudeBound:
    """The affine bound of ``|D|`` (one mode's box, ``pairs`` empty) or ``|D_1 D_2|`` (a pair's,
    its products in the columns ``pairs`` of :func:`lifted_pair`) that replaces ``box_max`` on the
    right of the multiplied constraint where it is tighter (:mod:`magnitude_bound`, stop 59).
    Slopes per unit of the box's normalised coordinates."""
    w, _, c, h, _, _, m = _box_terms(omega_rad_s, lo, hi)
    factors = [_affine_factors(w, c[i], h[i]) for i in range(m)]
    deviations = [np.hypot(h[i, A0], w * h[i, A1]) for i in range(m)]
    if m == 1:
        D, dD = factors[0][0], factors[0][1]
        return affine_magnitude_bound(D, dD.T, np.zeros((w.size, 0)), deviations[0], box_max)
    (D1, dD1, _, _), (D2, dD2, _, _) = factors
    Q_c, Q_y, Q_z = _product_of_affine(D1, dD1, D2, dD2)
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    cols = pairs[:, 0] * 4 + pairs[:, 1] - 4
    deviation = np.abs(D1) * deviations[1] + deviations[0] * np.abs(D2) + deviations[0] * deviations[1]
    bound = affine_magnitude_bound(Q_c, Q_y, Q_z[:, cols], deviation, box_max)
    # a product of Q that is not a variable of the program (g = 0 at every point) cannot be bounded
    missing = np.any(np.delete(Q_z, cols, axis=1) != 0, axis=1)
    return AffineMagnitudeBound(bound.constant, bound.slope, bound.product_slope, bound.usable & ~missing)


def _per_unit_x(slope_y, lo, hi):
    """Slopes per unit of the normalised coordinates ``y`` turned into slopes per unit of ``x``."""
    half = 0.5 * (np.asarray(hi, dtype=float) - np.asarray(lo, dtype=float))
    return np.where(half > 0, slope_y / np.where(half > 0, half, 1.0), 0.0)


def mixed_form(omega_rad_s, g, lo, hi, multiplied: tuple[int, ...]):
    """A point's constraint multiplied through by the denominators of one mode or a pair only
    (those whose own remainder is large there), the group's other modes in their mean-value form
    (our choice, issue 47: a group of three, a close pair with a far mode):

        |(g - sum_o N_o / D_o) prod_k D_k - sum_k N_k prod_{l != k} D_l| <= E prod_k max_box |D_k|.

    With ``g' = g - sum_o N_o / D_o = r_o + J_o dx_o + R_o`` (:func:`linearised_group` of the
    others, ``|R_o| <= rho_o``) this is the thesis's embedding (eq. 3.26) of ``g'`` for one mode,
    exact in that mode's parameters, or :func:`lifted_pair` of ``g'`` for a pair; ``J_o dx_o``
    multiplies the denominators' product at the centre as a linear term, and what is left is the
    remainder ``|J_o| h_o max |dP| + rho_o max |P|`` (``P`` the product of the multiplied
    denominators, ``dP`` its deviation from the centre's). The split of eq. (3.11) bounds the far
    mode by the pair's whole mismatch; here the pair's parameters stay variables of the program,
    so at the far mode's points the pair's two residues enter through their (nearly equal)
    first-order coefficients, as in the data.

    Returns ``(r_c, J, err, scale, rho, products)``: the cone is ``|r_c + J (x - c) + K z| <= scale
    E + rho`` (``J`` per unit of ``x`` over the whole group; ``products`` the pair's, indices into
    the group's parameters, or ``None``).
    """
    w = np.asarray(omega_rad_s, dtype=float)
    m = np.size(lo) // 4
    others = [i for i in range(m) if i not in multiplied]
    o_lo, o_hi, o_cols = _sub_box(lo, hi, others)
    r_o, J_o, err_o, rho_o = linearised_group(w, g, o_lo, o_hi)
    reach_o = np.abs(J_o) @ (0.5 * (o_hi - o_lo))  # largest |J_o dx_o| over the box
    k_lo, k_hi, k_cols = _sub_box(lo, hi, multiplied)
    J = np.zeros((w.size, 4 * m), dtype=complex)
    _, _, c, h, L, H, _ = _box_terms(w, k_lo, k_hi)
    D_c = [(c[i, A0] - w * w) + 1j * w * c[i, A1] for i in range(len(multiplied))]
    dD = [np.hypot(h[i, A0], w * h[i, A1]) for i in range(len(multiplied))]
    D_max = [denominator_max(w, L[i, A0], H[i, A0], H[i, A1]) for i in range(len(multiplied))]
    products = None
    if len(multiplied) == 1:
        r_c = r_o * D_c[0] - (c[0, B0] + 1j * w * c[0, B1])
        J[:, k_cols[A1]], J[:, k_cols[A0]] = r_o * 1j * w, r_o
        J[:, k_cols[B1]], J[:, k_cols[B0]] = -1j * w, -1.0
        P_c, P_dev, scale = D_c[0], dD[0], D_max[0]
        err = err_o * D_max[0] + 16 * _EPS * (np.abs(r_o) * (np.abs(c[0, A0]) + w * w + w * np.abs(c[0, A1]))
                                              + np.abs(c[0, B0]) + w * np.abs(c[0, B1]))
    elif len(multiplied) == 2:
        r_c, J_k, err, scale, lifted = lifted_pair(w, r_o, k_lo, k_hi)
        J[:, k_cols] = J_k
        P_c = D_c[0] * D_c[1]
        P_dev = np.abs(D_c[0]) * dD[1] + dD[0] * np.abs(D_c[1]) + dD[0] * dD[1]
        err = err + err_o * scale
        products = ProductTerms(lifted.K, k_cols[np.asarray(lifted.pairs, dtype=int)].reshape(-1, 2))
    else:
        raise ValueError(f"mixed_form: one mode or a pair multiplied, found {len(multiplied)}")
    J[:, o_cols] = P_c[:, None] * J_o
    with np.errstate(invalid="ignore"):
        rho = (reach_o * P_dev + rho_o * scale) * (1.0 + 1e-12)
    rho = np.where(np.isfinite(rho_o), rho, np.inf)
    return r_c, J, err, scale, rho, products


def _multiplied_modes(omega, E, lo, hi, lift_pairs: tuple = ()) -> list:
    """Per point, the modes to multiply through in a group of three or more (:func:`mixed_form`):
    the mode with the largest remainder when the others' remainders together fit within the
    point's bound, else the two largest when the rest does, else ``None`` (every denominator:
    :func:`multiplied_group`). Where the two largest are one of ``lift_pairs`` (close pairs, as
    group-local mode indices), the pair is lifted unless the others' remainders together are under
    ``NEGLIGIBLE_REST`` of the bound.

    Why the pair before the single mode (stop 61): a close pair's two remainders add in the
    single form although the data see the pair's residue sums, which the lifted form keeps exact
    in the products shared by every point. On a 0.5 % same-sign pair (300 lines) it took the pair
    from 1.37 / 1.40 to 1.14 / 1.16 of the exact set and the far mode from 2.20 to 1.92, in the
    same time (docs/closely-spaced-modes.md). Only a close pair: two modes far apart have no sum
    the data see, and their products' envelopes over coarse boxes may be looser than one mode
    multiplied alone."""
    pairs = {tuple(sorted(int(k) for k in pair)) for pair in lift_pairs}
    m = np.size(lo) // 4
    per_mode = np.array([_remainders(omega, *_sub_box(lo, hi, [i])[:2]) for i in range(m)])
    order = np.argsort(-per_mode, axis=0, kind="stable")
    ranked = np.take_along_axis(per_mode, order, axis=0)
    # the others' remainders summed from the smallest up (no inf - inf where two can vanish)
    rest_of_one, rest_of_two = ranked[1:].sum(axis=0), ranked[2:].sum(axis=0)
    choice = []
    for j in range(np.size(omega)):
        first = int(order[0, j])
        second = int(order[1, j]) if m > 1 else first  # a group of one (the tight path of a lone mode)
        top_two = tuple(sorted({first, second}))
        alone_below = NEGLIGIBLE_REST * E[j] if top_two in pairs else E[j]
        if rest_of_one[j] <= alone_below:
            choice.append((first,))
        elif rest_of_two[j] <= E[j]:
            choice.append(top_two)
        elif rest_of_one[j] <= E[j]:
            choice.append((first,))
        else:
            choice.append(None)
    return choice


def _affine_radius(bound: AffineMagnitudeBound, rows, E, rho, radius, cols, sub_lo, sub_hi) -> np.ndarray:
    """Write the affine radius ``E U + rho`` of ``bound`` (over the sub-box ``sub_lo, sub_hi`` of
    the parameters ``cols``) into ``radius = (C, slope)`` at the rows where it is usable (a finite
    bound; in place); returns the product slopes (zero elsewhere)."""
    C, slope = radius
    affine = rows & bound.usable & np.isfinite(E)
    C[affine] = bound.constant[affine] * E[affine] + rho[affine]
    slope[np.ix_(affine, cols)] = E[affine, None] * _per_unit_x(bound.slope[affine], sub_lo, sub_hi)
    product_slope = np.zeros(bound.product_slope.shape)
    product_slope[affine] = E[affine, None] * bound.product_slope[affine]
    return product_slope


def _mixed_cones(omega, g, E, lo, hi, mult, cones, affine_radius: bool = True, lift_pairs: tuple = ()):
    """Write the cones of the points ``mult`` (in place into ``cones = (r_c, J, err, C, slope)``,
    ``slope`` the radius's slope per unit of ``x``) in the form :func:`_multiplied_modes` picks,
    the multiplied denominators' magnitude bounded affinely where that is tighter
    (:func:`denominator_bound`); returns the product terms of the pairs used and their slopes in
    the radius, or ``(None, None)``."""
    r_c, J, err, C, slope = cones
    choice = _multiplied_modes(omega, E, lo, hi, lift_pairs)
    K_cols, pairs, K_slopes = [], [], []
    for modes in dict.fromkeys(choice[j] for j in np.flatnonzero(mult)):
        rows = mult & np.array([c == modes for c in choice])
        bound = None
        if modes is None:
            P_c, J_m, err_m, rho_m, scale = multiplied_group(omega, g, lo, hi)
            lifted = None
        else:
            P_c, J_m, err_m, scale, rho_m, lifted = mixed_form(omega, g, lo, hi, modes)
            k_lo, k_hi, k_cols = _sub_box(lo, hi, modes)
            local_pairs = np.searchsorted(k_cols, lifted.pairs) if lifted is not None else ()
            bound = denominator_bound(omega, k_lo, k_hi, local_pairs, scale) if affine_radius else None
        r_c[rows], J[rows], err[rows] = P_c[rows], J_m[rows], err_m[rows]
        C[rows] = scale[rows] * E[rows] + rho_m[rows]
        K_slope = None
        if bound is not None:
            K_slope = _affine_radius(bound, rows, E, rho_m, (C, slope), k_cols, k_lo, k_hi)
        if lifted is not None and lifted.K.shape[1]:
            K_cols.append(np.where(rows[:, None], lifted.K, 0.0))
            pairs.append(lifted.pairs)
            K_slopes.append(np.zeros(lifted.K.shape) if K_slope is None else K_slope)
    if not K_cols:
        return None, None
    return ProductTerms(np.hstack(K_cols), np.vstack(pairs)), np.hstack(K_slopes)


def _second_order_rows(omega, g, E, lo, hi, rows, cones, products, product_slope):
    """Write the points ``rows`` (those in the divided form) to second order
    (:func:`second_order_group`) into ``cones = (r_c, J, err, C)`` (in place), their product
    terms beside ``products`` (the lifted or multiplied points'; zero on each other's rows);
    returns the merged product terms and their radius slopes (``None`` where none)."""
    r_c, J, err, C = cones
    r2, J2, err2, rho2, second = second_order_group(omega, g, lo, hi)
    r_c[rows], J[rows], err[rows], C[rows] = r2[rows], J2[rows], err2[rows], E[rows] + rho2[rows]
    if second is None:
        return products, product_slope
    used = np.any(second.K[rows] != 0, axis=0)  # a product that no row of ``rows`` uses is left out
    if not used.any():
        return products, product_slope
    second = ProductTerms(second.K[:, used], second.pairs[used])
    K2 = np.where(rows[:, None], second.K, 0.0)
    if products is None:
        return ProductTerms(K2, second.pairs), None if product_slope is None else np.zeros(K2.shape)
    slope = None if product_slope is None else np.hstack([product_slope, np.zeros(K2.shape)])
    return ProductTerms(np.hstack([products.K, K2]), np.vstack([products.pairs, second.pairs])), slope


def _remainders(omega, lo, hi) -> np.ndarray:
    return linearised_group(omega, np.zeros(np.size(omega), dtype=complex), lo, hi, with_jacobian=False)[3]


def _score(omega, E, lo, hi) -> float:
    """How much the remainders blur the box's points (lower is better; for choosing a split)."""
    ratio = np.minimum(_remainders(omega, lo, hi) / E, UNUSABLE_RATIO)
    return float(np.sum(np.log1p(ratio)))


def _split_dimension(omega, E, lo, hi, modes=None) -> int:
    """The free parameter (of ``modes``, default all) whose halving blurs the points least (by the
    remainders' score)."""
    best, best_score = -1, np.inf
    free = hi > lo
    if modes is not None:
        free &= np.isin(np.arange(np.size(lo)) // 4, modes)
    for k in np.flatnonzero(free):
        mid = 0.5 * (lo[k] + hi[k])
        scores = []
        for a, b in ((lo[k], mid), (mid, hi[k])):
            l2, h2 = lo.copy(), hi.copy()
            l2[k], h2[k] = a, b
            scores.append(_score(omega, E, l2, h2))
        s = max(scores)
        if s < best_score:
            best, best_score = int(k), s
    return best


def _widened(inner, points):
    """The hull ``inner`` (``(lo, hi)`` or ``None``) widened to take in ``points``."""
    if not points:
        return inner
    stack = np.array(points)
    lo, hi = stack.min(axis=0), stack.max(axis=0)
    if inner is not None:
        lo, hi = np.minimum(inner[0], lo), np.maximum(inner[1], hi)
    return lo, hi


class _Search:
    """The branch-and-bound's state: counters and the certified contraction of one box."""

    def __init__(self, omega, g, E, settings: GroupSettings):
        self.omega, self.g, self.E = omega, g, E
        self.settings = settings
        self.n_solves = 0
        self._lock = threading.Lock()
        self.root: tuple[np.ndarray, np.ndarray] | None = None  # the searched box (set by the search)
        self.anchor: np.ndarray | None = None  # a point that fits (a Chebyshev fit), once found
        self.inner: tuple[np.ndarray, np.ndarray] | None = None  # the hull of the witnesses
        self.hint: np.ndarray | None = None  # where to start looking for the anchor (an earlier stage's)

    # -- witnesses: where refining can no longer narrow the answer -----------------------------
    def witnesses_in(self, lo, hi, candidates, anchor, inner):
        """Points of this box that fit and widen the witnesses' hull ``inner`` as it stood when the
        box was taken: the anchor first if there is none (a Chebyshev fit, with the farthest
        fitting points around it), then every candidate (the contraction's points nearest each
        bound) that, pulled back towards the anchor, fits. Returns ``(new_anchor or None,
        points)``; reads nothing that other boxes change (the search adds them in order,
        :meth:`add_witnesses`), so the answer does not depend on the threads' timing."""
        new_anchor, found = None, []
        if anchor is None:
            x = self._fit_from(lo, hi, candidates)
            if x is None:
                return None, []
            new_anchor = anchor = x
            found = [x] + self._farthest(x)
            inner = _widened(inner, found)
        outside = [x for x in candidates
                   if inner is None or not (np.all(x >= inner[0]) and np.all(x <= inner[1]))]
        pulled = self._pulled_back(outside, anchor)
        if outside and not pulled:
            # the segment to the anchor leaves the set (a set in two pieces, or bent): this box's
            # own fitting point, then its candidates pulled back towards it
            local = self._fit_from(lo, hi, outside)
            if local is not None:
                pulled = [local] + self._pulled_back(outside, local)
        return new_anchor, found + pulled

    def add_witnesses(self, anchor, points) -> None:
        """Keep a box's witnesses (:meth:`witnesses_in`); the first anchor found stays the anchor."""
        if anchor is not None and self.anchor is None:
            self.anchor = anchor
        self.inner = _widened(self.inner, points)

    def _farthest(self, anchor) -> list:
        """Each free parameter's farthest fitting points from ``anchor`` by a local search
        (:func:`feasible_points.farthest_fitting`), on the search's subset of points and then
        pulled back until they fit every point."""
        root_lo, root_hi = self.root
        idx = _search_subset(self.omega, self.settings.search_points, root_lo, root_hi)
        directions = [(int(k), sign) for k in np.flatnonzero(root_hi > root_lo) for sign in (-1.0, 1.0)]

        def farthest(direction):
            return feasible_points.farthest_fitting(self.omega[idx], self.g[idx], self.E[idx], root_lo, root_hi,
                                                    anchor, direction[0], direction[1], iterations=6)

        # The searches are independent, and the first box's (which finds the anchor) runs while
        # nothing else can: on the 1,200 lines they were a third of the group's time. pool.map
        # returns them in order: the answer does not depend on the threads.
        with ThreadPoolExecutor(max_workers=max(1, self.settings.workers)) as pool:
            out = list(pool.map(farthest, directions))
        return self._pulled_back(out, anchor)

    def _pulled_back(self, candidates, towards) -> list:
        return [x for x in (feasible_points.pulled_back(c, towards, self.omega, self.g, self.E) for c in candidates) if x is not None]

    def _fit_from(self, lo, hi, candidates):
        """A point of the box that fits, by a Chebyshev fit from the hint (the subset's search's
        anchor), the box's centre or the candidate that fits best, or ``None``. (From a coarse
        box's centre the fit often stalls in a local minimum: a pair's modes merged.)"""
        starts = [] if self.hint is None else [self.hint]
        starts.append(0.5 * (lo + hi))
        if candidates:
            starts.append(min(candidates, key=lambda x: feasible_points.misfit(x, self.omega, self.g, self.E)))
        for x0 in starts:
            if np.all(x0 >= lo) and np.all(x0 <= hi):
                x, f = feasible_points.chebyshev_fit(self.omega, self.g, self.E, lo, hi, x0)
                if f <= 1.0:
                    return x
        return None

    def settled(self, lo, hi) -> bool:
        """Does the box stick out of the witnesses' hull by at most ``settle_fraction`` of its width?"""
        inner = self.inner
        if inner is None:
            return False
        tol = self.settings.settle_fraction * (inner[1] - inner[0])
        return bool(np.all(lo >= inner[0] - tol) and np.all(hi <= inner[1] + tol))

    def flag_outside(self, lo, hi, flags: dict) -> bool:
        """Does a flagged (uncertified) bound of the box stick out of the witnesses' hull? Only such
        a bound can become the answer's (the answer holds every witness)."""
        if not flags:
            return False
        inner = self.inner
        if inner is None:
            return True
        return any(lo[p] < inner[0][p] if sign > 0 else hi[p] > inner[1][p] for p, sign in flags)

    def within(self, lo, hi, ratio: float) -> bool:
        """Is every point's remainder over the box at most ``ratio`` of its bound? (``fine_ratio``:
        fine; ``tight_ratio``: tight.)"""
        finite = np.isfinite(self.E)
        return bool(np.all(_remainders(self.omega[finite], lo, hi) <= ratio * self.E[finite]))

    def _cones(self, lo, hi, idx):
        """Each point's cone: the divided form where its remainder is at most ``divided_ratio`` of the
        point's bound; a pair elsewhere in its lifted form (:func:`lifted_pair`), a larger group in its multiplied form
        (all are outer relaxations; the choice only picks the tighter), the multiplied
        denominators' magnitude on the right bounded affinely where that is tighter
        (:func:`denominator_bound`). Returns ``(r_c, J, err, C, products, active, slopes)`` with
        the points whose cone holds over the whole box left out (they bound nothing there);
        ``slopes`` (``None`` when every radius is constant) are the radii's slopes per unit of
        ``x`` and per product."""
        omega, g, E = self.omega[idx], self.g[idx], self.E[idx]
        r_c, J, err, rho = linearised_group(omega, g, lo, hi)
        C = E + rho
        divided = rho <= self.settings.divided_ratio * E
        products, slope, product_slope = None, np.zeros(J.shape), None
        if not divided.all():
            mult = ~divided
            r_c, J, err, C = r_c.copy(), J.copy(), err.copy(), C.copy()
            if np.size(lo) == 8:
                P_c, J_m, err_m, scale, lifted = lifted_pair(omega, g, lo, hi)
                K = np.where(mult[:, None], lifted.K, 0.0)
                products = ProductTerms(K, lifted.pairs)
                C[mult] = scale[mult] * E[mult]
                r_c[mult], J[mult], err[mult] = P_c[mult], J_m[mult], err_m[mult]
                if self.settings.affine_radius:
                    bound = denominator_bound(omega, lo, hi, lifted.pairs, scale)
                    product_slope = _affine_radius(bound, mult, E, np.zeros_like(E), (C, slope),
                                                   np.arange(np.size(lo)), lo, hi)
            else:
                products, product_slope = _mixed_cones(omega, g, E, lo, hi, mult, (r_c, J, err, C, slope),
                                                       self.settings.affine_radius, self.settings.lift_pairs)
        second = divided & (rho > SECOND_ORDER_FLOOR * E) if self.settings.second_order else np.zeros(0, bool)
        if second.any():
            r_c, J, err, C = r_c.copy(), J.copy(), err.copy(), C.copy()
            products, product_slope = _second_order_rows(omega, g, E, lo, hi, second, (r_c, J, err, C),
                                                         products, product_slope)
        C = np.where(np.isfinite(E), C, np.inf)
        h = 0.5 * (np.asarray(hi, dtype=float) - np.asarray(lo, dtype=float))
        reach = np.abs(r_c) + np.abs(J) @ h + err
        radius_min = C - np.abs(slope) @ h  # the radius's least value over the box
        if products is not None:
            reach = reach + np.sum(np.abs(products.K), axis=1)
        if product_slope is not None:
            radius_min = radius_min - np.sum(np.abs(product_slope), axis=1)
        active = np.isfinite(C) & ~(reach * (1.0 + 1e-9) < radius_min)
        slopes = None
        if np.any(slope[active]) or (product_slope is not None and np.any(product_slope[active])):
            n_aux = 0 if products is None else products.K.shape[1]
            slopes = (slope[active], np.zeros((int(active.sum()), n_aux)) if product_slope is None
                      else product_slope[active])
        if products is not None:
            products = ProductTerms(products.K[active], products.pairs)
        return r_c[active], J[active], err[active], C[active], products, active, slopes

    def _points_for(self, lo, hi) -> np.ndarray:
        """The points a box's program uses: every point once the box is fine (its remainders all
        within the bound: where the answer's last digits are decided), else at most
        ``search_points`` of them (:func:`_search_subset`: a subset is a valid relaxation, and a
        coarse box is decided by its band's points)."""
        every = np.arange(self.omega.size)
        if self.omega.size <= self.settings.search_points or self.within(lo, hi, self.settings.fine_ratio):
            return every
        return _search_subset(self.omega, self.settings.search_points, lo, hi)

    def contract(self, lo, hi):
        """Certified bounds of the box's feasible set, repeated while it shrinks (by more than the
        coarse tolerance while its remainders are large, the fine one after).

        Returns ``(lo, hi, fine, candidates, verdicts)`` or ``None`` when the box is proved empty;
        ``candidates`` are the last pass's points near each bound (the relaxation's, not checked);
        ``verdicts`` maps ``(parameter, +1 lower / -1 upper)`` to the reason a bound was kept
        uncertified, or to ``None`` where a later pass certified it (:func:`_merged_flags`).
        """
        sol, verdicts = None, {}
        for _ in range(self.settings.max_contractions):
            idx = self._points_for(lo, hi)
            r_c, J, err, C, products, active, slopes = self._cones(lo, hi, idx)
            if not active.any():
                return lo, hi, False, [], verdicts
            program = AffineConeProgram(r_c, J, err, lo, hi, self.omega[idx][active], products, slopes)
            sol = program.bound_box(C, lo, hi)
            with self._lock:
                self.n_solves += program.n_solves
            if not sol.feasible:
                return None
            verdicts.update(_verdicts(program.free, sol))
            new_lo, new_hi = np.maximum(lo, sol.lower), np.minimum(hi, sol.upper)
            new_hi = np.maximum(new_lo, new_hi)
            width = np.maximum(hi - lo, 1e-300)
            shrink = np.max(((hi - lo) - (new_hi - new_lo)) / width)
            lo, hi = new_lo, new_hi
            fine = self.within(lo, hi, self.settings.fine_ratio)
            if shrink < (self.settings.contraction_tolerance if fine else self.settings.coarse_contraction_tolerance):
                break
        fine = self.within(lo, hi, self.settings.fine_ratio)
        candidates = []
        if sol is not None:
            candidates = [x for x in np.vstack([sol.argmin, sol.argmax]) if np.all(np.isfinite(x))]
        return lo, hi, fine, candidates, verdicts


def _verdicts(free: np.ndarray, sol) -> dict:
    """One pass's verdict on each free bound: the reason it was kept uncertified, else ``None``."""
    reasons = dict(zip(sol.kept, sol.unverified))
    return {(int(p), sign): reasons.get((int(p), sign)) for p in np.flatnonzero(free) for sign in (1, -1)}


def _merged_flags(inherited: dict, verdicts: dict) -> dict:
    """A box's uncertified bounds: those it inherited, less the ones its contraction certified, plus
    the ones its contraction could not."""
    flags = dict(inherited)
    for key, reason in verdicts.items():
        if reason is None:
            flags.pop(key, None)
        else:
            flags[key] = reason
    return flags


def _search_subset(omega: np.ndarray, n_max: int, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices of at most ``n_max`` points for the search: those in the group's band first (where
    the modes are told apart), spread evenly in frequency, then others spread evenly. Any subset
    gives a valid outer bound (fewer constraints, a larger set); the hull is searched again with
    every point."""
    if omega.size <= n_max:
        return np.arange(omega.size)
    box_lo, box_hi = _split_modes(lo), _split_modes(hi)
    band = (omega >= 0.9 * np.sqrt(max(float(np.min(box_lo[:, A0])), 0.0))) & (omega <= 1.1 * np.sqrt(float(np.max(box_hi[:, A0]))))

    def spread(idx, n):
        if idx.size <= n:
            return idx
        idx = idx[np.argsort(omega[idx], kind="stable")]
        return idx[np.unique(np.linspace(0, idx.size - 1, n).round().astype(int))]

    # each mode's resonance first (within a bandwidth of its a0 range): a lightly damped mode's
    # few points there decide its box, and an even spread drops half of them
    peak = near_resonance(omega, box_lo, box_hi, bandwidths=1.0)
    peaks = spread(np.flatnonzero(peak), n_max // 2)
    left = np.ones(omega.size, dtype=bool)
    left[peaks] = False
    inside = np.concatenate([peaks, spread(np.flatnonzero(band & left), max((2 * n_max) // 3 - peaks.size, 0))])
    outside = spread(np.flatnonzero(~band & left), n_max - inside.size)
    return np.sort(np.concatenate([inside, outside]))


def _priority(search: _Search, lo: np.ndarray, hi: np.ndarray) -> float:
    """Which open box to refine first: the one that sticks out furthest beyond the witnesses' hull
    (in units of the hull's width), or before any witness the largest (in units of the searched
    box). The answer is the hull of the leaves, so the box that widens it most goes first; a box
    inside the hull never needs refining."""
    inner = search.inner
    if inner is None:
        root_lo, root_hi = search.root
        width = np.where(root_hi > root_lo, root_hi - root_lo, 1.0)
        return float(np.max((hi - lo) / width))
    return float(np.max(_protrusion(inner, lo, hi)))


def _hull_width(inner) -> np.ndarray:
    """The witnesses' hull's width per parameter, kept above zero (a single witness: a point)."""
    return np.maximum(inner[1] - inner[0], 1e-12 * np.maximum(np.abs(inner[0]), 1e-300))


def _protrusion(inner, lo, hi) -> np.ndarray:
    """How far each parameter of the box sticks out beyond the witnesses' hull ``inner``, in units
    of the hull's width."""
    return np.maximum(inner[0] - lo, hi - inner[1]) / _hull_width(inner)


def _widest_mode(search: _Search, lo: np.ndarray, hi: np.ndarray):
    """In a group of three or more, the mode whose parameter sticks out furthest beyond the
    witnesses' hull (the one that widens the answer most; the remainders' score alone splits the
    pair, whose many resonant points dominate it, and never the far mode: our finding on the 1 %
    pair with a far mode). ``None`` for a pair or before any witness: every mode."""
    inner = search.inner
    if inner is None or np.size(lo) <= 8:
        return None
    return [int(np.argmax(_protrusion(inner, lo, hi))) // 4]


def _relatively_widest(inner, lo, hi, modes) -> int:
    """The free parameter of ``modes`` whose box is widest against the witnesses' hull ``inner``
    (``-1`` when none is free). The polish's rule (stop 59): there a far mode's own poles are
    already narrow, and what keeps its residues wide is the pair's box, whose residues trade
    against each other; the remainders' rule never cuts a residue (it is linear: halving it blurs
    nothing), so the pair's residues were never cut and the far mode kept their corners' slack."""
    index = np.arange(np.size(lo))
    free = (hi > lo) & np.isin(index // 4, modes)
    if not free.any():
        return -1
    return int(index[free][np.argmax(((hi - lo) / _hull_width(inner))[free])])


def _wide_residue_slope(root, lo, hi, modes, share: float) -> int:
    """The widest ``b1`` of ``modes`` while it is wider than ``share`` of the searched box's
    (``root``), else ``-1``. The polish's first cut where a mode outside the groups is what sticks
    out furthest (stop 61): a close pair's b1 each span their
    prior in the exact set (only their sum is determined), so the witnesses' rule never cuts them,
    yet the lifted form's envelope of each b1 times the other mode's a0 (``jw a0`` in the products:
    the largest coefficients) grows with their width, and it is those envelopes that held the
    pair's residue sums, and through them a far mode, loose in every leaf: halving a leaf's pair b1
    narrowed its far-mode bound most (docs/closely-spaced-modes.md). Only there: cut wherever a
    grouped b1 was wide, the polish of a campaign with three pairs (six grouped modes, each b1 to
    be cut twice) spent its budget on them, and its first iterations' boxes widened (stop 61)."""
    index = np.arange(np.size(lo))
    slopes = index[(hi > lo) & np.isin(index // 4, modes) & (index % 4 == B1)]
    if not slopes.size:
        return -1
    k = int(slopes[np.argmax((hi - lo)[slopes])])
    root_lo, root_hi = root
    return k if hi[k] - lo[k] > share * (root_hi[k] - root_lo[k]) else -1


def _children(search: _Search, lo, hi, fine: bool, depth: int, settings: GroupSettings, flags: dict):
    """A contracted box's two halves, or ``None`` when it is a leaf: settled against the witnesses,
    tight, fine before any witness exists, or at the depth limit; never while a flagged
    (uncertified) bound sticks out of the witnesses' hull, short of the limit. The cut is the middle of the
    parameter whose halving blurs the points least. (Cutting at the witnesses' hull instead, so
    that one child is a slab the relaxation may prove empty in one solve, was tried: more boxes
    and wider answers on the benchmark's 1 % and 3 % pairs.)"""
    leaf = search.settled(lo, hi) or (fine and (search.inner is None or search.within(lo, hi, settings.tight_ratio)))
    if (leaf and not search.flag_outside(lo, hi, flags)) or depth >= settings.max_depth:
        return None
    k = -1
    if settings.split_among is not None and search.inner is not None:
        # first the grouped b1, where a mode outside the groups sticks out furthest
        if (settings.cut_wide_b1 is not None
                and int(np.argmax(_protrusion(search.inner, lo, hi))) // 4 not in settings.split_among):
            k = _wide_residue_slope(search.root, lo, hi, settings.split_among, settings.cut_wide_b1)
        if k < 0:
            k = _relatively_widest(search.inner, lo, hi, settings.split_among)
    if k < 0:
        k = _split_dimension(search.omega, search.E, lo, hi, _widest_mode(search, lo, hi))
    if k < 0:
        k = _split_dimension(search.omega, search.E, lo, hi)
    if k < 0:
        return None
    mid = 0.5 * (lo[k] + hi[k])
    left_hi, right_lo = hi.copy(), lo.copy()
    left_hi[k], right_lo[k] = mid, mid
    return (lo, left_hi), (right_lo, hi), k


LOOKAHEAD = 2  # boxes in flight: a setting of the search, not the machine's core count (in_order_pool)


def _branch_and_bound(search: _Search, lo: np.ndarray, hi: np.ndarray, settings: GroupSettings, counts: dict,
                      root_flags: dict, pieces: tuple = ()):
    """Best-first search of the box (:func:`_priority`) by ``settings.workers`` threads (the conic
    solver runs outside the GIL), the boxes' results applied in the order they were taken
    (:func:`setmem_hil.numerics.in_order_pool.run_in_order`: the same answer from the same data,
    whatever the threads' timing or their number). Returns the leaves (contracted, not proved
    empty). Past ``max_boxes`` every open box becomes a leaf as it stands, or with
    ``settings.contract_at_budget`` contracted once more: the hull is still guaranteed, only
    wider than a longer search's. A leaf is ``(lo, hi, flags)``: ``flags`` maps its uncertified bounds
    ``(parameter, +1 lower / -1 upper)`` to the reason; the root's are ``root_flags``.

    ``pieces`` (boxes whose union holds the root's feasible set, :func:`piece_hulls`): the
    contracted root's children are its intersections with them, not its two halves."""
    open_boxes = [(lo, hi, 0, dict(root_flags))]
    search.root = (lo, hi)
    leaves: list[tuple[np.ndarray, np.ndarray, dict]] = []
    taken = [0]

    spent = [False]  # the budget is spent: with contract_at_budget, nothing is split from here

    def take():
        if open_boxes and taken[0] >= settings.max_boxes:
            counts["exhausted"] = True
            if not settings.contract_at_budget:
                leaves.extend((b_lo, b_hi, flags) for b_lo, b_hi, _, flags in open_boxes)
                open_boxes.clear()
            spent[0] = True  # set when taken, read when applied: the same on any threads' timing (in_order_pool)
        while open_boxes:
            k = int(np.argmax([_priority(search, b[0], b[1]) for b in open_boxes]))
            b_lo, b_hi, depth, flags = open_boxes.pop(k)
            if depth > 0 and search.settled(b_lo, b_hi) and not search.flag_outside(b_lo, b_hi, flags):
                leaves.append((b_lo, b_hi, flags))  # the witnesses grew since it was split: nothing to gain
                continue
            taken[0] += 1
            counts["boxes"] += 1
            return b_lo, b_hi, depth, flags, search.anchor, search.inner  # the witnesses as they stand now
        return None

    def compute(box):
        b_lo, b_hi, depth, _, anchor, inner = box
        out = search.contract(b_lo, b_hi)
        found = (None, [])
        if out is not None and (out[2] or depth == 0):
            found = search.witnesses_in(out[0], out[1], out[3], anchor, inner)
        return out, found

    def apply(box, result):
        out, (anchor, points) = result
        search.add_witnesses(anchor, points)
        if out is None:
            counts["pruned"] += 1
            return
        depth, flags = box[2], _merged_flags(box[3], out[4])
        parts = _pieces_of(out[0], out[1], pieces) if depth == 0 and not spent[0] else []
        if parts:
            # a piece's own bounds are certified (its search's); the root's flags kept on all (conservative)
            open_boxes.extend((p_lo, p_hi, 1, dict(flags)) for p_lo, p_hi in parts)
            return
        children = None if spent[0] else _children(search, out[0], out[1], out[2], depth, settings, flags)
        if children is None:
            leaves.append((out[0], out[1], flags))
            return
        left, right, k = children
        # the cut is exact: the left half's upper bound of k and the right half's lower one are certified
        open_boxes.append((*left, depth + 1, {key: r for key, r in flags.items() if key != (k, -1)}))
        open_boxes.append((*right, depth + 1, {key: r for key, r in flags.items() if key != (k, 1)}))

    run_in_order(take, compute, apply, LOOKAHEAD, settings.workers)
    return leaves


def _pieces_of(lo, hi, pieces) -> list:
    """The non-empty intersections of the box with ``pieces`` (flat ``(lower, upper)``), or ``[]``
    for none or a single one (then the box is split as usual)."""
    parts = []
    for p_lo, p_hi in pieces:
        c_lo, c_hi = np.maximum(lo, p_lo), np.minimum(hi, p_hi)
        if np.all(c_lo <= c_hi):
            parts.append((c_lo, c_hi))
    return parts if len(parts) > 1 else []


def piece_hulls(pieces, count: int) -> list:
    """At most ``count`` boxes whose union holds the union of ``pieces`` (``(lower, upper)``
    pairs): the pieces ordered along the main direction of their centres (in units of their
    spread) and cut into ``count`` runs of consecutive pieces, each run replaced by its hull. A
    close pair's set is a thin slanted sliver (its residues go together); a few hulls along it
    keep much of that, where the one hull of all loses it (our choice, issue 47, stop 58)."""
    pieces = list(pieces)
    if len(pieces) <= count:
        return pieces
    centres = np.array([0.5 * (np.ravel(l) + np.ravel(h)) for l, h in pieces])
    spread = np.ptp(centres, axis=0)
    z = (centres - centres.mean(axis=0)) / np.where(spread > 0, spread, 1.0)
    direction = np.linalg.svd(z, full_matrices=False)[2][0]
    order = np.argsort(z @ direction, kind="stable")
    return [(np.min([pieces[i][0] for i in run], axis=0), np.max([pieces[i][1] for i in run], axis=0))
            for run in np.array_split(order, count)]


def _hull(leaves):
    """The leaves' hull and its uncertified bounds: a flag counts where its leaf's bound is the
    hull's own."""
    lo = np.min([l for l, _, _ in leaves], axis=0)
    hi = np.max([h for _, h, _ in leaves], axis=0)
    flags = {}
    for l, h, leaf_flags in leaves:
        for (p, sign), reason in leaf_flags.items():
            if (l[p] <= lo[p]) if sign > 0 else (h[p] >= hi[p]):
                flags[(p, sign)] = reason
    return lo, hi, flags


def identify_group(omega_rad_s, g, E, lo, hi, settings: GroupSettings = GroupSettings(), pieces: tuple = ()) -> GroupResult:
    """Certified bounds of a group of modes' parameters (module docstring).

    The search runs first on at most ``settings.search_points`` points (a subset: its set
    contains the whole data's); then the hull of its leaves is searched again with every point,
    where a box's program still uses the subset while the box is coarse and every point once it
    is fine.

    Parameters
    ----------
    omega_rad_s, g, E : arrays (N,)
        Points, the data with every mode outside the group subtracted at its midpoint, and the
        bound on each point's error (the data's bound plus the outside modes' mismatch, eq. 3.11).
    lo, hi : arrays (m, 4)
        The group's current box (the prior intersected with earlier bounds); finite.
    pieces : sequence of (lower, upper), arrays (m, 4)
        Boxes whose union holds every parameter of the box that fits (an earlier search's leaves,
        :func:`piece_hulls`): the first stage starts from them instead of halving the box.

    Returns
    -------
    GroupResult
        Bounds inside ``[lo, hi]``.

    Raises
    ------
    ValueError
        When every box is proved empty (the caller names the data points).
    """
    omega = np.asarray(omega_rad_s, dtype=float)
    g = np.asarray(g, dtype=complex)
    E = np.asarray(E, dtype=float)
    m = np.asarray(lo).shape[0]
    box_lo = np.asarray(lo, dtype=float).reshape(-1).copy()
    box_hi = np.asarray(hi, dtype=float).reshape(-1).copy()
    counts = {"boxes": 0, "pruned": 0, "exhausted": False}
    n_solves, flags, anchor = 0, {}, None
    subsets = [_search_subset(omega, settings.search_points, box_lo, box_hi)]
    if subsets[0].size < omega.size:
        subsets = subsets + [np.arange(omega.size)] if settings.subset_stage else [np.arange(omega.size)]
    flat_pieces = tuple((np.ravel(p_lo), np.ravel(p_hi)) for p_lo, p_hi in pieces)
    for idx in subsets:
        search = _Search(omega[idx], g[idx], E[idx], settings)
        search.hint = anchor
        leaves = _branch_and_bound(search, box_lo, box_hi, settings, counts, flags, flat_pieces)
        flat_pieces = ()
        n_solves += search.n_solves
        if not leaves:
            raise GroupProvedEmpty("every box of the group was proved empty")
        box_lo, box_hi, flags = _hull(leaves)  # the next stage's root: its flags carry over
        anchor = search.anchor  # fits the subset: where the search with every point starts looking
    reason = "; ".join(sorted(set(flags.values())))
    certified_leaves = all(not leaf_flags for _, _, leaf_flags in leaves)
    kept = tuple((l.reshape(m, 4), h.reshape(m, 4)) for l, h, _ in leaves) if certified_leaves else ()
    return GroupResult(box_lo.reshape(m, 4), box_hi.reshape(m, 4), not flags, reason, counts["boxes"],
                       len(leaves), counts["pruned"], n_solves, counts["exhausted"], kept)
