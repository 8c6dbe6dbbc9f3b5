"""The beam driven by a generator's arbitrary waveform: points held one sample period each (issue 26).

A generator playing an arbitrary waveform with its interpolation filter off holds each point
``u_j`` for ``1 / rate`` seconds and repeats the whole waveform (``N`` points) for as long as the
output is on. Over a hold the force ``F = k u_j`` is constant, so the modal state moves exactly as

    z(t) = exp(lambda (t - t_j)) z_j + (exp(lambda (t - t_j)) - 1) / lambda  (V^-1 B) F

in the modal coordinates ``z = V^-1 x`` of ``A = V diag(lambda) V^-1`` (the beam's modes are
distinct and damped, so ``A`` is diagonalisable and no ``lambda`` is zero). :class:`HeldWaveform`
gives the state and the outputs at any times, vectorised over the samples of a record; what the
bench does with them is in :class:`~setmem_hil.sim_backends.instrument_bench.EmulatedBench`.
No I/O here.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["HeldWaveform"]


class HeldWaveform:
    """``A``, ``B`` (state space of the structure) and a waveform of force values ``force_n``
    (one per point, newtons) held ``1 / rate_hz`` each, starting at clock time ``t_start``."""

    def __init__(self, A: np.ndarray, B: np.ndarray, force_n: np.ndarray, rate_hz: float, t_start: float):
        self.lam, self.V = np.linalg.eig(A)
        self.Vinv = np.linalg.inv(self.V)
        self.Bm = self.Vinv @ np.asarray(B, dtype=float)
        self.force_n = np.asarray(force_n, dtype=float)
        self.rate_hz, self.t_start = float(rate_hz), float(t_start)
        self.period_s = self.force_n.size / self.rate_hz

    def force_at(self, t: np.ndarray) -> np.ndarray:
        k = np.floor((np.asarray(t, dtype=float) - self.t_start) * self.rate_hz + 1e-9).astype(np.int64)
        return self.force_n[np.mod(k, self.force_n.size)]

    def _hold(self, z: np.ndarray, tau: np.ndarray | float, force: np.ndarray | float) -> np.ndarray:
        e = np.exp(np.multiply.outer(tau, self.lam))
        return e * z + (e - 1.0) / self.lam * np.multiply.outer(force, self.Bm)

    def advance(self, x: np.ndarray, t_from: float, t_to: float) -> np.ndarray:
        """The real state at ``t_to`` from ``x`` at ``t_from``, hold by hold."""
        return np.real(self.V @ self._z_at_edges(self.Vinv @ x, t_from, t_to)[-1][1])

    def _hold_index(self, k: int) -> float:
        return float(self.force_n[k % self.force_n.size])

    def _z_at_edges(self, z: np.ndarray, t_from: float, t_to: float) -> list[tuple[float, np.ndarray, int]]:
        """``(t, z, k)`` at ``t_from``, at every hold's edge inside, and at ``t_to``; ``k`` the
        point held from ``t`` on. Each edge is ``t_start + k / rate`` from its integer ``k``
        (not a running sum of ``1 / rate``: at thousands of seconds that drifts by more than the
        index test's room, and the structure would be driven by the wrong point)."""
        rate = self.rate_hz
        held = math.floor((t_from - self.t_start) * rate + 1e-9)  # the point under way at t_from (an edge within 1e-9 counts as passed)
        a, k = t_from, held + 1  # the next edge
        out = [(t_from, z, held)]
        while True:
            b = self.t_start + k / rate
            if b >= t_to:
                break
            if b > a:
                z = self._hold(z, b - a, self._hold_index(held))
                out.append((b, z, k))
                a = b
            held, k = k, k + 1
        if t_to > a:
            z = self._hold(z, t_to - a, self._hold_index(held))
            out.append((t_to, z, held))
        return out

    def samples(self, x: np.ndarray, t_now: float, times: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The force and every output row ``rows @ x`` at ``times`` (ascending, >= ``t_now``)."""
        times = np.asarray(times, dtype=float)
        edges = self._z_at_edges(self.Vinv @ x, t_now, float(times[-1]))
        starts = np.array([t for t, _, _ in edges])
        zs = np.array([z for _, z, _ in edges])
        held = np.array([k for _, _, k in edges])
        j = np.clip(np.searchsorted(starts, times, side="right") - 1, 0, len(starts) - 1)
        tau = times - starts[j]
        force = self.force_n[np.mod(held[j], self.force_n.size)]
        e = np.exp(np.multiply.outer(tau, self.lam))
        z = e * zs[j] + (e - 1.0) / self.lam * np.multiply.outer(force, self.Bm)
        outputs = np.real(z @ (rows @ self.V).T).T
        return self.force_at(times), outputs
