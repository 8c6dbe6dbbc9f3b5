"""A structure in closed loop with the reference firmware's own C core (software in the loop).

:class:`EmulatedClosedLoop` steps, sample by sample at the target's rate ``fs_hz``:

    y_target[k] = antialias(y)(k Ts)              (hidden: a first-order lag at antialias_corner_hz)
    v[k]        = firmware tick(y_target[k])       (the C core: sections, gain, its delay, limit, trip)
    u[k]        = dac_gain * v[k - extra] + r[k]   (hidden: more delay, a wrong DAC gain; r: the generator)
    x[k+1]      = Ad x[k] + Bd u[k]                (the structure, exact for a drive held over each sample)
    f[k]        = u[k - 1] + noise                 (with force_channel: the board's second ADC, read with y)

The hidden effects sit where a rig has them: the extra delay and the DAC gain on the actuator's
side (between the firmware's drive and the force the structure feels), the anti-alias lag on the
sensor's (between the structure's response and the firmware's ADC; not on the force channel).

(the loop runs in C, ``sim_backends/sil_loop.c``, with the core: the same steps) and records
what a DAQ beside the rig would: the generator's injection ``r`` (summed into the
drive at the amplifier's input), the drive ``u`` and the response ``y`` (with the backend's sensor
noise). The structure and the anti-alias lag are discretised exactly for the held drive
(``expm`` of the augmented matrix). The protocol's lines go to the same C core
(:class:`EmulatedTargetChannel`), so the host talks to the firmware itself. Virtual time: a
record of ``n`` samples is computed, not waited for.

Hidden effects (``[target.emulation]``, for tests of what the model leaves out) are in
:class:`TargetEmulation`; faults for the safety tests: the link dropped after a number of lines,
and the structure's damping removed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.errors import DeviceDisconnectedError
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.numerics.zero_order_hold import held
from setmem_hil.sim_backends.firmware_core import FirmwareCore

__all__ = ["TargetEmulation", "EmulatedClosedLoop", "EmulatedTargetChannel", "LoopRecord", "held_discretisation"]


@dataclass(frozen=True)
class TargetEmulation:
    """What the emulated rig does that the model does not say (all off by default)."""

    extra_delay_samples: int = 0  # the DAC's pipeline: more delay than the firmware's own
    dac_gain: float = 1.0  # the drive's gain error (a wrong amplifier setting)
    antialias_corner_hz: float | None = None  # a first-order lag before the target's ADC
    drop_link_after_lines: int | None = None  # the serial link dies after this many command lines
    undamped: bool = False  # the structure's damping removed (a loop made unstable)
    force_channel: bool = False  # the board's second ADC reads the force at the structure's input (SUMS? F)


@dataclass(frozen=True)
class LoopRecord:
    """One record at the target's rate: injection ``r``, drive ``u``, response ``y``."""

    fs_hz: float
    t0_s: float
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray

    @property
    def t_s(self) -> np.ndarray:
        return self.t0_s + np.arange(self.r.size) / self.fs_hz


class EmulatedTargetChannel:
    """The firmware's line protocol, answered by its own C core (a :class:`LineChannel`)."""

    def __init__(self, loop: "EmulatedClosedLoop"):
        self.loop, self.lines = loop, 0

    def exchange(self, line: str) -> str:
        drop = self.loop.emulation.drop_link_after_lines
        if self.loop.link_down or (drop is not None and self.lines >= drop):
            self.loop.link_down = True
            raise DeviceDisconnectedError("emulated target: the serial link is down (no reply)")
        self.lines += 1
        return self.loop.core.command(line)

    def close(self) -> None:
        pass


class EmulatedClosedLoop:
    """The structure ``structure`` (all its modes) with the firmware core at ``fs_hz`` and
    ``delay_samples``; ``noise_rms``: the response sensor's white noise; ``seed``: its RNG."""

    def __init__(self, structure: ModalParameters, fs_hz: float, delay_samples: int, emulation: TargetEmulation = TargetEmulation(),
                 noise_rms: float = 0.0, seed: int = 0):
        self.fs_hz, self.emulation = float(fs_hz), emulation
        self.core = FirmwareCore(fs_hz, delay_samples)
        self.link_down = False
        self.noise_rms, self._rng = float(noise_rms), np.random.default_rng(seed)
        if emulation.undamped:
            structure = ModalParameters(np.column_stack([np.zeros(structure.n_modes), *np.asarray(structure.values).T[1:]]))
        self._Ad, self._Bd, self._C, self._lag = held_discretisation(structure, self.fs_hz, emulation.antialias_corner_hz)
        self._x = np.zeros(self._Ad.shape[0])
        self._pipeline = np.zeros(int(emulation.extra_delay_samples))
        self._held_force = np.zeros(1) if emulation.force_channel else None
        self._generator = (0.0, 0.0)
        self._n = 0

    def channel(self) -> EmulatedTargetChannel:
        return EmulatedTargetChannel(self)

    @property
    def time_s(self) -> float:
        return self._n / self.fs_hz

    def set_generator(self, amplitude: float, omega_rad_s: float) -> None:
        """The generator's sine summed into the drive: ``r = amplitude sin(omega t)`` (0: off)."""
        self._generator = (float(amplitude), float(omega_rad_s))

    def run(self, n_samples: int) -> LoopRecord:
        """Step the loop ``n_samples`` samples and return what the DAQ recorded."""
        a, w = self._generator
        t0, n = self.time_s, int(n_samples)
        r = a * np.sin(w * (self._n + np.arange(n)) / self.fs_hz) if a else np.zeros(n)
        noise = self._rng.standard_normal(n) * self.noise_rms if self.noise_rms else np.zeros(n)
        # the force ADC's own noise, as the sensor's (drawn after it: a run without a force channel is unchanged)
        force_noise = self._rng.standard_normal(n) * self.noise_rms if self.noise_rms and self._held_force is not None else None
        u, y = self.core.run_loop(n, self._Ad, self._Bd, self._C, self._lag, self._x, r, noise, self.emulation.dac_gain, self._pipeline,
                                  self._held_force, force_noise)
        self._n += n
        return LoopRecord(self.fs_hz, t0, r, u, y)


def held_discretisation(structure: ModalParameters, fs_hz: float, corner_hz: float | None):
    """``(Ad, Bd, C, lag)``: the structure (and the anti-alias lag on its output) for a drive
    held over each sample; ``C`` rows: the response, then (with a lag) the lagged response."""
    A, B, C, _ = structure.state_space_matrices()
    A, B, C = np.asarray(A, float), np.asarray(B, float).reshape(-1), np.asarray(C, float).reshape(1, -1)
    lag = corner_hz is not None
    if lag:  # x_f' = wc (y - x_f)
        wc = 2 * np.pi * float(corner_hz)
        n = A.shape[0]
        A = np.block([[A, np.zeros((n, 1))], [wc * C, -wc * np.ones((1, 1))]])
        B = np.concatenate([B, [0.0]])
        C = np.vstack([np.concatenate([C[0], [0.0]]), np.concatenate([np.zeros(n), [1.0]])])
    Ad, Bd = held(A, B, 1.0 / fs_hz)
    return Ad, Bd[:, 0], C, lag
