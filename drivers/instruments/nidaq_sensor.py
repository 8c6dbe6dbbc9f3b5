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
"""

from __future__ import annotations

import math

import numpy as np

from setmem_hil.drivers.protocols import SampleBlock
from setmem_hil.errors import DataQualityError, DeviceError

__all__ = ["NidaqSensor"]


class NidaqSensor:
    """Force and response voltages from analog inputs (e.g. ``"Dev1/ai0"``, ``"Dev1/ai1"``).

    ``response_channel`` and ``response_volt_per_unit`` may be lists (several response sensors,
    the control output's first)."""

    def __init__(self, force_channel: str, response_channel: str | list[str], force_volt_per_unit: float,
                 response_volt_per_unit: float | list[float], *,
                 range_v: float = 10.0, terminal: str = "DIFF", sample_rate_hz: float = 1000.0, nidaqmx_module=None):
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
                for channel in self.channels:
                    task.ai_channels.add_ai_voltage_chan(channel, terminal_config=constants.TerminalConfiguration[self.terminal],
                                                         min_val=-self.range_v, max_val=self.range_v)
                task.timing.cfg_samp_clk_timing(self.sample_rate_hz, sample_mode=constants.AcquisitionType.FINITE, samps_per_chan=n)
                data = task.read(number_of_samples_per_channel=n, timeout=duration_s + 10.0)
            finally:
                task.close()
        except self.nidaqmx.errors.DaqError as exc:
            raise DeviceError(f"{self.where}: {' '.join(str(exc).split())[:300]}") from None
        volts = np.asarray(data, dtype=float)
        if volts.shape != (len(self.channels), n):
            raise DeviceError(f"{self.where}: expected {len(self.channels)} x {n} samples, the driver returned shape {volts.shape}")
        t = self._t + np.arange(n) / self.sample_rate_hz
        self._t += n / self.sample_rate_hz
        at_rails = np.sum(np.abs(volts) >= 0.999 * self.range_v, axis=1)
        for channel, count in zip(self.channels, at_rails):
            if count:
                raise DataQualityError(f"NI-DAQ {channel}: {int(count)} samples at the +-{self.range_v:g} V input range (saturated)")
        units = volts / np.asarray(self.scale)[:, None]
        return SampleBlock(t_s=t, force=units[0], response=units[1], others=tuple(units[2:]))
