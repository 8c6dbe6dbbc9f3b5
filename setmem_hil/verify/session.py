"""One verification run: the target opened, the plan on the run engine, its stores, and the
target made safe on every exit (issue 45).

The stores are subscribers as for a campaign, and of the campaign's kind (issue 63 item 6):
:class:`VerificationJournal` commits every document to ``DIR/journal.sqlite`` (the campaign's
journal: its notes as the same events, every other document as an event holding it as JSON) and
:class:`RawLoopRecords` writes each point's record to ``DIR/raw.h5`` (the campaign's raw store:
``raw/<seq>.h5``, seq 0 the rig at rest) before the point's document. The earlier files stay for
their readers: :class:`JsonLinesJournal` appends every document to ``DIR/journal.jsonl`` (flushed
and synced as written) and :class:`RecordWriter` writes ``DIR/records/<seq>.npz``. However the run ends (the plan's own ``finally`` bypasses the target; then the run
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

from setmem_hil.io.journal import Journal, journal_path
from setmem_hil.io.raw_store import RawStore
from setmem_hil.model.experiment import RawRecord
from setmem_hil.run.engine import NOTE, START, STOP, RunEngine, RunStart
from setmem_hil.run.rig_safety import EXCITER_ARMED_EVENT, sigterm_as_interrupt
from setmem_hil.run.run_directory import directory_lock
from setmem_hil.run.safe_exit import first_fault, interrupted_by, stop_safely
from setmem_hil.drivers.real_time_target import BYPASS
from setmem_hil.errors import DeviceError, InputFormatError, RunInterrupted
from setmem_hil.verify.plan import NotEngaged, VerifyResult, VerifySetup, verification_plan
from setmem_hil.verify.target_service import TargetService, register_target_commands

__all__ = ["JsonLinesJournal", "RecordWriter", "VerificationJournal", "RawLoopRecords", "TargetActuator", "VERIFY_LOCK",
           "run_verification", "next_free_seq", "RAW_KIND_ANALYSER", "RAW_KIND_SAMPLES"]

RAW_KIND_ANALYSER = "closed-loop-analyser-sums"
"""A point measured by the target's analyser: its sums (``sums_r``, ``sums_u``, ``sums_y``, ...)."""
RAW_KIND_SAMPLES = "closed-loop-samples"
"""A point recorded by the rig: ``t_s``, ``r``, ``u``, ``y`` as read."""


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


class VerificationJournal:
    """The verification's documents in the campaign's journal (``DIR/journal.sqlite``): created
    from the target procedure on the first verification in ``DIR``, appended to by later ones.
    Notes (``exciter-armed``, ``interrupted``, ``output-off``, ...) are stored as the campaign
    stores them, events of their own kind; ``start`` / ``stop`` as ``run-start`` / ``run-stop``;
    every other document as an event of its name holding the document as JSON (a record's
    samples go to the raw store, not here)."""

    def __init__(self, out: Path, target_procedure):
        from setmem_hil import __version__

        if journal_path(out).exists():
            self.journal = Journal.open(out)
        else:
            self.journal = Journal.create(out, procedure_text=target_procedure.source_text, procedure_name=target_procedure.name,
                                          seed=0, software_version=__version__, backend=f"target:{target_procedure.target.kind}",
                                          strategy="closed-loop-verification")

    def __call__(self, event: str, **info: Any) -> None:
        if event == NOTE:
            self.journal.add_event(str(info["kind"]), str(info["message"]))
            return
        kind = {START: "run-start", STOP: "run-stop"}.get(event, event)
        shown = {k: v for k, v in info.items() if k != "record"}
        self.journal.add_event(kind, json.dumps(shown, sort_keys=True, default=_jsonable))

    def close(self) -> None:
        self.journal.close()


class RawLoopRecords:
    """Each point's record in the campaign's raw store (``DIR/raw.h5``, :mod:`setmem_hil.io.raw_store`),
    named by the point's seq (the rig at rest before engaging: the verification's first seq, attribute
    ``label``; a later verification in the same directory numbers after the earlier's, :func:`next_free_seq`)."""

    def __init__(self, out: Path):
        self.store = RawStore(out)

    def __call__(self, event: str, **info: Any) -> None:
        if event != "loop-record":
            return
        record = info["record"]
        attrs = {"omega_rad_s": float(info["omega_rad_s"])}
        if info.get("label"):
            attrs["label"] = str(info["label"])
        if hasattr(record, "as_arrays"):  # the target's analyser: its sums are what was measured
            raw = RawRecord(RAW_KIND_ANALYSER, {k: np.asarray(v) for k, v in record.as_arrays().items()}, attrs)
        else:
            raw = RawRecord(RAW_KIND_SAMPLES, {"t_s": record.t_s, "r": record.r, "u": record.u, "y": record.y}, attrs)
        self.store.write((int(info["seq"]),), raw)


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


class _Journals:
    """Both journals as one subscriber (the safe exit writes its notes to it once)."""

    def __init__(self, *journals):
        self.journals = journals

    def __call__(self, event: str, **info: Any) -> None:
        for journal in self.journals:
            journal(event, **info)

    def close(self) -> None:
        for journal in self.journals:
            journal.close()

def next_free_seq(out: Path) -> int:
    """The first seq no earlier verification in ``out`` used (in the raw store or ``records/``): 0
    in a new directory. A second ``verify`` into the same directory appends its records after the
    first's instead of overwriting them (the journal already appends)."""
    from setmem_hil.io.raw_store import RAW_FOLDER

    used = [int(p.stem) for p in (out / RAW_FOLDER).glob("*.h5") if p.stem.isdigit()]
    used += [int(p.stem.rsplit("-", 1)[-1]) for p in (out / "records").glob("*.npz") if p.stem.rsplit("-", 1)[-1].isdigit()]
    return max(used) + 1 if used else 0


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
                            wait=opened.wait, first_seq=next_free_seq(out))
    actuator = TargetActuator(service)
    journal = _Journals(JsonLinesJournal(out / "journal.jsonl"), VerificationJournal(out, target_procedure))
    journal(NOTE, kind=EXCITER_ARMED_EVENT, message=f"{actuator.exciter}: the loop may be engaged from here")
    engine = RunEngine([RawLoopRecords(out), RecordWriter(out / "records"), journal, _progress(quiet)], safe_state="the target bypassed")
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
        return RunInterrupted(f"interrupted ({interrupted_by(caught)}); {safety}")
    failure = first_fault(caught)
    failure.safety_note = safety
    return failure
