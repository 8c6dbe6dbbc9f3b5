"""Augmented open-loop plant and the closed loop ``M`` of the ``M-Delta`` form (eq. 6.14-6.23).

Inputs of the augmented plant ``P`` are ``[w_a, w_c, w_1, w_2, u]`` and outputs
``[z_a, z_c, z_1, z_2, y]`` (eq. 6.16-6.22): ``w_a = Q_a z_a`` and ``w_c = Q_c z_c`` are the real
parametric uncertainties, ``w_1 = Delta_1 z_1`` the additive unmodelled dynamics
(``z_1 = W_1 u``), and ``w_2 = Delta_2 z_2`` the fictitious performance block
(``z_2 = W_2 y``; ``w_2`` is an output disturbance, so ``z_2 = W_2 S w_2`` nominally). The
uncertainty is ``Delta = blockdiag(Q_a, Q_c, Delta_1, Delta_2)`` (eq. 6.23): ``p`` real scalars
then two complex scalars.

Sign convention: the thesis designs with *positive* feedback (footnote 3 of section 6.3.2), and
so do we: ``u = K y``. The closed loop ``M`` is the lower LFT ``F_l(P, K)`` for that sign.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import tf2ss

from setmem_hil.robust.uncertain_plant import UncertainPlant
from setmem_hil.model.weights import Weights


@dataclass(frozen=True)
class StateSpaceMatrices:
    """Plain ``(A, B, C, D)`` of a continuous-time system."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    def frequency_response(self, omega_rad_s) -> np.ndarray:
        """``C (j omega I - A)^{-1} B + D`` for every omega, shape ``(n_omega, n_out, n_in)``."""
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
        n = self.n_states
        if n == 0:
            return np.broadcast_to(self.D.astype(complex), (w.size,) + self.D.shape).copy()
        lhs = 1j * w[:, None, None] * np.eye(n)[None] - self.A[None]
        rhs = np.broadcast_to(self.B.astype(complex), (w.size,) + self.B.shape)
        X = np.linalg.solve(lhs, rhs)
        return np.einsum("ij,wjk->wik", self.C, X) + self.D[None]

    def to_statespace(self):
        """As a python-control ``StateSpace``."""
        import control

        return control.ss(self.A, self.B, self.C, self.D)


def weight_state_space(num, den) -> StateSpaceMatrices:
    """Minimal controllable realisation of a proper SISO weight (eq. 6.14-6.15)."""
    A, B, C, D = tf2ss(np.asarray(num, dtype=float), np.asarray(den, dtype=float))
    return StateSpaceMatrices(
        np.atleast_2d(A).astype(float),
        np.atleast_2d(B).reshape(-1, 1).astype(float),
        np.atleast_2d(C).reshape(1, -1).astype(float),
        np.atleast_2d(D).reshape(1, 1).astype(float),
    )


@dataclass(frozen=True)
class AugmentedPlant:
    """The open-loop system ``P`` of eq. (6.16)-(6.22) and its uncertainty structure.

    Attributes
    ----------
    A, Bw, Bu, Cz, Dzw, Dzu, Cy, Dyw : np.ndarray
        ``A~, L~, B~, C~_1, D~_11, D~_12, C~_2, D~_21`` of eq. (6.20)-(6.22); ``D~_22 = 0``.
    n_real : int
        Number of real scalar blocks (the uncertain parameters), first in ``Delta``.
    n_complex : int
        Number of complex scalar blocks (2: ``Delta_1``, ``Delta_2``), last in ``Delta``.
    names : tuple of str
        Names of the real blocks, ``'<param>_<mode>'``.
    """

    A: np.ndarray
    Bw: np.ndarray
    Bu: np.ndarray
    Cz: np.ndarray
    Dzw: np.ndarray
    Dzu: np.ndarray
    Cy: np.ndarray
    Dyw: np.ndarray
    n_real: int
    n_complex: int
    names: tuple[str, ...]

    @property
    def n_w(self) -> int:
        return self.Bw.shape[1]

    def to_statespace(self):
        """``P`` as a python-control ``StateSpace`` with inputs ``[w, u]``, outputs ``[z, y]``."""
        import control

        B = np.hstack([self.Bw, self.Bu])
        C = np.vstack([self.Cz, self.Cy])
        D = np.block([[self.Dzw, self.Dzu], [self.Dyw, np.zeros((1, 1))]])
        return control.ss(self.A, B, C, D)

    def closed_loop(self, controller) -> StateSpaceMatrices:
        """``M = F_l(P, K)`` from ``w`` to ``z`` with positive feedback ``u = K y``.

        Parameters
        ----------
        controller : control.StateSpace or StateSpaceMatrices
            SISO compensator ``K``.
        """
        Ak, Bk, Ck, Dk = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (controller.A, controller.B, controller.C, controller.D))
        Ak = Ak.reshape(Ak.shape[0], -1) if Ak.size else np.zeros((0, 0))
        nk = Ak.shape[0]
        Bk = Bk.reshape(nk, 1)
        Ck = Ck.reshape(1, nk)
        Dk = Dk.reshape(1, 1)
        A = np.block([[self.A + self.Bu @ Dk @ self.Cy, self.Bu @ Ck], [Bk @ self.Cy, Ak]])
        B = np.vstack([self.Bw + self.Bu @ Dk @ self.Dyw, Bk @ self.Dyw])
        C = np.hstack([self.Cz + self.Dzu @ Dk @ self.Cy, self.Dzu @ Ck])
        D = self.Dzw + self.Dzu @ Dk @ self.Dyw
        return StateSpaceMatrices(A, B, C, D)


