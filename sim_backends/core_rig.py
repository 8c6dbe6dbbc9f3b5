"""In-process rig over a :class:`FakeDeviceCore` (no transport): for tests and benchmarks.

Implements :class:`setmem_hil.drivers.protocols.Rig` and its optional capabilities
(sample rate per acquisition, wait, measurement index, multisine excitation) by direct calls, so the sine-dwell
numerics can be exercised without any wire format.
"""

from __future__ import annotations


from setmem_hil.drivers.protocols import RigMetadata, SampleBlock
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore


class _CoreExciter:
    def __init__(self, core: FakeDeviceCore):
        self.core = core

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        self.core.set_sine(omega_rad_s, amplitude_n)

    def set_multisine(self, omegas_rad_s, amplitudes_n, phases_rad) -> None:
        self.core.set_multisine(omegas_rad_s, amplitudes_n, phases_rad)

    def stop(self) -> None:
        self.core.stop()


class _CoreSensor:
    def __init__(self, core: FakeDeviceCore):
        self.core = core

    def set_sample_rate(self, rate_hz: float) -> None:
        self.core.set_sample_rate(rate_hz)

    def wait(self, duration_s: float) -> None:
        self.core.wait(duration_s)

    def acquire(self, duration_s: float) -> SampleBlock:
        n = max(1, int(round(duration_s * self.core.sample_rate_hz)))
        self.core.capture(n)
        return self.core.read_buffer(0, n)


class CoreRig:
    """A rig that calls the fake device core directly."""

    def __init__(self, core: FakeDeviceCore):
        self.core = core
        self.exciter = _CoreExciter(core)
        self.sensor = _CoreSensor(core)
        self.closed = False

    @property
    def metadata(self) -> RigMetadata:
        md = self.core.metadata
        return RigMetadata(self.core.sample_rate_hz, md.force_range_n, md.response_range, md.force_unit, md.response_unit, md.name)

    def begin_measurement(self, index: int, attempt: int = 0) -> None:
        self.core.begin_measurement(index, attempt)

    def close(self) -> None:
        self.core.stop()
        self.closed = True
