"""One verification run: the target opened, the plan on the run engine, its stores, and the
target made safe on every exit (issue 45).

The stores are subscribers as for a campaign: :class:`JsonLinesJournal` appends every document
to ``DIR/journal.jsonl`` (flushed and synced as written: a power cut loses nothing measured) and
:class:`RecordWriter` writes each point's record to ``DIR/records/<seq>.npz`` before the point's
document. However the run ends (the plan's own ``finally`` bypasses the target; then the run
layer's one safe exit, :func:`setmem_hil.run.safe_exit.stop_safely`, again), the generator is
turned off and the target's bypass confirmed by read back, and the journal notes why the run
stopped and ``output-off`` (``confirmed`` / ``NOT confirmed``) exactly as a campaign's journal
does; what could not be confirmed is said in the error. One verification at a time per directory
(``.verify.lock``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from setmem_hil.run.engine import NOTE, RunEngine, RunStart
from setmem_hil.run.rig_safety import EXCITER_ARMED_EVENT, sigterm_as_interrupt
from setmem_hil.run.run_directory import directory_lock
from setmem_hil.run.safe_exit import first_fault, stop_reason, stop_safely
from setmem_hil.drivers.real_time_target import BYPASS
from setmem_hil.errors import DeviceError, InputFormatError, RunInterrupted
from setmem_hil.verify.plan import NotEngaged, VerifyResult, VerifySetup, verification_plan
from setmem_hil.verify.target_service import TargetService, register_target_commands

__all__ = ["JsonLinesJournal", "RecordWriter", "TargetActuator", "VERIFY_LOCK", "run_verification"]


class JsonLinesJournal:
    """Every document as one JSON line (objects that are not JSON: their ``repr``)."""

    def __init__(self, path: Path):
        self.path = path
        self._file = open(path, "a", encoding="utf-8")

    def __call__(self, event: str, **info: Any) -> None:
        if event == "loop-record":
            info = {k: v for k, v in info.items() if k != "record"}
        self._file.write(json.dumps({"event": event, **info}, default=_jsonable) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())

    def close(self) -> None:
        self._file.close()


def _jsonable(value: Any) -> Any:
    if isinstance(value, complex):
        return [value.real, value.imag]
    if isinstance(value, np.generic):
        return value.item()
    return repr(value)


class RecordWriter:
    """Each point's record (``t_s``, ``r``, ``u``, ``y``) as ``records/<seq>.npz``; the rig at rest
    (target bypassed, generator off) as ``records/baseline.npz``."""

    def __init__(self, folder: Path):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)

    def __call__(self, event: str, **info: Any) -> None:
        if event != "loop-record":
            return
        record = info["record"]
        name = info.get("file_name") or f"{info['seq']:04d}"
        tmp = self.folder / f".{name}.npz"
        with open(tmp, "wb") as f:
            if hasattr(record, "as_arrays"):  # the target's analyser: its sums are what was measured
                np.savez(f, **record.as_arrays())
            else:
                np.savez(f, t_s=record.t_s, r=record.r, u=record.u, y=record.y, omega_rad_s=info["omega_rad_s"])
        os.replace(tmp, self.folder / f"{name}.npz")


def _progress(quiet: bool):
    def show(event: str, **info: Any) -> None:
        if quiet:
            return
        if event == "loaded":
            print(f"compensator loaded: {info['sections']} sections, checksum {info['checksum']} read back", flush=True)
        elif event == "engaged":
            print(f"engaged at gain {info['gain']:g} (implemented mu-bar {info['implemented_mu_bar']:.4g})", flush=True)
        elif event == "point":
            lo, hi = info["predicted_abs_S_min"], info["predicted_abs_S_max"]
            print(f"  {info['omega_rad_s']:9.4g} rad/s: |S| {abs(complex(info['S_re'], info['S_im'])):.4g} +- {info['S_bound']:.2g}, "
                  f"predicted {lo:.4g}..{hi if hi is not None else float('inf'):.4g}: {'inside' if info['inside'] else 'OUTSIDE'}",
                  flush=True)
    return show


VERIFY_LOCK = ".verify.lock"


class TargetActuator:
    """The real-time target as the run layer's actuator (:func:`setmem_hil.run.safe_exit.stop_safely`):
    ``close()`` turns the injection and the generator off and bypasses the target, confirmed by
    read back; ``output_confirmed_off`` is True only after that read back (the campaign's exciter
    contract, :class:`setmem_hil.model.experiment.OutputConfirmingExperiment`)."""

    def __init__(self, service: TargetService):
        self.service = service
        self.exciter = service.target.where
        self.output_confirmed_off = False

    safe_sentence = "target bypassed and generator off (read back)"
    unsafe_advice = "switch the drive off at the amplifier"

    def confirm_output_off(self) -> None:
        self.output_confirmed_off = False
        self.service.generator_off()
        state = self.service.target.bypass()
        if state.mode != BYPASS:
            raise DeviceError(f"{self.service.target.where}: bypassed, but the target reports {state}")
        self.output_confirmed_off = True

    def close(self) -> None:
        self.confirm_output_off()


def run_verification(setup: VerifySetup, target_procedure, procedure, run_dir: str, out: Path, quiet: bool = False
                     ) -> tuple[VerifyResult, BaseException | None]:
    """Run the plan on the target of ``target_procedure`` around the structure of the run's
    ``procedure``; ``(result, failure)``: what was measured, and the error to report (None when it ended).
    One verification at a time per output directory; the run layer's safe exit on every path."""
    with directory_lock(out, VERIFY_LOCK, "another setmem-hil verify is running in this directory; wait for it or stop it first"):
        with sigterm_as_interrupt():  # SIGTERM ends with the target bypassed, the clean-up included
            return _verify_in(setup, target_procedure, procedure, run_dir, out, quiet)


