"""Frequency-domain simulated beam: the experiment protocol without any time-domain dwell.

``measure(omega)`` returns the true 8-mode response plus bounded complex noise; the reported
bound is the additive-noise bound plus ``|W1|`` when unmodelled dynamics are present (the thesis
adds the two, section 6.2). With ``unmodelled_dynamics=False`` the truth has only the modelled
modes and the bound is the noise bound alone (section 6.3.4, second run).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from setmem_hil.estimation.simulated_record import SIMULATED_PHASOR, simulated_points
from setmem_hil.model.experiment import Measurement, RawRecord
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import W1_DEN, W1_NUM, beam_parameters, beam_parameters_at, polynomial_magnitude, scaled_beam
from setmem_hil.sim_backends.noise import bounded_complex_noise, noise_bound_function


@dataclass
class SimulatedBeamExperiment:
    """The simulated beam behind the :class:`setmem_hil.model.experiment.Experiment` protocol.

    Parameters
    ----------
    noise_profile : str
        One of :data:`setmem_hil.sim_backends.noise.NOISE_PROFILES`.
    seed : int
        Seed of the noise generator (``numpy.random.default_rng``).
    unmodelled_dynamics : bool
        Keep modes 4-8 in the truth and add ``|W1|`` to the bound.
    n_modelled : int
        Number of modes the identification models (3 for the thesis).
    noise_scale : float
        Multiplies the noise bound.
    first_mode_rad_s : float
        The beam's first natural frequency (1 rad/s in the thesis). Every mode scales with it,
        the residues with its square, so the response at ``omega`` is the thesis beam's at
        ``omega / first_mode_rad_s`` (same magnitudes); the noise bound follows the response
        (evaluated at the normalised frequency). ``|W1|`` comes from ``w1_num``/``w1_den`` as
        given (time-scale the weights with the structure).
    """

    noise_profile: str = "fully_damped"
    seed: int = 0
    unmodelled_dynamics: bool = True
    n_modelled: int = 3
    noise_scale: float = 1.0
    w1_num: tuple = W1_NUM
    w1_den: tuple = W1_DEN
    first_mode_rad_s: float = 1.0
    sensors: tuple = (1.0,)
    actuator: float = 1.0
    control_output: int = 0  # index into sensors (0-based) of the sensor returned as ``response``
    truth_modes: tuple = ()  # ((omega_rad_s, zeta, b0, b1), ...): a structure replacing the beam (issue 47)
    truth: ModalParameters = field(init=False)
    n_measured: int = 0  # measurements taken so far; set it when resuming from a journal

    def __post_init__(self):
        if not (np.isfinite(self.first_mode_rad_s) and self.first_mode_rad_s > 0):
            raise ValueError(f"first_mode_rad_s: expected a positive frequency, found {self.first_mode_rad_s!r}")
        if not 0 <= int(self.control_output) < len(self.sensors):
            raise ValueError(f"control_output: expected an index into {len(self.sensors)} sensor(s), found {self.control_output!r}")
        S = float(self.first_mode_rad_s)
        self._truths, self._noise_bounds = [], []
        if self.truth_modes:
            self._use_truth_modes()
            return
        for x in self.sensors:
            # the thesis's beam exactly for the tip sensor and tip force; mode shapes elsewhere (issue 25)
            full = beam_parameters() if (x, self.actuator) == (1.0, 1.0) else beam_parameters_at(x, self.actuator)
            normalised_bound = noise_bound_function(self.noise_profile, full, self.noise_scale)
            if S != 1.0:
                full = scaled_beam(full, S)
                self._noise_bounds.append(lambda w, f=normalised_bound: f(np.asarray(w, dtype=float) / S))
            else:
                self._noise_bounds.append(normalised_bound)
            self._truths.append(full if self.unmodelled_dynamics else full.truncated(self.n_modelled))
        self._noise_bound = self._noise_bounds[self.control_output]
        self.truth = self._truths[self.control_output]
        self._raw: list[RawRecord] = []

    def _use_truth_modes(self) -> None:
        """A truth file's structure (:mod:`setmem_hil.io.truth_file`): its modes sorted by
        frequency, the lowest ``n_modelled`` modelled. The noise profile applies to it as to the
        beam (its fully damped version, its response). The higher modes are the unmodelled
        dynamics, and their own response's magnitude is added to each point's bound: the
        procedure's ``|W1|`` was shaped for the cantilever, so it need not cover another
        structure's modes."""
        if tuple(self.sensors) != (1.0,) or self.first_mode_rad_s != 1.0:
            raise ValueError("truth_modes: one sensor (the file's), unscaled")
        full = ModalParameters.from_mode_table(self.truth_modes)
        self._noise_bounds.append(noise_bound_function(self.noise_profile, full, self.noise_scale))
        self._truths.append(full if self.unmodelled_dynamics else full.truncated(min(self.n_modelled, full.n_modes)))
        self._noise_bound = self._noise_bounds[0]
        self.truth = self._truths[0]
        self._raw: list[RawRecord] = []

    def unmodelled_magnitude(self, w: np.ndarray) -> np.ndarray:
        """What the modelled modes leave out at ``w``: ``|W1|`` for the beam, the truth file's
        higher modes' own response for a truth file (zero without unmodelled dynamics)."""
        if not self.unmodelled_dynamics:
            return np.zeros(np.shape(w))
        if self.truth_modes:
            if self.truth.n_modes <= self.n_modelled:
                return np.zeros(np.shape(w))
            rest = ModalParameters(self.truth.values[self.n_modelled:])
            return np.abs(rest.frequency_response(w)).reshape(np.shape(w))
        return polynomial_magnitude(self.w1_num, self.w1_den, w)

    @property
    def truths(self) -> tuple[ModalParameters, ...]:
        """Every sensor's true structure (same poles, own residues), in the order of ``sensors``."""
        return tuple(self._truths)

    @property
    def modelled_truth(self) -> ModalParameters:
        """The true parameters of the modes the identification models."""
        return self.truth.truncated(self.n_modelled)

    def total_bound(self, omega_rad_s, noise_gain=1.0) -> np.ndarray:
        """Noise bound (times ``noise_gain``, see :meth:`measure_many`) plus the W1 term, if any."""
        w = np.asarray(omega_rad_s, dtype=float)
        return self._with_w1(self._noise_bound(w) * noise_gain, w)

    def _with_w1(self, noise_bound: np.ndarray, w: np.ndarray) -> np.ndarray:
        """A noise bound plus ``|W1|`` when the truth has unmodelled modes. ``|W1|`` bounds them
        at every sensor position: a cantilever's mass-normalised shapes are largest at the tip,
        so ``|phi_i(a) phi_i(x)| <= 4``, the thesis's tip residue."""
        return noise_bound + self.unmodelled_magnitude(w)

    def noise_generator(self, index: int, sensor: int | None = None) -> np.random.Generator:
        """Generator for the ``index``-th measurement (0-based) of a sensor.

        Noise depends only on ``(seed, index)``, not on a running stream, so a campaign resumed
        from its journal (``n_measured`` set to the number stored) measures exactly what an
        uninterrupted run would have, and serial and distributed sweeps agree. The control
        sensor uses ``(seed, index)``, so its data are those of a one-sensor run; another sensor
        ``k`` its own stream ``(seed, index, k + 1)``.
        """
        if sensor is None or sensor == self.control_output:
            return np.random.default_rng((self.seed, index))
        return np.random.default_rng((self.seed, index, sensor + 1))

    def measure_many(self, omega_rad_s, noise_gain=1.0) -> list[Measurement]:
        """Measure each frequency; ``noise_gain`` (per point) multiplies its noise and noise bound.

        The noise bound is the error of ``G`` at the unit force the thesis applies; a line of
        a multisine carries a smaller force ``a`` and its error grows as ``1 / a``: pass
        ``noise_gain = 1 / a``. With several sensors every one is read; the control sensor's
        reading is the measurement's response, the others its ``others``.
        """
        w = np.atleast_1d(np.asarray(omega_rad_s, dtype=float))
        gain = np.broadcast_to(np.asarray(noise_gain, dtype=float), w.shape)
        readings = [self._reading(k, w, gain) for k in range(len(self.sensors))]
        unmodelled = self.unmodelled_magnitude(w)
        record = RawRecord(SIMULATED_PHASOR, {
            "omega_rad_s": w.copy(), "phasor": np.array([r[0] for r in readings]), "noise_bound": np.array([r[1] for r in readings]),
            "unmodelled_bound": np.broadcast_to(unmodelled, (len(readings), w.size)).copy(),
        }, {"control_output": int(self.control_output), "seed": int(self.seed), "first_index": int(self.n_measured),
            "unmodelled_dynamics": bool(self.unmodelled_dynamics)})
        self.n_measured += w.size
        self._raw.append(record)
        return simulated_points(record)

    def take_raw_records(self) -> list[RawRecord]:
        """The raw records of the measurements since the last call (the simulated phasors and
        their bounds' terms, :data:`~setmem_hil.estimation.simulated_record.SIMULATED_PHASOR`)."""
        taken, self._raw = self._raw, []
        return taken

    def _reading(self, k: int, w: np.ndarray, gain: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sensor ``k``'s response (its truth plus bounded noise) and noise bound at ``w``."""
        bound = self._noise_bounds[k](w) * gain
        noise = np.array([bounded_complex_noise(bound[i : i + 1], self.noise_generator(self.n_measured + i, k))[0] for i in range(w.size)])
        return self._truths[k].frequency_response(w) + noise, bound

    def measure(self, omega_rad_s: float) -> Measurement:
        return self.measure_many([omega_rad_s])[0]

    def close(self) -> None:  # nothing to release
        return None
