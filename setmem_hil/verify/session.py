"""One verification run: the target opened, the plan on the run engine, its stores, and the
target made safe on every exit (issue 45).

The stores are subscribers as for a campaign: :class:`JsonLinesJournal` appends every document
to ``DIR/journal.jsonl`` (flushed and synced as written: a power cut loses nothing measured) and
:class:`RecordWriter` writes each point's record to ``DIR/records/<seq>.npz`` before the point's
document. However the run ends (the plan's own ``finally`` bypasses the target; if that failed
or never ran, here again), the generator is turned off and the target's bypass confirmed by
read back; what could not be confirmed is said in the error.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from setmem_hil.campaign.engine import RunEngine, RunStart
from setmem_hil.campaign.rig_safety import Terminated, sigterm_as_interrupt
from setmem_hil.drivers.real_time_target import BYPASS
from setmem_hil.errors import DeviceError, InputFormatError, RunInterrupted
from setmem_hil.verify.plan import NotEngaged, VerifyResult, VerifySetup, verification_plan
from setmem_hil.verify.target_service import TargetService, register_target_commands

__all__ = ["JsonLinesJournal", "RecordWriter", "run_verification"]


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


def run_verification(setup: VerifySetup, target_procedure, procedure, run_dir: str, out: Path, quiet: bool = False
                     ) -> tuple[VerifyResult, BaseException | None]:
    """Run the plan on the target of ``target_procedure`` around the structure of the run's
    ``procedure``; ``(result, failure)``: what was measured, and the error to report (None when it ended)."""
    from setmem_hil.experiment_factory import open_target

    opened = open_target(target_procedure, procedure)
    t = target_procedure.target
    service = TargetService(opened.target, opened.rig, fs_hz=t.fs_hz, delay_samples=t.delay_samples, drive_limit=t.drive_limit,
                            watchdog_s=t.watchdog_s, response_limit=target_procedure.verify.response_limit, measure=t.measure,
                            wait=opened.wait)
    journal = JsonLinesJournal(out / "journal.jsonl")
    engine = RunEngine([RecordWriter(out / "records"), journal, _progress(quiet)], safe_state="the target bypassed")
    register_target_commands(engine, service)
    result, failure = VerifyResult(), None
    try:
        with sigterm_as_interrupt():  # SIGTERM too ends with the target bypassed
            engine.run(verification_plan(setup, result), RunStart("closed-loop-verification", {
                "run_dir": str(run_dir), "procedure": target_procedure.name, "fs_hz": t.fs_hz, "delay_samples": t.delay_samples,
                "gains": list(setup.gains), "frequencies_rad_s": list(setup.frequencies_rad_s)}))
    except NotEngaged as exc:
        failure = InputFormatError("setmem-hil verify", "", str(exc))
    except KeyboardInterrupt as exc:
        failure = RunInterrupted("interrupted (SIGTERM)" if isinstance(exc, Terminated) else "interrupted (Ctrl-C)")
    except DeviceError as exc:
        failure = exc
    finally:
        safety = _confirm_safe(service)
        journal.close()
    if failure is not None:
        failure = _with_safety(failure, safety)
    elif not safety.startswith("target bypassed"):
        failure = DeviceError(f"the verification finished, but {safety}")
    return result, failure


def _confirm_safe(service: TargetService) -> str:
    try:
        service.generator_off()
        state = service.target.bypass()
        return "target bypassed and generator off (read back)" if state.mode == BYPASS else f"the target reports {state}"
    except (DeviceError, OSError) as exc:
        return f"the target's bypass could not be confirmed ({exc}): switch the drive off at the amplifier"


def _with_safety(failure: BaseException, safety: str) -> BaseException:
    """The failure with what the clean-up achieved: a device fault carries it as the CLI's
    ``safety_note`` (as a campaign's does); the others say it in their message."""
    if isinstance(failure, DeviceError):
        failure.safety_note = safety
        return failure
    if isinstance(failure, InputFormatError):
        return InputFormatError(failure.source, failure.location, f"{failure.problem}; {safety}")
    return RunInterrupted(f"{failure}; {safety}")
