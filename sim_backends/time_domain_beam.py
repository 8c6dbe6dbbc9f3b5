"""Time-domain simulation of the modal beam driven by a sinusoidal shaker force.

The structure is the block-diagonal state space of thesis eq. (2.6)-(2.8) (tip force to tip
displacement, ``setmem_hil.sim_backends.beam.beam_parameters()``, 8 modes). The shaker force
is a *continuous* sinusoid ``f(t) = a sin(omega (t - t_on))``. We generate it with a two-state
exosystem ``z' = S z``, ``S = [[0, omega], [-omega, 0]]``, ``f = z[0]``, and discretise the
augmented autonomous system

    d/dt [x; z] = [[A, B e1^T], [0, S]] [x; z]

exactly with ``scipy.linalg.expm`` of the augmented matrix times the sample interval. This is
the exact zero-order-hold discretisation of the augmented system (it has no input), so the
samples are those of the continuous-time solution, with no ZOH distortion of the sinusoid
itself: a ZOH of the *force* would delay it by half a sample (``omega dt / 2``, 0.1 rad at 32
samples per period), which would bias the phase of every measured response. Hence the true
response at ``omega`` is exactly ``params.frequency_response(omega)`` (eq. 2.3), and the
transient after any change of input is exactly the sum of the modal free responses with poles
``-zeta_k omega_k +- j omega_k sqrt(1 - zeta_k^2)``.

A multisine ``f(t) = sum_k a_k sin(omega_k (t - t_on) + phi_k)`` (:meth:`TimeDomainBeam.set_multisine`)
uses one such two-state block per line (``f`` is the sum of their first states); one line with
phase 0 is exactly the single sine.

No noise and no I/O here; the fake device (``fake_device_core``) adds sensor noise and a
virtual clock.

Example
-------
>>> import numpy as np
>>> from setmem_hil.sim_backends.beam import beam_parameters
>>> beam = TimeDomainBeam(beam_parameters())
>>> beam.set_sine(2.0, 1.0)
>>> force, disp = beam.simulate(64, 0.1)
>>> force.shape, disp.shape
((64,), (64,))
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from setmem_hil.numerics.blas_threads import blas_one_thread
from setmem_hil.model.modal_model import ModalParameters


@dataclass
class TimeDomainBeam:
    """Exact sampled simulation of a modal structure under sinusoidal force.

    Parameters
    ----------
    params : ModalParameters
        The true structure (all its modes are simulated).
    others : tuple of ModalParameters
        Further sensors on the same structure (issue 25): the same poles, their own residues.
        Each is one more output row ``C_k`` of the same state (eq. 2.8 per output).

    Attributes
    ----------
    x : ndarray, shape (2 n_modes,)
        Structural state (per mode: displacement-like state, its derivative; eq. 2.6).
    z : ndarray, shape (2 L,)
        Exosystem state, per line ``[a sin(phase), a cos(phase)]``; the force is the sum of the
        lines' first states.
    omega_rad_s : float
        Current excitation frequency (0 when stopped; the first line of a multisine).
    amplitude_n : float
        Current force amplitude (a multisine: the sum of its lines' amplitudes, a bound of its peak).
    line_omegas_rad_s : tuple of float
        The lines of the exosystem (one for a sine; ``(0.0,)`` after :meth:`reset`; kept by
        :meth:`stop`, whose exosystem state is zero).
    """

    params: ModalParameters
    others: tuple[ModalParameters, ...] = ()
    x: np.ndarray = field(init=False)
    z: np.ndarray = field(init=False)
    omega_rad_s: float = field(init=False, default=0.0)
    amplitude_n: float = field(init=False, default=0.0)
    line_omegas_rad_s: tuple[float, ...] = field(init=False, default=())

    def __post_init__(self):
        A, B, C, _ = self.params.state_space_matrices()
        rows = [C]
        for k, other in enumerate(self.others, start=2):
            A_k, _, C_k, _ = other.state_space_matrices()
            if A_k.shape != A.shape or not np.allclose(A_k, A, rtol=1e-12, atol=0.0):
                raise ValueError(f"sensor {k}: its poles differ from sensor 1's (one structure has one set of poles)")
            rows.append(C_k)
        self._A, self._B, self._C = A, B, np.vstack(rows)
        self._n = A.shape[0]
        self._phi_cache: dict[tuple, np.ndarray] = {}
        self.reset()

    # -- state -----------------------------------------------------------------------------
    def reset(self) -> None:
        """Put the structure at rest and the force at zero."""
        self.x = np.zeros(self._n)
        self.z = np.zeros(2)
        self.omega_rad_s = 0.0
        self.amplitude_n = 0.0
        self.line_omegas_rad_s = (0.0,)

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        """Start ``f = amplitude sin(omega (t - now))`` (phase 0 at the moment of the command).

        The structural state is kept, so a change of frequency causes a transient.
        """
        if not (np.isfinite(omega_rad_s) and omega_rad_s > 0):
            raise ValueError(f"omega_rad_s: expected a finite positive frequency, found {omega_rad_s!r}")
        if not (np.isfinite(amplitude_n) and amplitude_n >= 0):
            raise ValueError(f"amplitude_n: expected a finite amplitude >= 0, found {amplitude_n!r}")
        self.omega_rad_s = float(omega_rad_s)
        self.amplitude_n = float(amplitude_n)
        self.line_omegas_rad_s = (self.omega_rad_s,)
        self.z = np.array([0.0, float(amplitude_n)])

    def set_multisine(self, omegas_rad_s, amplitudes_n, phases_rad) -> None:
        """Start ``f = sum_k a_k sin(omega_k (t - now) + phi_k)``; the structural state is kept."""
        w, a, p = (np.atleast_1d(np.asarray(v, dtype=float)).ravel() for v in (omegas_rad_s, amplitudes_n, phases_rad))
        if not (w.size >= 1 and w.size == a.size == p.size):
            raise ValueError(f"multisine: expected equal numbers of frequencies, amplitudes and phases, found {w.size}, {a.size}, {p.size}")
        if not (np.all(np.isfinite(w)) and np.all(w > 0) and np.all(np.isfinite(a)) and np.all(a >= 0) and np.all(np.isfinite(p))):
            raise ValueError(f"multisine: expected finite positive frequencies and amplitudes >= 0, found {w.tolist()}, {a.tolist()}")
        self.omega_rad_s = float(w[0])
        self.amplitude_n = float(np.sum(a))
        self.line_omegas_rad_s = tuple(float(v) for v in w)
        self.z = np.column_stack([a * np.sin(p), a * np.cos(p)]).ravel()

    def stop(self) -> None:
        """Force to zero; the structure keeps ringing at its own modes."""
        self.z = np.zeros(self.z.size)
        self.amplitude_n = 0.0

    # -- simulation ------------------------------------------------------------------------
    def transition_matrix(self, dt_s: float) -> np.ndarray:
        """``expm(M dt)`` of the augmented matrix ``M = [[A, B e1^T ...], [0, S]]`` (cached)."""
        lines = self.line_omegas_rad_s
        key = (lines, float(dt_s))
        phi = self._phi_cache.get(key)
        if phi is None:
            n, m = self._n, 2 * len(lines)
            M = np.zeros((n + m, n + m))
            M[:n, :n] = self._A
            for k, w in enumerate(lines):
                e = n + 2 * k
                M[:n, e] = self._B[:, 0]
                M[e, e + 1] = w
                M[e + 1, e] = -w
            with blas_one_thread():
                phi = expm(M * dt_s)
            if len(self._phi_cache) > 64:
                self._phi_cache.clear()
            self._phi_cache[key] = phi
        return phi

    def simulate(self, n_samples: int, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``n_samples`` steps of ``dt_s``; return (force, displacement) at each step start.

        Sample ``k`` is taken at ``k dt`` after the current time; on return the state is at
        ``n_samples dt``. Exact for the continuous-time system (no discretisation error).
        """
        force, outputs = self.simulate_outputs(n_samples, dt_s)
        return force, outputs[:, 0]

    def simulate_outputs(self, n_samples: int, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`simulate`, with every sensor's displacement: shape ``(n_samples, 1 + len(others))``."""
        if n_samples < 0 or not (dt_s > 0):
            raise ValueError(f"simulate: expected n_samples >= 0 and dt_s > 0, found {n_samples}, {dt_s}")
        phi = self.transition_matrix(dt_s)
        n = self._n
        s = np.concatenate([self.x, self.z])
        states = np.empty((n_samples, s.size))
        for k in range(n_samples):
            states[k] = s
            s = phi @ s
        self.x, self.z = s[:n].copy(), s[n:].copy()
        force = states[:, n::2].sum(axis=1)  # the lines' first states (one line: exactly z[0])
        # row by row: the first output is computed exactly as a one-sensor beam computes it
        return force, np.column_stack([states[:, :n] @ row for row in self._C])

    def true_response(self, omega_rad_s) -> np.ndarray:
        """Steady-state response over force, ``G(j omega)`` (eq. 2.3)."""
        return self.params.frequency_response(omega_rad_s)
