"""Modal model of a lightly damped structure, with interval-valued parameters.

A mode is ``G_i(s) = (b1_i s + b0_i) / (s^2 + a1_i s + a0_i)`` (thesis eq. 2.1-2.3, 3.6), so
``a0 = omega_n^2`` and ``a1 = 2 zeta omega_n``. Parameters are held per mode in the order
``PARAM_NAMES = ("a1", "a0", "b1", "b0")`` (the thesis's theta of Problem 3.2), as arrays of
shape ``(n_modes, 4)``: :class:`ModalParameters` is one point, :class:`IntervalModel` a box
(lower and upper arrays). Everything is vectorised over frequency.

The state space is the block-diagonal form of eq. (2.6)-(2.8):
``A_i = [[0, 1], [-a0_i, -a1_i]]``, ``B_i = [0, 1]^T``, ``C_i = [b0_i, b1_i]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARAM_NAMES: tuple[str, ...] = ("a1", "a0", "b1", "b0")
A1, A0, B1, B0 = range(4)


def _as_param_array(values, name: str) -> np.ndarray:
    arr = np.array(values, dtype=float)
    if arr.ndim == 1 and arr.size == 4:
        arr = arr.reshape(1, 4)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise ValueError(f"{name}: expected shape (n_modes, 4) in order {PARAM_NAMES}, found {arr.shape}")
    return arr


def modal_response(params: np.ndarray, omega_rad_s) -> np.ndarray:
    """Per-mode frequency response ``G_i(j omega)`` (eq. 3.9), shape ``(n_modes, n_omega)``."""
    p = _as_param_array(params, "params")
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))[None, :]
    s = 1j * w
    num = p[:, B1, None] * s + p[:, B0, None]
    den = s * s + p[:, A1, None] * s + p[:, A0, None]
    return num / den


def resonance_band(lower, upper, bandwidths: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per mode of the box ``[lower, upper]`` (shape ``(n_modes, 4)``), the frequencies where it can
    resonate: its ``sqrt(a0)`` range widened on each side by ``bandwidths`` of its largest
    half-power bandwidth ``a1_max`` (``a1 = 2 zeta omega_n``, eq. 2.3). Returns ``(lo, hi)`` in
    rad/s, each shape ``(n_modes,)``; ``lo`` may be negative (nothing below 0 exists)."""
    lo_p, hi_p = _as_param_array(lower, "lower"), _as_param_array(upper, "upper")
    widen = bandwidths * hi_p[:, A1]
    return np.sqrt(np.maximum(lo_p[:, A0], 0.0)) - widen, np.sqrt(np.maximum(hi_p[:, A0], 0.0)) + widen


def near_resonance(omega_rad_s, lower, upper, bandwidths: float = 1.0) -> np.ndarray:
    """Which of the frequencies ``omega_rad_s`` lie in some mode's :func:`resonance_band`."""
    lo, hi = resonance_band(lower, upper, bandwidths)
    w = np.asarray(omega_rad_s, dtype=float)[:, None]
    return np.any((w >= lo) & (w <= hi), axis=1)


def residual_response(lower_residual: float, upper_residual: float, omega_rad_s) -> np.ndarray:
    """Receptance of the residual terms: ``-r_l / omega^2 + r_u`` (``r_l / s^2 + r_u`` at ``s = j omega``)."""
    w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
    return (-lower_residual / (w * w) + upper_residual).astype(complex)


