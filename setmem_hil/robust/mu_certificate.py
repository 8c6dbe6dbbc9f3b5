"""mu-bar certified on whole frequency intervals, not only at grid points.

The mixed-mu upper bound of :mod:`~setmem_hil.robust.mixed_mu` is evaluated at grid frequencies;
between them nothing is proved, and a lightly damped closed loop can peak between two points
(the issue of "prone to miss peaks" that MATLAB's ``robstab`` answers with interval tests).

**The test for one set of scalings.** Fix ``D_L = D^2 > 0``, ``G_L = D^2 G`` (the Lemma 2.1 form,
eq. 2.16) and a level ``beta``. Then ``mu(M(j w)) <= beta`` at every ``w`` where

    Phi(w) = M^* D_L M + j (G_L M - M^* G_L) - beta^2 D_L  <=  0,     M = C (j w I - A)^{-1} B + D.

``Phi`` is a para-Hermitian rational function of ``s = j w`` with the realisation
``[(sI - A)^{-1} B; I]^* Pi [(sI - A)^{-1} B; I]``, ``Pi = [C D; 0 I]^* [[D_L, -j G_L], [j G_L,
-beta^2 D_L]] [C D; 0 I] = [[Q, S], [S^*, R]]``. Because ``A`` is stable, ``Phi(j w)`` is singular
exactly where ``j w`` is an eigenvalue of the Hamiltonian matrix

    H = [[A - B R^{-1} S^*,            -B R^{-1} B^*      ],
         [-Q + S R^{-1} S^*,   -A^* + S R^{-1} B^*     ]]

(the zeros of ``Phi``; the same construction as the Hamiltonian test of the H-infinity norm,
Boyd-Balakrishnan-Kabamba 1989, Bruinsma-Steinbuch 1990). Between two consecutive crossing
frequencies no eigenvalue of ``Phi`` changes sign, so one evaluation inside tells whether the
whole piece is certified. One eigen-decomposition of a ``2n x 2n`` matrix therefore certifies
every frequency where those scalings work, typically a wide band around the grid point they were
optimised for.

**Covering the band** (ours, in the spirit of Ferreres, Magni and Biannic, IJRNC 2003): the band
starts uncovered; each step takes the uncovered interval, certifies with the scalings of the grid
point inside it with the lowest bound (they reach furthest), and removes what they certify. An
uncovered interval with no grid point left gets a new precise solve at its centre; if that
exceeds the level, the grid missed a peak: a local search finds it and the level rises to it.
The certified statement is ``mu-bar(w) <= level`` for every ``w`` of the band, with
``level = peak (1 + rtol)`` and ``peak`` the largest bound evaluated anywhere (grid, refinement
or certification points).

**What is rigorous and what is not.** Every certified piece is checked at explicit frequencies
(its midpoint and both ends, with the eigensolver's rounding margin) with the same scalings; a
piece is certified only if it contains no computed crossing. Crossings are taken generously
(every eigenvalue within ``CROSSING_RTOL`` of the imaginary axis counts), so an eigenvalue moved
off the axis by rounding still splits the piece. As for every Hamiltonian-based H-infinity norm
(MATLAB's ``hinfnorm``), the result holds up to the accuracy of those eigenvalues.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from setmem_hil.robust.augmented_plant import StateSpaceMatrices
from setmem_hil.robust.mixed_mu import MixedMuBound, MuStructure, mixed_mu_upper, rounding_margin

__all__ = ["BandCertificate", "certify_band", "certified_pieces", "CERTIFICATE_RTOL"]

CERTIFICATE_RTOL = 1e-4
"""The certified level is the largest evaluated bound times ``1 + CERTIFICATE_RTOL``."""
CROSSING_RTOL = 1e-2
"""Eigenvalues of the Hamiltonian with ``|Re| <= CROSSING_RTOL |lambda|`` split a piece (generous:
a spurious split costs one evaluation, a missed one could hide a violation)."""
END_SHRINK = 1e-6
"""Certified pieces stop this far (relative) inside a computed crossing; the sliver is left to
other scalings, so a crossing computed slightly off is never inside a claimed piece."""
D_FLOOR = 1e-12
"""``D_L`` entries are floored at this times the largest, keeping ``R`` invertible (any positive
``D_L`` gives a valid certificate; the checks use the floored values)."""
MAX_SCALINGS = 400
"""Hamiltonian tests per band before the certificate is given up (``certified = False``)."""
PEAK_SEARCH_POINTS = 9  # precise solves across an interval where the grid missed a peak
PRECISE_TOL, PRECISE_MAX_ITER = 1e-7, 100


@dataclass
class BandCertificate:
    """What :func:`certify_band` proved.

    Attributes
    ----------
    certified : bool
        Every frequency of ``band`` is covered by a certified piece (else the scaling budget ran out).
    level : float
        ``mu-bar(w) <= level`` on every certified piece: ``peak (1 + rtol)``.
    peak : float
        Largest bound evaluated anywhere (grid, refinement and the points added here).
    n_intervals : int
        Certified pieces in the cover of the band.
    n_scalings : int
        Hamiltonian tests done.
    omegas, matrices, bounds
        One entry per solve done here (beyond the grid): its frequencies, ``M(j w)`` and bounds;
        the analysis adds them to its curve.
    pieces : list of (lo, hi, d, g)
        The cover: each certified interval with the scalings (eq. 2.15) that prove it.
    """

    certified: bool
    level: float
    peak: float
    n_intervals: int
    n_scalings: int
    omegas: list = field(default_factory=list)
    matrices: list = field(default_factory=list)
    bounds: list = field(default_factory=list)
    pieces: list = field(default_factory=list)

    @property
    def omega(self) -> np.ndarray:
        """Every frequency solved here, in solve order."""
        return np.concatenate(self.omegas) if self.omegas else np.zeros(0)


def _lmi_scalings(d: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(D_L, G_L) = (D^2, D^2 G)`` of eq. (2.16), ``D_L`` floored (:data:`D_FLOOR`)."""
    d_l = d**2
    d_l = np.maximum(d_l, D_FLOOR * d_l.max())
    return d_l, d_l * g