def augmented_plant(plant: UncertainPlant, weights: Weights, design_w2: bool = True) -> AugmentedPlant:
    """Build ``P`` of eq. (6.20)-(6.22).

    Parameters
    ----------
    plant : UncertainPlant
        Nominal plant and rank-one parametric uncertainty (eq. 6.7-6.12).
    weights : Weights
        ``W_1`` (eq. 6.1) and ``W_2`` (eq. 6.13).
    design_w2 : bool
        Use ``W_2`` with the extra roll-off pole (section 6.3.1), which makes ``D_2 = 0`` so the
        H2 problem is well posed. The same plant is used for the analysis: the pole at
        ``10^4`` rad/s changes ``|W_2|`` by less than 0.5 % below 1000 rad/s.
    """
    w1 = weight_state_space(weights.w1_num, weights.w1_den)
    w2_num, w2_den = weights.w2_for_design() if design_w2 else (weights.w2_num, weights.w2_den)
    w2 = weight_state_space(w2_num, w2_den)
    A, B, C = plant.A, plant.B, plant.C
    n, n1, n2 = A.shape[0], w1.n_states, w2.n_states
    r, pc = plant.n_a, plant.F_c.shape[0]
    E_a, F_a, E_c, F_c = plant.E_a, plant.F_a, plant.E_c, plant.F_c
    Z = np.zeros
    # eq. (6.20)
    At = np.block(
        [
            [A, Z((n, n1)), Z((n, n2))],
            [Z((n1, n)), w1.A, Z((n1, n2))],
            [w2.B @ C, Z((n2, n1)), w2.A],
        ]
    )
    Lt = np.block(
        [
            [E_a, Z((n, pc)), Z((n, 1)), Z((n, 1))],
            [Z((n1, r)), Z((n1, pc)), Z((n1, 1)), Z((n1, 1))],
            [Z((n2, r)), w2.B @ E_c, w2.B, w2.B],
        ]
    )
    Bt = np.vstack([B, w1.B, Z((n2, 1))])
    # eq. (6.21)
    C1 = np.block(
        [
            [F_a, Z((r, n1)), Z((r, n2))],
            [F_c, Z((pc, n1)), Z((pc, n2))],
            [Z((1, n)), w1.C, Z((1, n2))],
            [w2.D @ C, Z((1, n1)), w2.C],
        ]
    )
    D11 = np.block(
        [
            [Z((r + pc + 1, r)), Z((r + pc + 1, pc)), Z((r + pc + 1, 2))],
            [Z((1, r)), w2.D @ E_c, w2.D, w2.D],
        ]
    )
    D12 = np.vstack([Z((r + pc, 1)), w1.D, Z((1, 1))])
    # eq. (6.22)
    C2 = np.hstack([C, Z((1, n1)), Z((1, n2))])
    D21 = np.hstack([Z((1, r)), E_c, np.ones((1, 2))])
    return AugmentedPlant(At, Lt, Bt, C1, D11, D12, C2, D21, r + pc, 2, plant.names)
