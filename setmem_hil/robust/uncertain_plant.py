"""Nominal plant plus rank-one parametric uncertainty (thesis eq. 6.2-6.12).

Each uncertain parameter ``theta_i = mid_i + q_i * width_i / 2`` with ``|q_i| <= 1`` (the midpoint
is the nominal model, eq. 2.25) perturbs the block-diagonal state space of eq. (2.6)-(2.8) by a
rank-one term ``q_i l_i n_i^T``:

* ``a1`` and ``a0`` of mode ``k`` enter the ``A`` matrix (``A_k = [[0, 1], [-a0, -a1]]``), so
  ``l = -sqrt(h) e_{2k+1}`` and ``n = sqrt(h) e_{2k+1}`` (``a1``) or ``n = sqrt(h) e_{2k}`` (``a0``),
  with ``h = width / 2``;
* ``b1`` and ``b0`` enter ``C = [b0, b1]``: ``l = sqrt(h)`` (a scalar output) and
  ``n = sqrt(h) e_{2k+1}`` (``b1``) or ``n = sqrt(h) e_{2k}`` (``b0``).

With a common **gain** ``k`` in ``[k_lo, k_hi]`` on the whole plant (the sensors' calibration,
:mod:`setmem_hil.identification.calibration_scale`: the model was identified as measured, the
plant is ``k`` times it), ``C_true = k (C_mid + Delta C)`` with ``k = k0 (1 + delta)``,
``|delta| <= e``: the nominal ``C`` is ``k0 C_mid``, each residue's term is widened to
``k0 (1 + e)`` times its half width (that holds ``(1 + delta) Delta C``) and one more real
parameter ``gain`` adds ``q k0 e C_mid`` (``l = sqrt(k0 e)``, ``n = sqrt(k0 e) C_mid``). The set
is exactly represented (``q_gain = delta / e``, ``q_i' = q_i (1 + delta) / (1 + e)``), and the
common scale is one uncertainty instead of an independent widening of every residue (0.005 of
mu-bar instead of 0.022 at the end of a section 6.3.2 campaign, 1 % calibration per sensor). A
choice of this project; the thesis's structure is the rest.

The scaling ``||l_i|| = ||n_i||`` is the thesis's choice (section 6.3.1). Parameters in ``A``
come first (``r`` of them, eq. 6.5-6.6: ``E_a, F_a``), then those in ``C`` (``E_c, F_c``), each
group in mode order and, within a mode, in :data:`~setmem_hil.model.modal_model.PARAM_NAMES` order.
Fixed parameters (zero width) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.model.modal_model import A0, A1, B0, B1, PARAM_NAMES, IntervalModel


@dataclass(frozen=True)
class UncertainPlant:
    """Nominal plant and the rank-one uncertainty structure of eq. (6.7)-(6.12).

    Attributes
    ----------
    A, B, C : np.ndarray
        Nominal (midpoint) state space, eq. (2.6)-(2.8); ``D = 0``.
    E_a : np.ndarray, shape (n_states, r)
        Columns ``l_i`` of the parameters in ``A`` (eq. 6.5).
    F_a : np.ndarray, shape (r, n_states)
        Rows ``n_i^T`` of the parameters in ``A`` (eq. 6.6).
    E_c : np.ndarray, shape (1, p - r)
        The (scalar) ``l_i`` of the parameters in ``C``.
    F_c : np.ndarray, shape (p - r, n_states)
        Rows ``n_i^T`` of the parameters in ``C``.
    names : tuple of str
        ``'<param>_<mode>'`` (modes from 1) of the ``p`` uncertain parameters, in the order of
        ``blockdiag(Q_a, Q_c)`` (eq. 6.23).
    half_widths : np.ndarray, shape (p,)
        ``width_i / 2``: the parameter change for ``q_i = 1``.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    E_a: np.ndarray
    F_a: np.ndarray
    E_c: np.ndarray
    F_c: np.ndarray
    names: tuple[str, ...]
    half_widths: np.ndarray

    @property
    def n_real(self) -> int:
        """Number ``p`` of uncertain (real) parameters."""
        return len(self.names)

    @property
    def n_a(self) -> int:
        """Number ``r`` of uncertain parameters in the ``A`` matrix."""
        return self.E_a.shape[1]

    def perturbed_matrices(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(A + E_a Q_a F_a, C + E_c Q_c F_c)`` for normalised offsets ``q`` (eq. 6.2-6.3)."""
        q = np.asarray(q, dtype=float)
        if q.shape != (self.n_real,):
            raise ValueError(f"q: expected shape ({self.n_real},), found {q.shape}")
        r = self.n_a
        A = self.A + self.E_a @ np.diag(q[:r]) @ self.F_a
        C = self.C + self.E_c @ np.diag(q[r:]) @ self.F_c
        return A, C


def uncertain_plant(model: IntervalModel, gain: tuple[float, float] | None = None) -> UncertainPlant:
    """Rank-one uncertainty description of an interval model (eq. 6.2-6.12).

    Parameters
    ----------
    model : IntervalModel
        Parameter intervals; the nominal plant is at the midpoints (eq. 2.25).
    gain : (float, float), optional
        A common gain interval ``[k_lo, k_hi]`` (``0 < k_lo <= k_hi``) on the whole plant
        (module docstring): one more real parameter, ``gain``, last.

    Returns
    -------
    UncertainPlant
        With ``A + sum_i q_i l_i n_i^T`` (``i <= r``) and ``C + sum_i q_i l_i n_i^T``
        (``i > r``) spanning exactly the interval box for ``|q_i| <= 1``.

    Examples
    --------
    >>> import numpy as np
    >>> from setmem_hil.model.modal_model import IntervalModel
    >>> m = IntervalModel([[0.01, 0.9, 0.0, 3.0]], [[0.03, 1.1, 0.0, 5.0]])
    >>> uncertain_plant(m).names
    ('a1_1', 'a0_1', 'b0_1')
    """
    A, B, C, _ = model.midpoint.state_space_matrices()
    n_states = A.shape[0]
    half = 0.5 * model.width
    k0, e = 1.0, 0.0
    if gain is not None:
        k_lo, k_hi = (float(v) for v in gain)
        if not 0.0 < k_lo <= k_hi:
            raise ValueError(f"gain: expected 0 < k_lo <= k_hi, found {gain!r}")
        k0, e = 0.5 * (k_lo + k_hi), (k_hi - k_lo) / (k_lo + k_hi)
    residue_factor = k0 * (1.0 + e)  # the residues' box, scaled and widened to hold (1 + delta) Delta C
    a_cols, a_rows, c_cols, c_rows = [], [], [], []
    a_names, c_names, a_half, c_half = [], [], [], []
    for mode in range(model.n_modes):
        k = 2 * mode
        for j in (A1, A0):
            if half[mode, j] <= 0.0:
                continue
            s = np.sqrt(half[mode, j])
            l = np.zeros(n_states)
            n = np.zeros(n_states)
            l[k + 1] = -s
            n[k + 1 if j == A1 else k] = s
            a_cols.append(l)
            a_rows.append(n)
            a_names.append(f"{PARAM_NAMES[j]}_{mode + 1}")
            a_half.append(half[mode, j])
    for mode in range(model.n_modes):
        k = 2 * mode
        for j in (B1, B0):
            if half[mode, j] <= 0.0:
                continue
            h = residue_factor * half[mode, j]
            s = np.sqrt(h)
            n = np.zeros(n_states)
            n[k + 1 if j == B1 else k] = s
            c_cols.append(s)
            c_rows.append(n)
            c_names.append(f"{PARAM_NAMES[j]}_{mode + 1}")
            c_half.append(h)
    if e > 0.0:
        s = np.sqrt(k0 * e)
        c_cols.append(s)
        c_rows.append(s * np.ravel(C))
        c_names.append("gain")
        c_half.append(k0 * e)
    C = k0 * C
    E_a = np.array(a_cols).T.reshape(n_states, len(a_cols))
    F_a = np.array(a_rows).reshape(len(a_rows), n_states)
    E_c = np.array(c_cols, dtype=float).reshape(1, len(c_cols))
    F_c = np.array(c_rows).reshape(len(c_rows), n_states)
    return UncertainPlant(
        A=A,
        B=B,
        C=C,
        E_a=E_a,
        F_a=F_a,
        E_c=E_c,
        F_c=F_c,
        names=tuple(a_names + c_names),
        half_widths=np.array(a_half + c_half, dtype=float),
    )