def _phi_top(M: np.ndarray, d_l: np.ndarray, g_l: np.ndarray, beta: float) -> tuple[np.ndarray, np.ndarray]:
    """Largest eigenvalue of ``Phi(w)`` and its rounding margin, for a stack of ``M``."""
    Mh = np.conj(np.swapaxes(M, -1, -2))
    GM = g_l[:, None] * M
    Phi = Mh @ (d_l[:, None] * M) + 1j * (GM - np.conj(np.swapaxes(GM, -1, -2))) - beta**2 * np.diag(d_l)
    return np.linalg.eigvalsh(Phi)[..., -1], rounding_margin(Phi)


def crossing_frequencies(system: StateSpaceMatrices, d_l: np.ndarray, g_l: np.ndarray, beta: float) -> np.ndarray | None:
    """Frequencies ``w > 0`` where ``Phi(j w)`` may be singular (sorted; generous, see module doc);
    None when ``Phi(inf)`` is singular (no Hamiltonian)."""
    A, B, C, Dm = system.A, system.B, system.C, system.D
    DL, GL = np.diag(d_l), np.diag(g_l)
    Q = C.T @ DL @ C
    S = C.T @ DL @ Dm - 1j * C.T @ GL
    R = Dm.T @ DL @ Dm - 1j * Dm.T @ GL + 1j * GL @ Dm - beta**2 * DL
    try:
        RiSh = np.linalg.solve(R, np.conj(S.T))
        RiBt = np.linalg.solve(R, B.T)
    except np.linalg.LinAlgError:
        return None  # Phi(inf) singular at this level: these scalings give no interval test
    H = np.block([[A - B @ RiSh, -B @ RiBt], [-Q + S @ RiSh, -A.T + S @ RiBt]])
    lam = np.linalg.eigvals(H)
    near = np.abs(lam.real) <= CROSSING_RTOL * np.abs(lam)
    w = np.abs(lam[near].imag)
    return np.unique(w[w > 0])


