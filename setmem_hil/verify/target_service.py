"""The verification's commands on the run engine: the real-time target and the rig around it.

:class:`TargetService` performs the plan's requests (:mod:`setmem_hil.verify.messages`) with a
:class:`~setmem_hil.drivers.real_time_target.RealTimeTarget` and one of two ways to measure a
point (``[target] measure``):

* ``"recorder"``: a :class:`LoopRig` (the generator summed into the drive and a recorder of
  injection, drive and response); the record is the samples;
* ``"analyser"``: the target's own injection and analyser (``INJECT``, ``ANALYSE``, polled with
  ``ANALYSIS?``, then ``SUMS?``); the record is the sums
  (:class:`~setmem_hil.estimation.analyser_sums.AnalyserSums`). ``wait(seconds)`` lets the target
  run: the wall clock for a board, the emulated loop's own steps for an emulated one.

While a point settles and records, it watches the loop every :data:`WATCH_S` seconds (and at
least once a period): the target's state (which also feeds its watchdog) and the response against
the procedure's limit. A target that tripped, or a response past its limit, stops the point: the
generator off, the target bypassed, then :class:`LoopFault` (exit 4) naming it. An analyser that
does not advance for :data:`STALL_S` seconds is a fault too (the target's sample timer stopped).
"""

from __future__ import annotations

import math
import time
from typing import Callable, Protocol

import numpy as np

from setmem_hil.run.engine import RunEngine
from setmem_hil.drivers.real_time_target import TRIPPED, RealTimeTarget, trip_meaning
from setmem_hil.errors import DeviceError, DeviceIdentityError, DeviceTimeoutError
from setmem_hil.verify.messages import Bypass, Engage, IdentifyTarget, InjectAndRecord, LoadCompensator

__all__ = ["LoopRig", "LoopFault", "TargetService", "register_target_commands", "WATCH_S"]

WATCH_S = 0.25
"""The host looks at the target at least this often while the loop runs (the watchdog's default is 0.5 s)."""
STALL_S = 10.0
"""An analyser whose progress does not change for this long (wall clock) has stopped."""


class LoopRig(Protocol):
    """The generator at the summing junction and the recorder beside the rig."""

    fs_hz: float

    def set_generator(self, amplitude: float, omega_rad_s: float) -> None: ...

    def run(self, n_samples: int): ...  # -> LoopRecord (r, u, y, t_s)


class LoopFault(DeviceError):
    """The loop was stopped for safety: the target tripped, or the response passed its limit."""