@dataclass(frozen=True)
class ModalParameters:
    """One point in parameter space: ``values[i] = (a1, a0, b1, b0)`` of mode ``i``.

    Optional residual terms for modes outside the band (modal-analysis practice, issue 14):
    ``lower_residual`` ``r_l`` (mass line, ``r_l / s^2``, i.e. ``-r_l / omega^2`` in receptance)
    and ``upper_residual`` ``r_u`` (residual flexibility, a constant). Both default to 0 and
    enter :meth:`frequency_response` only; the state-space form holds the modes alone.
    """

    values: np.ndarray
    lower_residual: float = 0.0
    upper_residual: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "values", _as_param_array(self.values, "values"))

    @property
    def n_modes(self) -> int:
        return self.values.shape[0]

    @classmethod
    def from_modal(cls, omega_n, zeta, b0, b1=None) -> "ModalParameters":
        """Build from natural frequencies (rad/s), damping ratios and residues."""
        omega_n = np.atleast_1d(np.asarray(omega_n, dtype=float))
        zeta = np.broadcast_to(np.asarray(zeta, dtype=float), omega_n.shape)
        b0 = np.broadcast_to(np.asarray(b0, dtype=float), omega_n.shape)
        b1 = np.zeros_like(omega_n) if b1 is None else np.broadcast_to(np.asarray(b1, dtype=float), omega_n.shape)
        return cls(np.column_stack([2 * zeta * omega_n, omega_n**2, b1, b0]))

    @classmethod
    def from_mode_table(cls, modes) -> "ModalParameters":
        """From rows ``(omega_n rad/s, zeta, b0, b1)`` (a truth file's modes), sorted by frequency."""
        rows = sorted(tuple(float(v) for v in m) for m in modes)
        w, z, b0, b1 = (np.array([m[k] for m in rows], dtype=float) for k in range(4))
        return cls.from_modal(w, z, b0, b1)

    @property
    def natural_frequencies(self) -> np.ndarray:
        return np.sqrt(self.values[:, A0])

    @property
    def damping_ratios(self) -> np.ndarray:
        return self.values[:, A1] / (2 * np.sqrt(self.values[:, A0]))

    def mode_responses(self, omega_rad_s) -> np.ndarray:
        """``G_i(j omega)`` for every mode, shape ``(n_modes, n_omega)``."""
        return modal_response(self.values, omega_rad_s)

    def frequency_response(self, omega_rad_s) -> np.ndarray:
        """``G(j omega) = sum_i G_i(j omega)`` (eq. 2.3) plus the residual terms, shape ``(n_omega,)``."""
        g = self.mode_responses(omega_rad_s).sum(axis=0)
        if self.lower_residual or self.upper_residual:
            w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
            g = g + residual_response(self.lower_residual, self.upper_residual, w)
        return g

    def state_space_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Block-diagonal ``(A, B, C, D)`` of eq. (2.6)-(2.8); D = 0."""
        n = self.n_modes
        A = np.zeros((2 * n, 2 * n))
        B = np.zeros((2 * n, 1))
        C = np.zeros((1, 2 * n))
        for i, (a1, a0, b1, b0) in enumerate(self.values):
            k = 2 * i
            A[k, k + 1] = 1.0
            A[k + 1, k] = -a0
            A[k + 1, k + 1] = -a1
            B[k + 1, 0] = 1.0
            C[0, k] = b0
            C[0, k + 1] = b1
        return A, B, C, np.zeros((1, 1))

    def to_statespace(self):
        """The model as a ``control.StateSpace`` (python-control)."""
        import control

        return control.ss(*self.state_space_matrices())

    def truncated(self, n_modes: int) -> "ModalParameters":
        return ModalParameters(self.values[:n_modes])


@dataclass(frozen=True)
class IntervalModel:
    """A modal model whose parameters are intervals ``lower <= theta <= upper`` (eq. 2.24).

    ``lower`` and ``upper`` have shape ``(n_modes, 4)`` in the order of :data:`PARAM_NAMES`.
    A parameter with zero width is *fixed* (e.g. ``b1 = 0`` for a displacement sensor).
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        lo = _as_param_array(self.lower, "lower")
        hi = _as_param_array(self.upper, "upper")
        if lo.shape != hi.shape:
            raise ValueError(f"lower and upper: expected equal shapes, found {lo.shape} and {hi.shape}")
        if np.any(lo > hi):
            i, j = np.argwhere(lo > hi)[0]
            raise ValueError(
                f"mode {i + 1} {PARAM_NAMES[j]}: lower bound {lo[i, j]:.6g} exceeds upper bound {hi[i, j]:.6g}"
            )
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def n_modes(self) -> int:
        return self.lower.shape[0]

    @property
    def midpoint(self) -> ModalParameters:
        """Nominal model at the interval midpoints (eq. 2.25)."""
        return ModalParameters(0.5 * (self.lower + self.upper))

    def nominal(self) -> ModalParameters:
        """The nominal model (the midpoints, eq. 2.25); ``.to_statespace()`` gives it to python-control."""
        return self.midpoint

    @property
    def width(self) -> np.ndarray:
        """Interval widths ``delta = upper - lower`` (eq. 2.27)."""
        return self.upper - self.lower

    @property
    def fixed(self) -> np.ndarray:
        """Boolean mask of parameters with zero width."""
        return self.width == 0.0

    def contains(self, params: ModalParameters | np.ndarray, rtol: float = 0.0) -> np.ndarray:
        """Elementwise ``lower <= theta <= upper`` (with optional relative slack)."""
        p = params.values if isinstance(params, ModalParameters) else _as_param_array(params, "params")
        scale = np.maximum(np.abs(self.lower), np.abs(self.upper))
        slack = rtol * np.where(np.isfinite(scale), scale, 0.0)  # an infinite bound needs no slack
        return (p >= self.lower - slack) & (p <= self.upper + slack)

    def intersect(self, other: "IntervalModel") -> "IntervalModel":
        """Tightest box in both (used to keep bounds from loosening, eq. 5.4-5.5)."""
        lo = np.maximum(self.lower, other.lower)
        hi = np.minimum(self.upper, other.upper)
        return IntervalModel(lo, np.maximum(lo, hi))

    def sample(self, unit_offsets: np.ndarray) -> ModalParameters:
        """Point ``mid + x * (upper - mid)`` for offsets ``x`` in [-1, 1] (Table 6-6)."""
        x = _as_param_array(unit_offsets, "unit_offsets")
        mid = 0.5 * (self.lower + self.upper)
        return ModalParameters(mid + x * (self.upper - mid))

    def time_scaled(self, factor: float) -> "IntervalModel":
        """The model of the time-scaled structure ``G'(s) = G(s / factor)``: every frequency times
        ``factor`` (``a1, b1`` times ``factor``, ``a0, b0`` times ``factor**2``)."""
        f = float(factor)
        scale = np.array([f, f * f, f, f * f])
        return IntervalModel(self.lower * scale, self.upper * scale)

    def magnitude_scaled(self, factor: float) -> "IntervalModel":
        """The model of ``factor G`` (``factor > 0``): ``b1, b0`` times ``factor``."""
        f = float(factor)
        scale = np.array([1.0, 1.0, f, f])
        return IntervalModel(self.lower * scale, self.upper * scale)

    def named_intervals(self) -> list[dict[str, list[float]]]:
        """``[{"a1": [lo, hi], ...}, ...]``: the identify result format's ``modes``."""
        return [
            {name: [float(self.lower[i, j]), float(self.upper[i, j])] for j, name in enumerate(PARAM_NAMES)}
            for i in range(self.n_modes)
        ]

    @classmethod
    def from_named_intervals(cls, modes: list[dict[str, list[float]]]) -> "IntervalModel":
        lo = [[float(m[name][0]) for name in PARAM_NAMES] for m in modes]
        hi = [[float(m[name][1]) for name in PARAM_NAMES] for m in modes]
        return cls(np.array(lo, dtype=float).reshape(-1, 4), np.array(hi, dtype=float).reshape(-1, 4))

    @classmethod
    def point(cls, params: ModalParameters) -> "IntervalModel":
        """A zero-width model (a simulation model in the identify result format)."""
        return cls(params.values.copy(), params.values.copy())