def _verify_in(setup: VerifySetup, target_procedure, procedure, run_dir: str, out: Path, quiet: bool
               ) -> tuple[VerifyResult, BaseException | None]:
    from setmem_hil.experiment_factory import open_target

    opened = open_target(target_procedure, procedure)
    t = target_procedure.target
    service = TargetService(opened.target, opened.rig, fs_hz=t.fs_hz, delay_samples=t.delay_samples, drive_limit=t.drive_limit,
                            watchdog_s=t.watchdog_s, response_limit=target_procedure.verify.response_limit, measure=t.measure,
                            wait=opened.wait)
    actuator = TargetActuator(service)
    journal = JsonLinesJournal(out / "journal.jsonl")
    journal(NOTE, kind=EXCITER_ARMED_EVENT, message=f"{actuator.exciter}: the loop may be engaged from here")
    engine = RunEngine([RecordWriter(out / "records"), journal, _progress(quiet)], safe_state="the target bypassed")
    register_target_commands(engine, service)
    result, caught = VerifyResult(), None
    try:
        engine.run(verification_plan(setup, result), RunStart("closed-loop-verification", {
            "run_dir": str(run_dir), "procedure": target_procedure.name, "fs_hz": t.fs_hz, "delay_samples": t.delay_samples,
            "gains": list(setup.gains), "frequencies_rad_s": list(setup.frequencies_rad_s)}))
    except (NotEngaged, KeyboardInterrupt, DeviceError) as exc:
        caught = exc
    finally:
        stop = stop_safely(actuator, journal, caught)
        journal.close()
    failure = _reported(caught, stop.safety)
    if failure is None and stop.close_error is not None:
        failure = DeviceError(f"the verification finished, but {stop.safety}")
    return result, failure


def _reported(caught: BaseException | None, safety: str) -> BaseException | None:
    """The error the operator reads, with what the safe exit achieved: a device fault by its first
    unanswered command, carrying the safety sentence as the CLI's ``safety_note`` (as a
    campaign's does); the others say it in their message."""
    if caught is None:
        return None
    if isinstance(caught, NotEngaged):
        return InputFormatError("setmem-hil verify", "", f"{caught}; {safety}")
    if isinstance(caught, KeyboardInterrupt):
        return RunInterrupted(f"interrupted ({stop_reason(caught)[1].split(':')[0]}); {safety}")
    failure = first_fault(caught)
    failure.safety_note = safety
    return failure
