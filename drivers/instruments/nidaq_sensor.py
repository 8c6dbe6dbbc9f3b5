"""An NI DAQ card as the rig's sensor (NI-DAQmx through the ``nidaqmx`` package, extra ``[daq]``).

Implements :class:`setmem_hil.drivers.protocols.Sensor` (``acquire``) and
:class:`~setmem_hil.drivers.protocols.RateConfigurableSensor` (``set_sample_rate``): each
acquisition is one finite task with two analog voltage inputs (force, response), hardware
sample clock at the set rate; volts are converted with the sensors' ``volt_per_unit``. The
samples then go through the existing sine fit (:mod:`setmem_hil.estimation.sine_fit`), as for
any sampled rig. NI's driver (NI-DAQmx runtime) must be installed on the PC; an error from it is
one :class:`~setmem_hil.errors.DeviceError` line naming the channels.
"""

from __future__ import annotations

import math

import numpy as np

from setmem_hil.drivers.protocols import SampleBlock
from setmem_hil.errors import DeviceError

__all__ = ["NidaqSensor"]


class NidaqSensor:
    """Force and response voltages from two analog inputs (e.g. ``"Dev1/ai0"``, ``"Dev1/ai1"``)."""

    def __init__(self, force_channel: str, response_channel: str, force_volt_per_unit: float, response_volt_per_unit: float, *,
                 range_v: float = 10.0, terminal: str = "DIFF", sample_rate_hz: float = 1000.0, nidaqmx_module=None):
        if nidaqmx_module is None:
            try:
                import nidaqmx as nidaqmx_module
            except ImportError:  # pragma: no cover - the [daq] extra is in [test]
                raise DeviceError("NI-DAQ: the nidaqmx package is not installed; pip install 'setmem-hil[daq]'") from None
        self.nidaqmx = nidaqmx_module
        self.channels = (force_channel, response_channel)
        self.scale = (float(force_volt_per_unit), float(response_volt_per_unit))
        self.range_v, self.terminal = float(range_v), terminal
        self.sample_rate_hz = float(sample_rate_hz)
        self._t = 0.0  # the sensor's own time axis: acquisitions follow each other

    @property
    def where(self) -> str:
        return f"NI-DAQ {self.channels[0]}, {self.channels[1]}"

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
        if volts.shape != (2, n):
            raise DeviceError(f"{self.where}: expected 2 x {n} samples, the driver returned shape {volts.shape}")
        t = self._t + np.arange(n) / self.sample_rate_hz
        self._t += n / self.sample_rate_hz
        return SampleBlock(t_s=t, force=volts[0] / self.scale[0], response=volts[1] / self.scale[1])
