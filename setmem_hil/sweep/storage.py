"""Storage of a sweep's campaigns: ``DIR/runs/<strategy>-seed<N>/`` (see :mod:`setmem_hil.sweep.runner`).

A campaign is written into a fresh directory under ``DIR/runs/.partial/`` and renamed into place
when finished (``os.replace`` of a directory is atomic on one filesystem), so only complete runs
appear under their final name: ``summary.json`` + ``journal.sqlite`` when the campaign finished,
``error.json`` (+ the partial journal) when it raised. ``summary.json`` carries the procedure's
fingerprint so that a sweep never mixes runs of different procedures.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
import time
import traceback
import uuid
from pathlib import Path
from typing import Sequence

from setmem_hil.errors import InputFormatError
from setmem_hil.io.atomic_file import write_json_atomic
from setmem_hil.io.procedure import Procedure

RUNS_DIRNAME = "runs"
PARTIAL_DIRNAME = ".partial"
SUMMARY_NAME = "summary.json"
ERROR_NAME = "error.json"
JOURNAL_NAME = "journal.sqlite"


def run_name(strategy: str, seed: int, design: str | None = None) -> str:
    """Directory name of one campaign under ``DIR/runs``: ``<strategy>-seed<N>``, or
    ``<strategy>-<design>-seed<N>`` in a sweep over designs (``--designs``)."""
    return f"{strategy}-seed{int(seed)}" if design is None else f"{strategy}-{design}-seed{int(seed)}"


def procedure_fingerprint(procedure: Procedure) -> str:
    """SHA-256 of everything in ``procedure`` that changes a campaign's results.

    The seed (set per campaign by the sweep), the file's text, path and description (comments
    and prose) are left out; the parsed prior, goal, initial frequencies, input design, weights,
    backend settings and safety limits are in.
    """
    core = dataclasses.replace(procedure, seed=0, source_text="", source_path="", description="")
    return hashlib.sha256(repr(core).encode("utf-8")).hexdigest()


def new_partial_dir(runs_dir: Path, name: str) -> Path:
    partial = runs_dir / PARTIAL_DIRNAME
    partial.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f"{name}-", dir=partial))
    tmp.chmod(0o755)  # mkdtemp makes it private; a finished run is readable like any directory
    return tmp


def install_run(tmp_dir: Path, final_dir: Path) -> None:
    """Move a finished run directory into place (replacing a failed earlier attempt)."""
    if final_dir.exists():
        old = final_dir.parent / PARTIAL_DIRNAME / f"{final_dir.name}-replaced-{uuid.uuid4().hex}"
        os.replace(final_dir, old)
        os.replace(tmp_dir, final_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp_dir, final_dir)


def run_record(seed: int, strategy: str, summary: dict, design: str | None = None) -> dict:
    """The ``sweep.json`` row of a finished campaign (``design``: named in a sweep over designs)."""
    return {
        "seed": int(seed),
        "strategy": strategy,
        **({} if design is None else {"design": design}),
        "reached_goal": bool(summary["reached_goal"]),
        "experiments_added": int(summary["experiments_added"]),
        "final_mu_peak": float(summary["final_mu_peak"]),
        "wall_s": float(summary["wall_s"]),
    }


def error_record(seed: int, strategy: str, error: str, design: str | None = None) -> dict:
    """The ``sweep.json`` row of a failed campaign."""
    return {"seed": int(seed), "strategy": strategy, **({} if design is None else {"design": design}), "reached_goal": False,
            "experiments_added": None, "final_mu_peak": None, "wall_s": None, "error": error}


def error_document(seed: int, strategy: str, exc: BaseException, where: str) -> dict:
    return {
        "seed": int(seed),
        "strategy": strategy,
        "error": f"{type(exc).__name__}: {exc}",
        "error_type": type(exc).__name__,
        "traceback": "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
        "where": where,
        "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def record_failure(out_dir: str | os.PathLike, seed: int, strategy: str, exc: BaseException, where: str,
                   design: str | None = None) -> dict:
    """Store ``error.json`` for a campaign whose task failed outside :func:`sweep_campaign`
    (worker died, task not deserialisable, ...); never touches a finished run."""
    final = Path(out_dir) / RUNS_DIRNAME / run_name(strategy, seed, design)
    err = error_document(seed, strategy, exc, where)
    if not (final / SUMMARY_NAME).is_file():
        tmp = new_partial_dir(final.parent, final.name)
        write_json_atomic(err, tmp / ERROR_NAME)
        install_run(tmp, final)
    return {**error_record(seed, strategy, err["error"], design), "status": "failed"}


def read_run(out_dir: str | os.PathLike, seed: int, strategy: str, design: str | None = None) -> dict | None:
    """The stored ``sweep.json`` row of one campaign, or ``None`` if it has not run."""
    final = Path(out_dir) / RUNS_DIRNAME / run_name(strategy, seed, design)
    if (final / SUMMARY_NAME).is_file():
        return run_record(seed, strategy, json.loads((final / SUMMARY_NAME).read_text(encoding="utf-8")), design)
    if (final / ERROR_NAME).is_file():
        err = json.loads((final / ERROR_NAME).read_text(encoding="utf-8"))
        return error_record(seed, strategy, str(err.get("error", "unknown error")), design)
    return None


def plan_runs(procedure: Procedure, seeds: Sequence[int], strategies: Sequence[str], out_dir: Path,
              designs: Sequence[str | None] = (None,)) -> tuple[list[tuple[int, str, str | None]], list[tuple[int, str, str | None]]]:
    """Split the campaigns (seed, strategy, design: None unless named) into (pending, done);
    refuse done runs of a different procedure."""
    fingerprint = procedure_fingerprint(procedure)
    pending, done = [], []
    for seed in seeds:
        for strategy, design in ((s, d) for s in strategies for d in designs):
            summary_path = out_dir / RUNS_DIRNAME / run_name(strategy, seed, design) / SUMMARY_NAME
            if not summary_path.is_file():
                pending.append((seed, strategy, design))
                continue
            try:
                stored = json.loads(summary_path.read_text(encoding="utf-8")).get("sweep", {})
            except (OSError, ValueError):
                stored = {}
            if stored.get("procedure_fingerprint") != fingerprint:
                raise InputFormatError(
                    str(summary_path), "",
                    "this finished campaign was run with a different procedure or goal than this sweep; "
                    "use another --out directory (or delete the runs to redo them)",
                )
            done.append((seed, strategy, design))
    return pending, done


def clean_partials(out_dir: Path) -> None:
    """Remove what killed campaigns left under ``DIR/runs/.partial`` (one sweep per DIR at a time)."""
    partial = Path(out_dir) / RUNS_DIRNAME / PARTIAL_DIRNAME
    if partial.is_dir():
        for entry in partial.iterdir():
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)


__all__ = [
    "ERROR_NAME",
    "JOURNAL_NAME",
    "PARTIAL_DIRNAME",
    "RUNS_DIRNAME",
    "SUMMARY_NAME",
    "error_record",
    "plan_runs",
    "procedure_fingerprint",
    "read_run",
    "record_failure",
    "run_name",
    "run_record",
    "write_json_atomic",
]
