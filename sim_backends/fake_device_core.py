"""Transport-independent fake shaker/DAQ device: state machine, virtual clock, fault injection.

Every fake device (serial, CAN, Modbus) wraps one :class:`FakeDeviceCore` and only translates
its wire format into the calls below. The core owns a :class:`TimeDomainBeam` (exact sampled
simulation of the 8-mode beam, eq. 2.6-2.8), sensor noise on both channels, an *accelerated
(virtual) clock* (``capture`` simulates ``n`` samples of simulated time at once, so a 300 s
dwell costs milliseconds) and seeded fault injection (issue 8).

API (what a transport wrapper calls)
------------------------------------
``core.set_sine(omega_rad_s, amplitude_n)``
    Start/change the sinusoid; raises :class:`DeviceRejectedError` outside the device's own
    hard limits (``omega`` in ``(0, max_omega_rad_s]``, amplitude in ``[0, force_range_n]``).
``core.set_multisine(omegas_rad_s, amplitudes_n, phases_rad)``
    Start a sum of sinusoids (a multisine record); the sum of the amplitudes (a bound of the
    peak) must be within ``force_range_n``.
``core.stop()``
    Output to zero (idempotent). ``core.host_lost()`` does the same (watchdog on disconnect).
``core.set_sample_rate(rate_hz)``
    Sample rate of the next captures (``min_rate_hz .. max_rate_hz``).
``core.begin_measurement(index, attempt=0)``
    Simulation control: reseeds the sensor noise with ``default_rng((seed, index, attempt))``
    and the fault draws with ``default_rng((fault_seed, index, attempt))``, and lets the
    structure come to rest (the loop's computation between dwells is modelled as long compared
    with the slowest decay); the virtual clock restarts at 0. Noise of dwell ``n`` therefore depends only on ``(seed, n,
    attempt)``, so a campaign resumed from its journal measures exactly what an uninterrupted
    one would. Idempotent.
``core.capture(n_samples, request_id=None) -> int``
    Simulate ``n_samples`` (at most ``max_samples``) into the sample buffer, advancing the
    virtual clock; returns the buffer length. Repeating the *same* ``request_id`` returns the
    existing buffer without simulating again, so a transport may retry a capture safely.
``core.wait(duration_s)``
    Advance the virtual clock without sampling (settling).
``core.read_buffer(offset, count) -> SampleBlock``
    A slice of the last capture (idempotent; safe to retry). ``core.buffer_length``.
``core.status() -> DeviceStatus``
    Frequency, amplitude, output flag, sample rate, virtual time, buffer length, measurement.
``core.metadata``
    :class:`setmem_hil.drivers.protocols.RigMetadata` (ranges and units).
``core.faults``
    :class:`FaultInjector`; transports call ``core.faults.draw(kind)`` once per frame for the
    frame-level kinds (:data:`FRAME_FAULT_KINDS`) and act on a ``True``; the core applies the
    data-level kinds (:data:`DATA_FAULT_KINDS`) itself inside ``capture``.
    ``core.faults.injected`` counts injections per kind.

Construction from a procedure: :meth:`FakeDeviceCore.from_procedure(procedure, seed)` (noise
profile, noise scale, unmodelled dynamics and ``procedure.backend.faults``).

Sensor noise: white Gaussian on both channels. The response channel's RMS follows the
procedure's noise profile ``R(omega)`` (``setmem_hil.sim_backends.noise``) at the commanded
frequency times ``response_noise_per_bound`` (so the dwell's information content tracks the
frequency-domain simulation's), with a floor ``response_noise_floor``; the force channel has a
fixed RMS ``force_noise_n``. During a multisine the response noise is *coloured* instead: white
noise shaped in the frequency domain by the profile (its spectral density at ``omega`` is what a
single sine at ``omega`` would see), so every line meets the noise the single-sine dwell at its
frequency would (the profile is interpolated on a 256-point logarithmic grid).

Example
-------
>>> core = FakeDeviceCore(seed=3)
>>> core.begin_measurement(0)
>>> core.set_sample_rate(32 * 2.0 / (2 * 3.141592653589793))
>>> core.set_sine(2.0, 1.0)
>>> core.capture(320)
320
>>> block = core.read_buffer(0, 320)
>>> block.force.shape
(320,)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.errors import DeviceRejectedError, ProcedureError
from setmem_hil.io.fault_kinds import DATA_FAULT_KINDS, FAULT_KINDS, FRAME_FAULT_KINDS  # noqa: F401 (re-exported)
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import beam_parameters, beam_parameters_at
from setmem_hil.sim_backends.time_domain_beam import TimeDomainBeam



@dataclass(frozen=True)
class FaultSettings:
    """Fault injection settings (``procedure.backend.faults``).

    Parameters
    ----------
    rate : float
        Probability of each enabled kind per opportunity (per frame for frame kinds, per
        capture for data kinds), in ``[0, 1]``.
    kinds : tuple of str
        Enabled kinds, a subset of :data:`FAULT_KINDS` (default: all).
    seed : int
        Seed of the fault draws.
    rates : tuple of (kind, rate)
        Per-kind overrides of ``rate`` (TOML: ``rates = {disconnect = 0.002}``); e.g. a
        disconnect ends the dwell, so it should be rarer per frame than a corrupted frame.
    """

    rate: float = 0.0
    kinds: tuple[str, ...] = FAULT_KINDS
    seed: int = 0
    rates: tuple[tuple[str, float], ...] = ()

    def rate_of(self, kind: str) -> float:
        """Probability for ``kind``: its entry in ``rates`` if any, else ``rate``."""
        return dict(self.rates).get(kind, self.rate)

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any] | None, source: str = "procedure") -> "FaultSettings":
        """Parse ``{"rate": 0.05, "kinds": [...], "seed": 7}``; raises ProcedureError naming the key."""
        m = dict(mapping or {})
        unknown = set(m) - {"rate", "kinds", "seed", "rates"}
        if unknown:
            raise ProcedureError(source, "[backend.faults]", f"unknown keys {sorted(unknown)}; expected rate, kinds, seed, rates")
        rates = m.get("rates", {})
        if not isinstance(rates, Mapping):
            raise ProcedureError(source, "[backend.faults] key 'rates'", f"expected a table of kind = rate, found {rates!r}")
        for k, r in rates.items():
            if k not in FAULT_KINDS:
                raise ProcedureError(source, "[backend.faults.rates]", f"unknown kind {k!r}; expected some of {list(FAULT_KINDS)}")
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 <= float(r) <= 1.0:
                raise ProcedureError(source, f"[backend.faults.rates] key '{k}'", f"expected a number in [0, 1], found {r!r}")
        rate = m.get("rate", 0.0)
        if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0.0 <= float(rate) <= 1.0:
            raise ProcedureError(source, "[backend.faults] key 'rate'", f"expected a number in [0, 1], found {rate!r}")
        kinds = m.get("kinds", FAULT_KINDS)
        if isinstance(kinds, str) or not all(isinstance(k, str) for k in kinds):
            raise ProcedureError(source, "[backend.faults] key 'kinds'", f"expected a list of names, found {kinds!r}")
        bad = [k for k in kinds if k not in FAULT_KINDS]
        if bad:
            raise ProcedureError(source, "[backend.faults] key 'kinds'", f"unknown kinds {bad}; expected some of {list(FAULT_KINDS)}")
        seed = m.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ProcedureError(source, "[backend.faults] key 'seed'", f"expected an integer, found {seed!r}")
        return cls(float(rate), tuple(kinds), int(seed), tuple((str(k), float(r)) for k, r in rates.items()))


@dataclass
class FaultInjector:
    """Seeded fault draws and per-kind counters of what was injected.

    ``draw(kind)`` is ``True`` with probability ``rate`` if ``kind`` is enabled. The generator
    is reseeded by :meth:`reseed` at every measurement attempt, so faults are reproducible.
    """

    settings: FaultSettings = field(default_factory=FaultSettings)
    injected: dict[str, int] = field(default_factory=dict)
    suspended: bool = False  # True while a transport must not inject (e.g. teardown)

    def __post_init__(self):
        self._rng = np.random.default_rng((self.settings.seed, 0x5EED))
        self.injected = {k: 0 for k in FAULT_KINDS}

    def reseed(self, *key: int) -> None:
        self._rng = np.random.default_rng((self.settings.seed, *key))

    @property
    def rng(self) -> np.random.Generator:
        """Generator for fault details (where to cut a frame, which bits to flip)."""
        return self._rng

    def enabled(self, kind: str) -> bool:
        return self.settings.rate_of(kind) > 0 and kind in self.settings.kinds and not self.suspended

    def draw(self, kind: str) -> bool:
        if kind not in FAULT_KINDS:
            raise ValueError(f"fault kind: expected one of {FAULT_KINDS}, found {kind!r}")
        if not self.enabled(kind):
            return False
        hit = bool(self._rng.random() < self.settings.rate_of(kind))
        if hit:
            self.injected[kind] += 1
        return hit


@dataclass(frozen=True)
class DeviceStatus:
    """Snapshot of the device state."""

    omega_rad_s: float
    amplitude_n: float
    output_on: bool
    sample_rate_hz: float
    time_s: float
    buffer_length: int
    measurement_index: int
    attempt: int


class FakeDeviceCore:
    """The fake shaker + two-channel DAQ (see the module docstring for the API).

    Parameters
    ----------
    truth : ModalParameters, optional
        Simulated structure (default: the 8-mode beam).
    seed : int
        Seed of the sensor noise.
    response_noise_rms : float or callable, optional
        RMS of the displacement noise per sample, or a function of the commanded ``omega``.
        Default: ``1e-3``.
    force_noise_n : float
        RMS of the force-sensor noise per sample.
    force_range_n, response_range : float
        Full-scale ranges of the channels (samples clip there; the shaker's hard amplitude limit
        is ``force_range_n``).
    faults : FaultSettings, optional
    max_samples : int
        Largest capture.
    other_truths : tuple of ModalParameters
        Further displacement sensors on the same structure (issue 25; same poles as ``truth``,
        own residues): each capture's ``others`` channels, in this order.
    other_noise_rms : tuple of (float or callable)
        Each further sensor's noise RMS, as ``response_noise_rms``; its own noise stream
        ``(seed, index, attempt, k)`` for sensor ``k >= 1``, so the first sensor's samples are
        those of a one-sensor core.
    """

    min_rate_hz = 1e-3
    max_rate_hz = 1e5
    max_omega_rad_s = 1e5

    def __init__(
        self,
        truth: ModalParameters | None = None,
        *,
        seed: int = 0,
        response_noise_rms: float | Callable[[float], float] = 1e-3,
        force_noise_n: float = 2e-3,
        force_range_n: float = 10.0,
        response_range: float = 1000.0,
        faults: FaultSettings | None = None,
        max_samples: int = 20000,
        other_truths: tuple[ModalParameters, ...] = (),
        other_noise_rms: tuple = (),
    ):
        self.truth = truth if truth is not None else beam_parameters()
        if len(other_noise_rms) != len(other_truths):
            raise ValueError(f"other_noise_rms: expected one per other sensor ({len(other_truths)}), found {len(other_noise_rms)}")
        self.other_truths = tuple(other_truths)
        self._other_noise = tuple(other_noise_rms)
        self.beam = TimeDomainBeam(self.truth, self.other_truths)
        self.seed = int(seed)
        self._response_noise = response_noise_rms
        self.force_noise_n = float(force_noise_n)
        self.metadata = RigMetadata(
            sample_rate_hz=100.0, force_range_n=float(force_range_n), response_range=float(response_range),
            name="fake-beam",
        )
        self.faults = FaultInjector(faults or FaultSettings())
        self.max_samples = int(max_samples)
        self.sample_rate_hz = 100.0
        self.time_s = 0.0
        self.measurement_index = 0
        self.attempt = 0
        self._noise_rng = np.random.default_rng((self.seed, 0, 0))
        self._other_rngs = self._sensor_rngs()
        self._buffer = SampleBlock(np.zeros(0), np.zeros(0), np.zeros(0))
        self._last_request_id: object = None

    # -- construction ----------------------------------------------------------------------
    @classmethod
    def from_procedure(cls, procedure, seed: int, **overrides) -> "FakeDeviceCore":
        """Core configured from ``procedure.backend`` (simulation settings and faults).

        The truth keeps the 8 modes when ``unmodelled_dynamics`` and otherwise the procedure's
        modelled modes; the response noise RMS is ``R(omega) * response_noise_per_bound``
        (``procedure.backend.transport.get("response_noise_per_bound", 1.0)``) with a floor of
        ``1e-6``, ``R`` the profile of ``setmem_hil.sim_backends.noise``.
        """
        from setmem_hil.sim_backends.noise import noise_bound_function

        sim = procedure.backend.simulation
        n_modelled = procedure.prior.n_modes
        per_bound = float(procedure.backend.transport.get("response_noise_per_bound", 1.0))
        floor = 1e-6
        truths, noises = [], []
        for x in (sim.sensors[sim.control_output - 1],) + tuple(x for i, x in enumerate(sim.sensors) if i != sim.control_output - 1):
            # the thesis's beam exactly for the tip sensor and tip force; mode shapes elsewhere (issue 25)
            full = beam_parameters() if (x, sim.actuator) == (1.0, 1.0) else beam_parameters_at(x, sim.actuator)
            truths.append(full if sim.unmodelled_dynamics else full.truncated(n_modelled))
            bound = noise_bound_function(sim.noise_profile, full, sim.noise_scale)
            noises.append(lambda w, bound=bound: max(floor, per_bound * float(bound(np.array([w]))[0])))
        faults = FaultSettings.from_mapping(procedure.backend.faults, procedure.source_path or procedure.name)
        kwargs = dict(seed=seed, response_noise_rms=noises[0], faults=faults, other_truths=tuple(truths[1:]),
                      other_noise_rms=tuple(noises[1:]))
        kwargs.update(overrides)
        return cls(truths[0], **kwargs)

    # -- commands --------------------------------------------------------------------------
    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        omega = float(omega_rad_s)
        amp = float(amplitude_n)
        if not (np.isfinite(omega) and 0.0 < omega <= self.max_omega_rad_s):
            raise DeviceRejectedError("range", f"fake device: omega {omega!r} rad/s outside (0, {self.max_omega_rad_s:g}]")
        if not (np.isfinite(amp) and 0.0 <= amp <= self.metadata.force_range_n):
            raise DeviceRejectedError("range", f"fake device: amplitude {amp!r} N outside [0, {self.metadata.force_range_n:g}]")
        if self.beam.line_omegas_rad_s == (omega,) and amp == self.beam.amplitude_n:
            return  # idempotent: repeating the command does not restart the sine
        self.beam.set_sine(omega, amp)

    def set_multisine(self, omegas_rad_s, amplitudes_n, phases_rad) -> None:
        w, a, p = (np.atleast_1d(np.asarray(v, dtype=float)).ravel() for v in (omegas_rad_s, amplitudes_n, phases_rad))
        if not (w.size >= 1 and w.size == a.size == p.size):
            raise DeviceRejectedError("range", f"fake device: multisine with {w.size} frequencies, {a.size} amplitudes, {p.size} phases")
        if not (np.all(np.isfinite(w)) and np.all(w > 0) and np.all(w <= self.max_omega_rad_s)):
            raise DeviceRejectedError("range", f"fake device: multisine frequencies {w.tolist()} outside (0, {self.max_omega_rad_s:g}] rad/s")
        if not (np.all(np.isfinite(a)) and np.all(a >= 0) and float(np.sum(a)) <= self.metadata.force_range_n and np.all(np.isfinite(p))):
            raise DeviceRejectedError("range", f"fake device: multisine amplitudes sum to {float(np.sum(a))!r} N, outside [0, {self.metadata.force_range_n:g}]")
        self.beam.set_multisine(w, a, p)

    def stop(self) -> None:
        self.beam.stop()

    def host_lost(self) -> None:
        """Watchdog: the host connection dropped, so the output goes to zero."""
        self.beam.stop()

    def set_sample_rate(self, rate_hz: float) -> None:
        rate = float(rate_hz)
        if not (np.isfinite(rate) and self.min_rate_hz <= rate <= self.max_rate_hz):
            raise DeviceRejectedError("range", f"fake device: sample rate {rate!r} Hz outside [{self.min_rate_hz:g}, {self.max_rate_hz:g}]")
        self.sample_rate_hz = rate

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        if int(index) < 0 or int(attempt) < 0:
            raise DeviceRejectedError("range", f"fake device: measurement index {index} / attempt {attempt} must be >= 0")
        self.measurement_index, self.attempt = int(index), int(attempt)
        self._noise_rng = np.random.default_rng((self.seed, self.measurement_index, self.attempt))
        self._other_rngs = self._sensor_rngs()
        self.faults.reseed(self.measurement_index, self.attempt)
        self.beam.reset()
        self.time_s = 0.0  # the virtual clock restarts with each measurement (bit-identical resumes)
        self._buffer = SampleBlock(np.zeros(0), np.zeros(0), np.zeros(0))
        self._last_request_id = None

    def _sensor_rngs(self) -> tuple[np.random.Generator, ...]:
        return tuple(np.random.default_rng((self.seed, self.measurement_index, self.attempt, k))
                     for k in range(1, 1 + len(self.other_truths)))

    # -- acquisition -----------------------------------------------------------------------
    def response_noise_rms(self) -> float:
        r = self._response_noise
        return float(r(self.beam.omega_rad_s)) if callable(r) else float(r)

    def capture(self, n_samples: int, request_id: object = None) -> int:
        n = int(n_samples)
        if not 1 <= n <= self.max_samples:
            raise DeviceRejectedError("range", f"fake device: capture of {n} samples outside [1, {self.max_samples}]")
        if request_id is not None and request_id == self._last_request_id:
            return self.buffer_length
        dt = 1.0 / self.sample_rate_hz
        t = self.time_s + dt * np.arange(n)
        force, outputs = self.beam.simulate_outputs(n, dt)
        disp = outputs[:, 0]
        self.time_s += n * dt
        force = force + self.force_noise_n * self._noise_rng.standard_normal(n)
        disp = disp + self._response_noise_samples(n, dt)
        others = tuple(np.clip(outputs[:, k] + self._response_noise_samples(n, dt, self._other_noise[k - 1], self._other_rngs[k - 1]),
                               -self.metadata.response_range, self.metadata.response_range)
                       for k in range(1, outputs.shape[1]))
        force = np.clip(force, -self.metadata.force_range_n, self.metadata.force_range_n)
        disp = np.clip(disp, -self.metadata.response_range, self.metadata.response_range)
        t, force, disp = self._inject_data_faults(t, force, disp)
        self._buffer = SampleBlock(t, force, disp, others)
        self._last_request_id = request_id
        return n

    def _response_noise_samples(self, n: int, dt: float, r=None, rng: np.random.Generator | None = None) -> np.ndarray:
        """White noise at the commanded frequency's RMS; coloured by the profile during a multisine.
        ``r``, ``rng``: another sensor's noise RMS and stream (default the control sensor's)."""
        r = self._response_noise if r is None else r
        white = (self._noise_rng if rng is None else rng).standard_normal(n)
        if len(self.beam.line_omegas_rad_s) <= 1 or not callable(r) or n < 4:
            return (float(r(self.beam.omega_rad_s)) if callable(r) else float(r)) * white
        omega = 2 * np.pi * np.fft.rfftfreq(n, dt)
        omega[0] = omega[1]
        grid = np.geomspace(omega[1], omega[-1], 256)
        density = np.array([float(r(w)) for w in grid])
        shape = np.exp(np.interp(np.log(omega), np.log(grid), np.log(np.maximum(density, 1e-300))))
        return np.fft.irfft(np.fft.rfft(white) * shape, n)

    def _inject_data_faults(self, t, force, disp):
        n = t.size
        rng = self.faults.rng
        if self.faults.draw("saturation"):
            k = int(rng.integers(0, n))
            m = max(1, n // 20)
            disp = disp.copy()
            disp[k : k + m] = np.sign(disp[k : k + m] + 1e-300) * self.metadata.response_range
        if self.faults.draw("nan"):
            disp = disp.copy()
            disp[int(rng.integers(0, n))] = np.nan
        if self.faults.draw("inf"):
            force = force.copy()
            force[int(rng.integers(0, n))] = np.inf if rng.random() < 0.5 else -np.inf
        if self.faults.draw("timestamp_jump") and n > 1:
            t = t.copy()
            t[int(rng.integers(1, n)) :] += float(rng.uniform(0.5, 5.0)) / self.sample_rate_hz
        return t, force, disp

    def wait(self, duration_s: float) -> None:
        """Advance the virtual clock by ``duration_s`` without sampling (exact, in <= 1000 steps)."""
        d = float(duration_s)
        if not (np.isfinite(d) and d >= 0):
            raise DeviceRejectedError("range", f"fake device: wait of {d!r} s must be finite and >= 0")
        if d == 0:
            return
        steps = int(min(1000, max(1, np.ceil(d * self.sample_rate_hz))))
        self.beam.simulate(steps, d / steps)
        self.time_s += d

    @property
    def buffer_length(self) -> int:
        return int(self._buffer.t_s.size)

    def read_buffer(self, offset: int, count: int) -> SampleBlock:
        off, cnt = int(offset), int(count)
        if off < 0 or cnt < 0 or off + cnt > self.buffer_length:
            raise DeviceRejectedError("range", f"fake device: read of [{off}, {off + cnt}) outside buffer of {self.buffer_length}")
        b = self._buffer
        return SampleBlock(b.t_s[off : off + cnt].copy(), b.force[off : off + cnt].copy(), b.response[off : off + cnt].copy(),
                           tuple(o[off : off + cnt].copy() for o in b.others))

    def status(self) -> DeviceStatus:
        return DeviceStatus(
            omega_rad_s=self.beam.omega_rad_s,
            amplitude_n=self.beam.amplitude_n,
            output_on=self.beam.amplitude_n > 0,
            sample_rate_hz=self.sample_rate_hz,
            time_s=self.time_s,
            buffer_length=self.buffer_length,
            measurement_index=self.measurement_index,
            attempt=self.attempt,
        )

    def true_response(self, omega_rad_s) -> np.ndarray:
        """The simulated structure's true ``G(j omega)`` (for tests)."""
        return self.truth.frequency_response(omega_rad_s)