def certified_pieces(system: StateSpaceMatrices, d: np.ndarray, g: np.ndarray, beta: float,
                     intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Sub-intervals of ``intervals`` where the scalings ``(d, g)`` of eq. (2.15) prove
    ``mu-bar <= beta`` (the Hamiltonian test of the module doc).

    Each segment between consecutive crossings is decided at its centre (with the rounding
    margin). Runs of certified segments are joined: a crossing between two of them is one of a
    lower eigenvalue of ``Phi``, and the top one is <= 0 there by continuity. Where a run meets an
    uncertified segment it stops :data:`END_SHRINK` short of the computed crossing, and that end
    is checked too, so a crossing computed slightly off never lends the run a violating sliver.
    """
    if not intervals:
        return []
    d_l, g_l = _lmi_scalings(d, g)
    cuts = crossing_frequencies(system, d_l, g_l, beta)
    if cuts is None:
        return []
    segments = []  # (lo, hi, lo is a crossing, hi is a crossing)
    for lo, hi in intervals:
        inner = cuts[(cuts > lo) & (cuts < hi)]
        edges = np.concatenate([[lo], inner, [hi]])
        n = edges.size - 1
        segments.extend((edges[i], edges[i + 1], i > 0, i < n - 1) for i in range(n))
    ends = np.array([(a, b) for a, b, _, _ in segments])
    centres = np.where(ends[:, 0] > 0.0, np.sqrt(ends[:, 0] * ends[:, 1]), 0.5 * ends[:, 1])
    tops, margins = _phi_top(system.frequency_response(centres), d_l, g_l, beta)
    good = tops + margins <= 0.0
    runs = []
    for (a, b, a_cut, b_cut), ok in zip(segments, good):
        if not ok:
            continue
        if runs and a_cut and runs[-1][1] == a:  # joins the previous certified segment
            runs[-1] = (runs[-1][0], b, runs[-1][2], b_cut)
        else:
            runs.append((a, b, a_cut, b_cut))
    pieces = []
    for a, b, a_cut, b_cut in runs:
        a_in = a * (1.0 + END_SHRINK) if a_cut else a
        b_in = b * (1.0 - END_SHRINK) if b_cut else b
        if b_in > a_in:
            pieces.append((a_in, b_in, a_cut, b_cut))
    if not pieces:
        return []
    shrunk = [w for a, b, a_cut, b_cut in pieces for w, cut in ((a, a_cut), (b, b_cut)) if cut]
    bad = set()
    if shrunk:
        end_tops, _ = _phi_top(system.frequency_response(np.array(shrunk)), d_l, g_l, beta)
        bad = {w for w, top in zip(shrunk, end_tops) if top > 0.0}
    return [(a, b) for a, b, _, _ in pieces if a not in bad and b not in bad]


def _subtract(intervals: list[tuple[float, float]], pieces: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """``intervals`` minus the union of ``pieces`` (both lists of closed intervals)."""
    out = list(intervals)
    for a, b in pieces:
        nxt = []
        for lo, hi in out:
            if b <= lo or a >= hi:
                nxt.append((lo, hi))
                continue
            if lo < a:
                nxt.append((lo, a))
            if b < hi:
                nxt.append((b, hi))
        out = nxt
    return out


class _Pool:
    """Frequencies with scalings, not yet used for a Hamiltonian test."""

    def __init__(self, omega: np.ndarray, bound: MixedMuBound):
        self.omega = np.asarray(omega, dtype=float)
        self.beta = np.asarray(bound.beta, dtype=float)
        self.d = np.asarray(bound.d)
        self.g = np.asarray(bound.g)
        self.used = np.zeros(self.omega.size, dtype=bool)

    def add(self, omega: np.ndarray, bound: MixedMuBound) -> None:
        self.omega = np.concatenate([self.omega, omega])
        self.beta = np.concatenate([self.beta, bound.beta])
        self.d = np.concatenate([self.d, bound.d])
        self.g = np.concatenate([self.g, bound.g])
        self.used = np.concatenate([self.used, np.zeros(omega.size, dtype=bool)])

    def best_inside(self, lo: float, hi: float, level: float) -> int | None:
        """Unused point in ``[lo, hi]`` with the lowest bound below ``level``, if any."""
        ok = ~self.used & (self.omega >= lo) & (self.omega <= hi) & (self.beta < level)
        if not ok.any():
            return None
        idx = np.flatnonzero(ok)
        return int(idx[np.argmin(self.beta[idx])])


def certify_band(
    system: StateSpaceMatrices,
    structure: MuStructure,
    band: tuple[float, float],
    omega: np.ndarray,
    bound: MixedMuBound,
    rtol: float = CERTIFICATE_RTOL,
    max_scalings: int = MAX_SCALINGS,
) -> BandCertificate:
    """Certify ``mu-bar(w) <= peak (1 + rtol)`` on the whole ``band`` (module doc).

    Parameters
    ----------
    system : StateSpaceMatrices
        The stable closed loop ``M(s)`` (its ``A`` must be Hurwitz).
    structure : MuStructure
        Block structure of ``Delta`` (eq. 2.11).
    band : (float, float)
        Frequencies (rad/s) to certify, ``0 <= lo < hi``.
    omega : np.ndarray
        Frequencies already solved (the grid and its refinement) ...
    bound : MixedMuBound
        ... and their bounds and scalings.
    rtol : float
        Relative tolerance of the certified level over the largest evaluated bound.
    max_scalings : int
        Budget of Hamiltonian tests.

    Returns
    -------
    BandCertificate
    """
    lo, hi = float(band[0]), float(band[1])
    if not (0.0 <= lo < hi):
        raise ValueError(f"band: expected 0 <= lo < hi, found {band!r}")
    pool = _Pool(omega, bound)
    peak = float(np.max(bound.beta))
    new_w, new_M, new_b = [], [], []

    def solve(points: np.ndarray) -> MixedMuBound:
        nonlocal peak
        M = system.frequency_response(points)
        b = mixed_mu_upper(M, structure, tol=PRECISE_TOL, max_iter=PRECISE_MAX_ITER)
        pool.add(points, b)
        new_w.append(points)
        new_M.append(M)
        new_b.append(b)
        peak = max(peak, float(b.beta.max()))
        return b

    uncovered = [(lo, hi)]
    cover = []
    n_tests = 0
    while uncovered and n_tests < max_scalings:
        a, b = uncovered[0]
        level = peak * (1.0 + rtol)
        k = pool.best_inside(a, b, level)
        if k is None:
            centre = np.array([np.sqrt(a * b) if a > 0.0 else 0.5 * b])
            if solve(centre).beta[0] >= level:
                _search_missed_peak(solve, a, b)
            continue
        pool.used[k] = True
        n_tests += 1
        pieces = certified_pieces(system, pool.d[k], pool.g[k], level, uncovered)
        cover.extend((p_lo, p_hi, pool.d[k], pool.g[k]) for p_lo, p_hi in pieces)
        uncovered = _subtract(uncovered, pieces)
    level = peak * (1.0 + rtol)
    return BandCertificate(
        certified=not uncovered,
        level=level,
        peak=peak,
        n_intervals=len(cover),
        n_scalings=n_tests,
        omegas=new_w,
        matrices=new_M,
        bounds=new_b,
        pieces=cover,
    )


def _search_missed_peak(solve, a: float, b: float) -> None:
    """The grid missed a peak in ``(a, b)``: solve across it, then twice around the largest value
    (the same 2 x 6 refinement as the grid's peak), so the level rises to the peak's value."""
    a = max(a, 1e-6 * b)  # geometric spacing needs a > 0
    points = np.geomspace(a, b, PEAK_SEARCH_POINTS + 2)[1:-1]
    found = solve(points)
    w, beta = points, found.beta
    for _ in range(2):
        k = int(np.argmax(beta))
        left = w[k - 1] if k > 0 else a
        right = w[k + 1] if k + 1 < w.size else b
        finer = np.geomspace(left, right, 8)[1:-1]
        more = solve(finer)
        w = np.concatenate([w, finer])
        beta = np.concatenate([beta, more.beta])
        order = np.argsort(w)
        w, beta = w[order], beta[order]
