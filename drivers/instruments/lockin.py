"""A lock-in amplifier driven through its profile (SR830, SR860, ...): phasor readings."""

from __future__ import annotations

from setmem_hil.drivers.instruments.profile import LockInProfile
from setmem_hil.drivers.instruments.scpi_commands import parse_number, parse_numbers
from setmem_hil.drivers.instruments.scpi_instrument import ScpiInstrument
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DataQualityError, DeviceRejectedError

__all__ = ["LockIn", "LockInOverload", "ReferenceUnlocked", "filter_settling_time_constants"]


class LockInOverload(DataQualityError):
    """The lock-in's input or output is overloaded at its present full scale."""


class ReferenceUnlocked(DataQualityError):
    """The lock-in's reference is not (yet) locked: it relocks after every frequency step, so
    the dwell waits (:meth:`PhasorDwellExperiment._wait_locked`) before this is a fault."""

# Time, in time constants, for the output filter to settle within 1 % after a step, by filter
# order (SR830 manual, "Time constants and settling": 5, 7, 9 and 10 tau for 6-24 dB/oct).
_SETTLING_TAUS = {1: 5.0, 2: 7.0, 3: 9.0, 4: 10.0}


def filter_settling_time_constants(order: int) -> float:
    return _SETTLING_TAUS[order]


class LockIn(ScpiInstrument):
    """X, Y (V RMS) of one sensor signal at the reference frequency."""

    profile: LockInProfile

    # auto-ranging: the full scale is at least this many times the largest reading component
    # (room for the response to grow while it settles), and a reading above RANGE_UP_FRACTION of
    # the full scale moves one range up
    RANGE_HEADROOM = 3.0
    RANGE_UP_FRACTION = 0.8

    def __init__(self, name: str, profile: LockInProfile, link: VisaLink):
        super().__init__(name, profile, link)
        self.time_constant_s = 0.0
        self.full_scale_v = profile.full_scale_v

    @property
    def settling_time_s(self) -> float:
        """Time after which the output has settled and successive readings are independent."""
        return filter_settling_time_constants(self.profile.filter_order) * self.time_constant_s

    def initialise(self) -> None:
        """Init sequence, then select and verify the external reference."""
        self.run_init()
        self.set_checked(self.profile.reference)

    def set_time_constant(self, at_least_s: float) -> float:
        """The shortest time constant of the instrument >= ``at_least_s`` (or its longest); returns it."""
        values = self.profile.time_constants_s
        index = next((i for i, v in enumerate(values) if v >= at_least_s), len(values) - 1)
        if values[index] != self.time_constant_s:
            self._set_index(self.profile.time_constant, index, "time constant")
            self.time_constant_s = values[index]
        return self.time_constant_s

    @property
    def can_range(self) -> bool:
        return self.profile.sensitivity is not None and bool(self.profile.sensitivities_v)

    def set_range_for(self, reading_v: complex) -> bool:
        """Smallest full scale >= ``RANGE_HEADROOM`` x the larger of |X|, |Y| (the largest if
        none is); returns whether the range changed. Without a sensitivity in the profile: no-op."""
        if not self.can_range:
            return False
        need = self.RANGE_HEADROOM * max(abs(reading_v.real), abs(reading_v.imag))
        ordered = sorted(range(len(self.profile.sensitivities_v)), key=lambda i: self.profile.sensitivities_v[i])
        index = next((i for i in ordered if self.profile.sensitivities_v[i] >= need), ordered[-1])
        return self._select_range(index)

    def range_up(self) -> bool:
        """One full scale up; False when already at the largest."""
        if not self.can_range:
            return False
        bigger = [v for v in self.profile.sensitivities_v if v > self.full_scale_v]
        if not bigger:
            return False
        return self._select_range(self.profile.sensitivities_v.index(min(bigger)))

    def _select_range(self, index: int) -> bool:
        value = self.profile.sensitivities_v[index]
        if value == self.full_scale_v:
            return False
        self._set_index(self.profile.sensitivity, index, "sensitivity")
        self.full_scale_v = value
        return True

    def _set_index(self, setting, index: int, what: str) -> None:
        """Send an indexed setting (``{index}`` in its template), read the index back, check errors."""
        command = setting.set.format(index=index)
        self.link.write(command)
        if setting.query:
            got = self.query_parsed(setting.query, self._picker(setting, lambda t: int(parse_number(t))), f"{what} read-back")
            if got != index:
                raise DeviceRejectedError("instrument", f"{self.where}: {what} index {index} sent, the instrument reads back {got}")
        self.check_errors(command)

    def near_full_scale(self, reading_v: complex) -> bool:
        return max(abs(reading_v.real), abs(reading_v.imag)) > self.RANGE_UP_FRACTION * self.full_scale_v

    def reference_frequency_hz(self) -> float:
        return self.query_parsed(self.profile.reference_frequency_query, parse_number, "reference frequency")

    def read_xy(self) -> complex:
        """One reading ``X + jY`` in volts RMS; overload or reference unlock raise."""
        x, y = self.query_parsed(self.profile.read_xy, lambda r: parse_numbers(r, 2), "reading X, Y")
        self.check_status()
        return complex(x, y)

    def _status(self) -> int:
        return self.query_parsed(self.profile.status_query, lambda r: int(parse_number(r)), "status")

    def locked(self) -> bool:
        """Is the reference locked now? (True when the profile has no status query to tell.)"""
        return not (self.profile.status_query and self.profile.unlock_mask and self._status() & self.profile.unlock_mask)

    def check_status(self) -> None:
        if not self.profile.status_query:
            return
        status = self._status()
        if status & self.profile.unlock_mask:
            raise ReferenceUnlocked(f"{self.where}: reference unlocked (status {status})")
        if status & self.profile.overload_mask:
            raise LockInOverload(f"{self.where}: overload (status {status}): the signal exceeds the lock-in's "
                                 f"{self.full_scale_v:g} V full scale{'' if self.can_range else ''}; lower volt_per_unit or the force level")
