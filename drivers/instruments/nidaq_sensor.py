"""An NI DAQ card as the rig's sensor (NI-DAQmx through the ``nidaqmx`` package, extra ``[daq]``).

Implements :class:`setmem_hil.drivers.protocols.Sensor` (``acquire``) and
:class:`~setmem_hil.drivers.protocols.RateConfigurableSensor` (``set_sample_rate``): each
acquisition is one finite task with the analog voltage inputs force, response (and further
response channels: several sensors, issue 25, the block's ``others``), hardware sample clock at
the set rate; volts are converted with the sensors' ``volt_per_unit``. A channel at its input
range's rails is refused (a :class:`~setmem_hil.errors.DataQualityError` naming it: the dwell is
measured again). The
samples then go through the existing sine fit (:mod:`setmem_hil.estimation.sine_fit`), as for
any sampled rig. NI's driver (NI-DAQmx runtime) must be installed on the PC; an error from it is
one :class:`~setmem_hil.errors.DeviceError` line naming the channels.

IEPE sensors (issue 40: the accelerometers and force sensors of shaker tests need a constant
current and AC coupling): a channel with ``iepe_current_a`` is created as nidaqmx's IEPE
accelerometer (``add_ai_accel_chan``, m/s^2, sensitivity in mV/g) or IEPE force channel
(``add_ai_force_iepe_chan``, N, mV/N), internal current excitation (``current_excit_source``,
``current_excit_val``), the module's own terminal configuration; its readings come scaled and are
turned back into volts before the same rails check and conversion as a voltage channel. A
channel's ``coupling`` sets ``ai_coupling`` (AC: a high-pass whose error the bound carries,
:func:`ac_coupling_error`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from setmem_hil.drivers.protocols import SampleBlock
from setmem_hil.errors import DataQualityError, DeviceError

__all__ = ["NidaqSensor", "DaqInputSetup", "ac_coupling_error"]

STANDARD_GRAVITY = 9.80665  # m/s^2 in one g: nidaqmx takes an accelerometer's sensitivity in mV/g


@dataclass(frozen=True)
class DaqInputSetup:
    """How one analog input is created: the sensor's quantity, its IEPE current (0: a plain
    voltage input) and its coupling (None: the device's default)."""

    quantity: str = "displacement"
    iepe_current_a: float = 0.0
    coupling: str | None = None


def ac_coupling_error(omega_rad_s: float, corner_hz: float) -> float:
    """The largest relative error of a reading through a first-order AC-coupling high-pass of
    ``corner_hz``: ``|H - 1|`` with ``H = j w / (j w + w_c)``, i.e. ``w_c / |j w + w_c|``
    (1 at DC, 0.71 at the corner, about ``w_c / w`` well above it)."""
    wc = 2 * math.pi * corner_hz
    return wc / math.hypot(omega_rad_s, wc)


class NidaqSensor:
    """Force and response voltages from analog inputs (e.g. ``"Dev1/ai0"``, ``"Dev1/ai1"``).

    ``response_channel`` and ``response_volt_per_unit`` may be lists (several response sensors,
    the control output's first)."""

    def __init__(self, force_channel: str, response_channel: str | list[str], force_volt_per_unit: float,
                 response_volt_per_unit: float | list[float], *,
                 range_v: float = 10.0, terminal: str = "DIFF", sample_rate_hz: float = 1000.0, nidaqmx_module=None,
                 setups: list[DaqInputSetup] | None = None):
        if nidaqmx_module is None:
            try:
                import nidaqmx as nidaqmx_module
            except ImportError:  # pragma: no cover - the [daq] extra is in [test]
                raise DeviceError("NI-DAQ: the nidaqmx package is not installed; pip install 'setmem-hil[daq]'") from None
        self.nidaqmx = nidaqmx_module
        responses = [response_channel] if isinstance(response_channel, str) else list(response_channel)
        scales = [response_volt_per_unit] if isinstance(response_volt_per_unit, (int, float)) else list(response_volt_per_unit)
        if len(scales) != len(responses):
            raise ValueError(f"NI-DAQ: {len(responses)} response channels but {len(scales)} volt_per_unit values")
        self.channels = (force_channel, *responses)
        self.scale = (float(force_volt_per_unit), *(float(v) for v in scales))
        self.range_v, self.terminal = float(range_v), terminal
        self.setups = tuple(setups) if setups is not None else tuple(DaqInputSetup() for _ in self.channels)
        if len(self.setups) != len(self.channels):
            raise ValueError(f"NI-DAQ: {len(self.channels)} channels but {len(self.setups)} input setups")
        for channel, setup in zip(self.channels, self.setups):
            if setup.iepe_current_a and setup.quantity not in ("force", "acceleration"):
                raise ValueError(f"NI-DAQ {channel}: IEPE excitation is created for force and acceleration sensors, found {setup.quantity!r}")
        self.sample_rate_hz = float(sample_rate_hz)
        self._t = 0.0  # the sensor's own time axis: acquisitions follow each other

    @property
    def where(self) -> str:
        return f"NI-DAQ {', '.join(self.channels)}"

    def set_sample_rate(self, rate_hz: float) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise DeviceError(f"{self.where}: sample rate {rate_hz!r} Hz must be positive")
        self.sample_rate_hz = float(rate_hz)

    def acquire(self, duration_s: float) -> SampleBlock:
        n = max(2, int(round(duration_s * self.sample_rate_hz)))
        constants = self.nidaqmx.constants
        try:
            task = self.nidaqmx.Task()
            try:
                for channel, scale, setup in zip(self.channels, self.scale, self.setups):
                    self._add_channel(task, channel, scale, setup)
                task.timing.cfg_samp_clk_timing(self.sample_rate_hz, sample_mode=constants.AcquisitionType.FINITE, samps_per_chan=n)
                data = task.read(number_of_samples_per_channel=n, timeout=duration_s + 10.0)
            finally:
                task.close()
        except self.nidaqmx.errors.DaqError as exc:
            raise DeviceError(f"{self.where}: {' '.join(str(exc).split())[:300]}") from None
        volts = np.asarray(data, dtype=float)
        if volts.shape != (len(self.channels), n):
            raise DeviceError(f"{self.where}: expected {len(self.channels)} x {n} samples, the driver returned shape {volts.shape}")
        # IEPE channels read in newtons or m/s^2: back to volts, for the rails check and one conversion
        volts = volts * np.array([scale if setup.iepe_current_a else 1.0 for scale, setup in zip(self.scale, self.setups)])[:, None]
        t = self._t + np.arange(n) / self.sample_rate_hz
        self._t += n / self.sample_rate_hz
        at_rails = np.sum(np.abs(volts) >= 0.999 * self.range_v, axis=1)
        for channel, count in zip(self.channels, at_rails):
            if count:
                raise DataQualityError(f"NI-DAQ {channel}: {int(count)} samples at the +-{self.range_v:g} V input range (saturated)")
        units = volts / np.asarray(self.scale)[:, None]
        return SampleBlock(t_s=t, force=units[0], response=units[1], others=tuple(units[2:]))

    def _add_channel(self, task, channel: str, volt_per_unit: float, setup: DaqInputSetup):
        """One input of the task (module docstring): a voltage input, or an IEPE accelerometer
        or force channel; then its coupling."""
        constants = self.nidaqmx.constants
        if not setup.iepe_current_a:
            added = task.ai_channels.add_ai_voltage_chan(channel, terminal_config=constants.TerminalConfiguration[self.terminal],
                                                         min_val=-self.range_v, max_val=self.range_v)
        else:
            span = self.range_v / volt_per_unit  # the input range in the sensor's units
            common = dict(terminal_config=constants.TerminalConfiguration.DEFAULT, min_val=-span, max_val=span,
                          current_excit_source=constants.ExcitationSource.INTERNAL, current_excit_val=float(setup.iepe_current_a))
            if setup.quantity == "acceleration":
                added = task.ai_channels.add_ai_accel_chan(channel, units=constants.AccelUnits.METERS_PER_SECOND_SQUARED,
                                                           sensitivity=volt_per_unit * 1000.0 * STANDARD_GRAVITY,
                                                           sensitivity_units=constants.AccelSensitivityUnits.MILLIVOLTS_PER_G, **common)
            else:
                added = task.ai_channels.add_ai_force_iepe_chan(channel, units=constants.ForceUnits.NEWTONS, sensitivity=volt_per_unit * 1000.0,
                                                                sensitivity_units=constants.ForceIEPESensorSensitivityUnits.MILLIVOLTS_PER_NEWTON,
                                                                **common)
        if setup.coupling is not None:
            added.ai_coupling = constants.Coupling[setup.coupling]
        return added
