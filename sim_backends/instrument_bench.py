"""The emulated stepped-sine bench: generator, amplifier, shaker, beam, sensors and lock-ins.

What the instrument emulators (:mod:`setmem_hil.sim_backends.instrument_emulators`) answer from.
One :class:`EmulatedBench` holds the physics of a classic stepped-sine rig on a *virtual clock*:

* the generator's sine ``v(t) = V sin(phi(t))``, ``phi' = 2 pi f`` (phase-continuous frequency
  steps, as the 33500B and DG800 do), switched by the output relay;
* the amplifier and shaker as an ideal force source ``F = k_true v`` (``k_true`` is the nominal
  ``newton_per_volt`` times ``drive_gain_ratio``: the real gain is never exactly the nominal one);
* the modal beam (all 8 modes, thesis eq. 2.6-2.8) driven by that force;
* force and response sensors (volts per unit, each with a true sensitivity that may differ from
  the declared one by ``sensitivity_error``);
* two lock-in amplifiers on the external reference: the sensor voltage times
  ``j sqrt(2) exp(-j phi)`` through a cascade of ``order`` first-order low-pass filters of time
  constant ``tau`` (6 dB/oct per stage), so ``X + jY`` is the RMS phasor of the signal relative to
  the reference sine, with the 2-omega ripple and the modal transients of the real instrument.

Exactness. Between two commands the frequency and level are constant and the whole bench is a
linear autonomous system in the demodulation frame: with ``xh = x exp(-j phi)``,

    xh' = (A - j w I) xh + B (c + r),   c = F/(2j),  r' = -2 j w r,  r(0) = -F/(2j) exp(-2 j phi0)
    p1' = (d - p1) / tau,  pk' = (p(k-1) - pk) / tau,   d = j sqrt(2) s (C xh  or  c + r)

so one matrix exponential of that system advances the structure and both filters exactly over any
interval (``x = Re(xh exp(j phi))`` afterwards). The readings' noise is a white voltage noise of
density ``noise_v_per_rthz`` at each lock-in input through the same filter cascade (simulated in
steps of ``tau / 8``): longer time constants give quieter, more correlated readings, as on the
real instrument.

The clock only moves when the driver waits (:meth:`VirtualClock.sleep`), so a 1000 s dwell costs
milliseconds. No I/O here.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.held_waveform import HeldWaveform
from setmem_hil.numerics.blas_threads import blas_one_thread

__all__ = ["VirtualClock", "LockInState", "EmulatedBench", "BenchSettings"]


class VirtualClock:
    """Simulated seconds; ``sleep`` advances them at once (the drivers' clock in emulation)."""

    def __init__(self) -> None:
        self._t = 0.0
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def sleep(self, duration_s: float) -> None:
        if duration_s > 0:
            with self._lock:
                self._t += float(duration_s)


@dataclass
class LockInState:
    """One emulated lock-in: its filter and its noise."""

    volt_per_unit: float  # the sensor's *true* sensitivity
    tau_s: float = 0.1
    order: int = 4  # 24 dB/oct
    noise_v_per_rthz: float = 1e-6
    sensitivity_v: float = 1.0  # full scale
    filters: np.ndarray = field(default_factory=lambda: np.zeros(4, complex))
    noise: np.ndarray = field(default_factory=lambda: np.zeros(4, complex))

    def set_filter(self, tau_s: float, order: int) -> None:
        """A new time constant keeps the outputs (the real filter does not jump)."""
        if order != self.order:
            self.filters = np.resize(self.filters, order)
            self.noise = np.resize(self.noise, order)
        self.tau_s, self.order = float(tau_s), int(order)


@dataclass(frozen=True)
class BenchSettings:
    """What the emulated rig is made of (not what the procedure believes about it)."""

    newton_per_volt: float = 4.0  # the nominal gain the procedure declares
    drive_gain_ratio: float = 1.0  # true gain / nominal gain
    force_volt_per_unit: float = 0.0225
    response_volt_per_unit: float = 1000.0
    sensitivity_error: tuple[float, float] = (0.0, 0.0)  # true / declared - 1 (force, response)
    noise_v_per_rthz: tuple[float, float] = (2e-6, 2e-6)  # at the lock-in inputs (force, response)
    seed: int = 0
    relock_s: float = 0.0  # the lock-ins report "unlocked" this long after every frequency step
    other_response_volt_per_unit: tuple[float, ...] = ()  # more response sensors (issue 25): lock-ins "response2", ...


class EmulatedBench:
    """The physics behind the emulated instruments (thread-safe; one lock for every command).

    ``other_outputs`` are more response sensors on the same structure (issue 25): the same poles
    (checked), their own residues, so one more output row of the same state each; their lock-ins
    are ``"response2"``, ``"response3"``, ... with ``settings.other_response_volt_per_unit``.
    """

    def __init__(self, params: ModalParameters, settings: BenchSettings = BenchSettings(), clock: VirtualClock | None = None,
                 other_outputs: tuple[ModalParameters, ...] = ()):
        self.params = params
        self.settings = settings
        self.clock = clock or VirtualClock()
        A, B, C, _ = params.state_space_matrices()
        self._A, self._B = A, B[:, 0]
        if len(other_outputs) != len(settings.other_response_volt_per_unit):
            raise ValueError(f"{len(other_outputs)} other outputs but {len(settings.other_response_volt_per_unit)} sensitivities")
        self.outputs = (params, *other_outputs)
        rows = [C[0]]
        for other in other_outputs:
            if not np.allclose(other.values[:, :2], params.values[:, :2], rtol=1e-12, atol=0.0):
                raise ValueError("every output of the emulated bench must have the same poles")
            rows.append(other.state_space_matrices()[2][0])
        self._C = dict(zip(self.response_names(len(rows)), rows))
        self.x = np.zeros(A.shape[0])
        self.frequency_hz = 1000.0
        self.frequency_set_at = -math.inf  # clock time of the last frequency change (lock-in relock)
        self.amplitude_v = 0.0  # peak
        self.output_on = False
        self.phase = 0.0
        self.t = self.clock.now()
        ef, er = settings.sensitivity_error
        nf, nr = settings.noise_v_per_rthz
        self.lockins = {
            "force": LockInState(settings.force_volt_per_unit * (1 + ef), noise_v_per_rthz=nf),
            "response": LockInState(settings.response_volt_per_unit * (1 + er), noise_v_per_rthz=nr),
        }
        for name, vpu in zip(self.response_names(len(rows))[1:], settings.other_response_volt_per_unit):
            self.lockins[name] = LockInState(vpu * (1 + er), noise_v_per_rthz=nr)
        self.rng = np.random.default_rng(settings.seed)
        self.lock = threading.RLock()
        self.peak_force_n = 0.0  # the largest force amplitude ever applied (tests check the 5 % rule)
        self.arb_points: np.ndarray | None = None  # an arbitrary waveform playing (issue 26): points in [-1, 1]
        self.arb_rate_hz = 0.0
        self.arb_start = 0.0
        self._arb: HeldWaveform | None = None
        self._cache: dict[tuple, np.ndarray] = {}

    # -- what the instruments command ------------------------------------------------------------
    @property
    def true_gain(self) -> float:
        return self.settings.newton_per_volt * self.settings.drive_gain_ratio

    @property
    def force_amplitude_n(self) -> float:
        """The force's peak: the sine's amplitude, or the arbitrary waveform's largest point."""
        if not self.output_on:
            return 0.0
        scale = float(np.max(np.abs(self.arb_points))) if self.arb_points is not None else 1.0
        return self.true_gain * self.amplitude_v * scale

    def set_arbitrary(self, points: np.ndarray | None, rate_hz: float = 0.0) -> None:
        """Play ``points`` (in [-1, 1], each held ``1 / rate_hz``, repeated) scaled by the
        amplitude, from now; None: back to the sine."""
        with self.lock:
            self.advance()
            self.arb_points = None if points is None else np.asarray(points, dtype=float).copy()
            self.arb_rate_hz, self.arb_start = float(rate_hz), self.clock.now()
            self._arb = None
            self.peak_force_n = max(self.peak_force_n, self.force_amplitude_n)

    def _held(self) -> HeldWaveform | None:
        """The arbitrary waveform's physics while it drives the structure (None otherwise)."""
        if self.arb_points is None or not self.output_on:
            return None
        force = self.true_gain * self.amplitude_v * self.arb_points
        if self._arb is None or not np.array_equal(self._arb.force_n, force):
            self._arb = HeldWaveform(self._A, self._B, force, self.arb_rate_hz, self.arb_start)
        return self._arb

    def set_generator(self, *, frequency_hz: float | None = None, amplitude_v: float | None = None, output_on: bool | None = None) -> None:
        with self.lock:
            self.advance()
            if frequency_hz is not None:
                if float(frequency_hz) != self.frequency_hz:
                    self.frequency_set_at = self.clock.now()
                self.frequency_hz = float(frequency_hz)
            if amplitude_v is not None:
                self.amplitude_v = float(amplitude_v)
            if output_on is not None:
                self.output_on = bool(output_on)
            self.peak_force_n = max(self.peak_force_n, self.force_amplitude_n)

    def reseed(self, key: tuple[int, ...]) -> None:
        """Simulation control: the noise from here on depends only on ``key`` (resumable runs)."""
        with self.lock:
            self.rng = np.random.default_rng((self.settings.seed, *key))

    def read_lockin(self, name: str) -> complex:
        """``X + jY`` (V RMS) of lock-in ``name`` now: filter output plus its noise."""
        with self.lock:
            self.advance()
            li = self.lockins[name]
            return complex(li.filters[-1] + li.noise[-1])

    def reference_locked(self) -> bool:
        """A lock-in's PLL follows a frequency step only after ``relock_s``."""
        with self.lock:
            return self.clock.now() - self.frequency_set_at >= self.settings.relock_s

    # -- sampled records (an oscilloscope or a DAQ on the bench, issue 26) ------------------------
    def sync_edge_after(self, t: float) -> float | None:
        """The first rising edge of the generator's sync output (the drive sine's phase at 0) at
        or after clock time ``t``, with the drive as it is now; None while the output is off
        (the emulated sync follows the output relay)."""
        with self.lock:
            self.advance()
            if not self.output_on:
                return None
            held = self._held()
            if held is not None:  # the sync marks the start of each cycle of the waveform
                k = math.ceil((t - held.t_start) / held.period_s)
                return held.t_start + (k + (held.t_start + k * held.period_s < t)) * held.period_s
            omega = 2 * math.pi * self.frequency_hz
            phase_at_t = (self.phase + omega * (t - self.t)) % (2 * math.pi)
            return t + ((2 * math.pi - phase_at_t) % (2 * math.pi)) / omega

    def force_rising_after(self, t: float, level_n: float) -> float | None:
        """The first time at or after ``t`` the force rises through ``level_n`` (a scope
        triggering on the force channel): on a sine its rising zero crossing (the sync edge, for
        a level inside the swing), on an arbitrary waveform the first held point that steps from
        at or below the level to above it. None while nothing crosses."""
        with self.lock:
            self.advance()
            held = self._held()
            if held is None:
                return self.sync_edge_after(t) if abs(level_n) < self.force_amplitude_n else None
            f = held.force_n
            rising = np.flatnonzero((np.roll(f, 1) <= level_n) & (f > level_n))
            if rising.size == 0:
                return None
            k0 = math.ceil((t - held.t_start) * held.rate_hz)
            cycle, offset = divmod(k0, f.size)
            later = rising[rising >= offset]
            k = cycle * f.size + (later[0] if later.size else f.size + rising[0])
            return held.t_start + k / held.rate_hz

    def record(self, t0: float, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The force (N) and every output's displacement at ``t0 + k dt``, ``k < n``, exactly
        (the same transition matrices over each sample interval). ``t0`` must not be earlier
        than the bench's present. The bench ends at the last sample: a command during the
        record would take effect at its end (the drivers change nothing while recording)."""
        with self.lock:
            self.advance()
            if t0 < self.t - 1e-12:
                raise ValueError(f"record from {t0} s asked at {self.t} s: the bench cannot go back")
            if t0 > self.t:
                self._advance_to(t0)
            rows = np.array([self._C[name] for name in self.response_names(len(self.outputs))])
            held = self._held()
            if held is not None:
                force, ys = held.samples(self.x, self.t, t0 + dt * np.arange(n), rows)
                self._advance_to(t0 + dt * (n - 1))
                return force, ys
            omega = 2 * math.pi * self.frequency_hz
            force = np.empty(n)
            ys = np.empty((len(self.outputs), n))
            step = self._structure_step(omega, dt)
            xh = self.x * np.exp(-1j * self.phase)
            c = self.force_amplitude_n / 2j
            drive = np.array([c, -c * np.exp(-2j * self.phase)])
            for k in range(n):
                if k:
                    xh = step[0] @ xh + step[1] @ drive
                    drive = drive * np.array([1.0, np.exp(-2j * omega * dt)])
                phase = self.phase + omega * dt * k
                x = np.real(xh * np.exp(1j * phase))
                force[k] = self.force_amplitude_n * math.sin(phase)
                ys[:, k] = rows @ x
            self._advance_to(t0 + dt * (n - 1))
            return force, ys

    def _advance_to(self, t: float) -> None:
        dt = t - self.t
        if dt > 0:
            self._advance_state(dt)
            for li in self.lockins.values():
                self._advance_noise(li, dt)
            self.t = t

    def _structure_step(self, omega: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The structure's part of :meth:`_system` over ``dt``: ``xh <- P xh + Q [c, r]``."""
        n = self._A.shape[0]
        M = np.zeros((n + 2, n + 2), complex)
        M[:n, :n] = self._A - 1j * omega * np.eye(n)
        M[:n, n] = M[:n, n + 1] = self._B
        M[n + 1, n + 1] = -2j * omega
        with blas_one_thread():
            phi = expm(M * dt)
        return phi[:n, :n], phi[:n, n:]

    @staticmethod
    def response_names(n_outputs: int) -> tuple[str, ...]:
        """The response lock-ins' names: ``"response"``, then ``"response2"``, ``"response3"``..."""
        return ("response",) + tuple(f"response{k}" for k in range(2, n_outputs + 1))

    def true_response(self, omega_rad_s: float, output: int = 0) -> complex:
        """The structure's receptance at ``omega`` seen by response sensor ``output`` (0: the first)."""
        return complex(np.ravel(self.outputs[output].frequency_response(np.array([float(omega_rad_s)])))[0])

    # -- physics ---------------------------------------------------------------------------------
    def advance(self) -> None:
        """Bring the structure, the filters and the noise to the clock's present time."""
        now = self.clock.now()
        dt = now - self.t
        if dt <= 0:
            return
        self._advance_state(dt)
        for li in self.lockins.values():
            self._advance_noise(li, dt)
        self.t = now

    def _advance_state(self, dt: float) -> None:
        """The structure (and the lock-ins' filters, on a sine) over ``dt``. Under an arbitrary
        waveform the lock-ins' filters are not simulated: nothing reads a lock-in then."""
        held = self._held()
        if held is None:
            self._advance_signal(dt)
            return
        self.x = held.advance(self.x, self.t, self.t + dt)

    def _system(self, omega: float, dt: float) -> np.ndarray:
        """The transition matrix over ``dt``: structure (demodulated), drive and every lock-in's
        filter cascade (force first, then the responses in :meth:`response_names` order)."""
        chain = list(self.lockins.items())
        key = (omega, dt, *((li.tau_s, li.order, li.volt_per_unit) for _, li in chain))
        phi = self._cache.get(key)
        if phi is not None:
            return phi
        n = self._A.shape[0]
        size = n + 2 + sum(li.order for _, li in chain)
        M = np.zeros((size, size), complex)
        ic, ir = n, n + 1
        M[:n, :n] = self._A - 1j * omega * np.eye(n)
        M[:n, ic] = self._B
        M[:n, ir] = self._B
        M[ir, ir] = -2j * omega
        gain = 1j * math.sqrt(2.0)
        start = n + 2
        for name, li in chain:
            k = 1.0 / li.tau_s
            if name == "force":
                M[start, ic] = M[start, ir] = gain * li.volt_per_unit * k
            else:
                M[start, :n] = gain * li.volt_per_unit * self._C[name] * k
            for j in range(li.order):
                M[start + j, start + j] = -k
                if j:
                    M[start + j, start + j - 1] = k
            start += li.order
        with blas_one_thread():
            phi = expm(M * dt)
        if len(self._cache) > 256:
            self._cache.clear()
        self._cache[key] = phi
        return phi

    def _advance_signal(self, dt: float) -> None:
        omega = 2 * math.pi * self.frequency_hz
        force = self.force_amplitude_n
        n = self.x.size
        c = force / 2j
        chain = list(self.lockins.values())
        state = np.concatenate([self.x * np.exp(-1j * self.phase), [c, -c * np.exp(-2j * self.phase)], *(li.filters for li in chain)])
        state = self._system(omega, dt) @ state
        self.phase = (self.phase + omega * dt) % (2 * math.pi)
        self.x = np.real(state[:n] * np.exp(1j * self.phase))
        start = n + 2
        for li in chain:
            li.filters = state[start:start + li.order].copy()
            start += li.order

    def _advance_noise(self, li: LockInState, dt: float) -> None:
        """White input noise through the filter cascade, in steps of tau/8 (only the last 40 tau
        matter: older noise has decayed below 1e-9 of the output)."""
        h = li.tau_s / 8.0
        span = min(dt, 40.0 * li.tau_s)
        steps = max(1, int(math.ceil(span / h)))
        h = span / steps
        if dt > span:
            li.noise = np.zeros(li.order, complex)
            steps += 8 * 40  # burn-in from rest, so the restart does not show
        a = math.exp(-h / li.tau_s)
        sigma = li.noise_v_per_rthz / math.sqrt(2 * h)  # per quadrature: two-sided density over h
        w = sigma * (self.rng.standard_normal(steps) + 1j * self.rng.standard_normal(steps))
        s = li.noise
        for k in range(steps):
            prev = w[k]
            for j in range(li.order):
                s[j] = a * s[j] + (1 - a) * prev
                prev = s[j]
        li.noise = s