class TargetService:
    """Performs the verification's requests (see the module docstring)."""

    def __init__(self, target: RealTimeTarget, rig: LoopRig | None, *, fs_hz: float, delay_samples: int, drive_limit: float,
                 watchdog_s: float, response_limit: float | None = None, measure: str = "recorder",
                 wait: Callable[[float], object] = time.sleep, first_seq: int = 0):
        if measure == "recorder" and rig is None:
            raise ValueError("measure = 'recorder' needs a rig")
        self.target, self.rig, self.measure, self.wait = target, rig, measure, wait
        self.fs_hz, self.delay_samples, self.drive_limit = float(fs_hz), int(delay_samples), float(drive_limit)
        self.watchdog_s, self.response_limit = float(watchdog_s), response_limit
        # a directory's seqs are never reused: a second verification there numbers its records after
        # the first's (the rig at rest: first_seq, then each point), so nothing stored is overwritten
        self.first_seq, self.records = int(first_seq), int(first_seq)

    def identify(self, engine: RunEngine, request: IdentifyTarget):
        identity = self.target.identity()
        if not math.isclose(identity.fs_hz, self.fs_hz, rel_tol=1e-9) or identity.delay_samples != self.delay_samples:
            raise DeviceIdentityError(f"{self.target.where}: the target runs at {identity.fs_hz:g} Hz with {identity.delay_samples} "
                                      f"samples of delay, the procedure says {self.fs_hz:g} Hz and {self.delay_samples}: "
                                      "the guarantee was computed for the procedure's")
        return identity

    def load(self, engine: RunEngine, request: LoadCompensator) -> int:
        self.target.bypass()
        self.target.set_drive_limit(self.drive_limit)
        self.target.set_watchdog(self.watchdog_s)
        return self.target.load(request.sos, request.gain)

    def engage(self, engine: RunEngine, request: Engage):
        return self.target.engage(request.gain)

    def inject_and_record(self, engine: RunEngine, request: InjectAndRecord):
        record = self._analysed(request) if self.measure == "analyser" else self._recorded(request)
        if not request.label:
            self.records += 1
        label = request.label and (request.label if self.first_seq == 0 else f"{request.label}-{self.records:04d}")
        engine.emit("loop-record", seq=self.records, file_name=label or f"{self.records:04d}", label=request.label or None,
                    omega_rad_s=request.omega_rad_s,
                    record=record)
        return record

    def _recorded(self, request: InjectAndRecord):
        rate = self.rig.fs_hz
        chunk = max(1, int(min(WATCH_S, 2 * math.pi / request.omega_rad_s) * rate))
        self.rig.set_generator(request.amplitude, request.omega_rad_s)
        try:
            self._run_watched(int(round(request.settle_s * rate)), chunk, request)
            return self._run_watched(int(round(request.record_s * rate)), chunk, request, keep=True)
        finally:
            self.rig.set_generator(0.0, 0.0)

    def _analysed(self, request: InjectAndRecord):
        settle, count = int(round(request.settle_s * self.fs_hz)), max(8, int(round(request.record_s * self.fs_hz)))
        self.target.inject(request.amplitude, request.omega_rad_s)
        try:
            self.target.analyse(settle, count)
            progress = self._poll_analysis(request)
            return self.target.sums(request.omega_rad_s, self.fs_hz, progress)
        finally:
            self._injection_off()

    def _poll_analysis(self, request: InjectAndRecord):
        step = min(WATCH_S, 2 * math.pi / request.omega_rad_s)
        last, since = None, time.monotonic()
        while True:
            self.wait(step)
            progress = self.target.analysis()
            self._check(request, progress.peak_drive, progress.peak_response)
            if progress.state == "DONE":
                return progress
            if progress.state == "IDLE":
                raise DeviceError(f"{self.target.where}: the target's analyser stopped (IDLE) at {request.omega_rad_s:.4g} rad/s")
            if (progress.state, progress.done) != last:
                last, since = (progress.state, progress.done), time.monotonic()
            elif time.monotonic() - since > STALL_S:
                raise DeviceTimeoutError(f"{self.target.where}: the target's analyser did not advance in {STALL_S:g} s at "
                                         f"{request.omega_rad_s:.4g} rad/s ({progress.state} {progress.done}): its sample timer stopped")

    def _injection_off(self) -> None:
        try:
            self.target.inject(0.0, 0.0)
        except DeviceError:  # the link is down: the caller's error says so, and the session confirms what it can
            pass

    def _run_watched(self, n: int, chunk: int, request: InjectAndRecord, keep: bool = False):
        parts = []
        done = 0
        while done < n:
            part = self.rig.run(min(chunk, n - done))
            done += part.r.size
            self._check(request, float(np.max(np.abs(part.u))), float(np.max(np.abs(part.y))))
            if keep:
                parts.append(part)
        if not keep:
            return None
        first = parts[0]
        return type(first)(first.fs_hz, first.t0_s, *(np.concatenate([getattr(p, c) for p in parts]) for c in ("r", "u", "y")))

    def _check(self, request: InjectAndRecord, peak_drive: float, peak_response: float) -> None:
        """The target's state (a trip) and the response against its limit; :class:`LoopFault` after making safe."""
        state = self.target.state()
        where = f"at {request.omega_rad_s:.4g} rad/s"
        if state.mode == TRIPPED:
            self._make_safe()
            raise LoopFault(f"{self.target.where}: the target tripped ({state.reason}) {where}, "
                            f"peak drive {peak_drive:.3g}: {trip_meaning(state.reason)}; bypassed")
        if self.response_limit is not None and peak_response > self.response_limit:
            self._make_safe()
            raise LoopFault(f"the response reached {peak_response:.3g} {where}, past the limit {self.response_limit:g}: "
                            "the loop grew; bypassed")

    def generator_off(self) -> None:
        """The injection off, whichever injects."""
        if self.rig is not None:
            self.rig.set_generator(0.0, 0.0)
        if self.measure == "analyser":
            self._injection_off()

    def _make_safe(self) -> None:
        self.generator_off()
        self.target.bypass()

    def bypass(self, engine: RunEngine, request: Bypass):
        self.generator_off()
        return self.target.bypass()


def register_target_commands(engine: RunEngine, service: TargetService) -> TargetService:
    engine.register_command(IdentifyTarget, service.identify)
    engine.register_command(LoadCompensator, service.load)
    engine.register_command(Engage, service.engage)
    engine.register_command(InjectAndRecord, service.inject_and_record)
    engine.register_command(Bypass, service.bypass)
    return service
