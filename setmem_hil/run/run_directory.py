"""A run's directory: its name, its files, and one process at a time in it."""

from __future__ import annotations

import re
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator

from rich.console import Console

from setmem_hil import os_support
from setmem_hil.errors import InputFormatError
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import Procedure

__all__ = ["LOCK_FILENAME", "PROCEDURE_COPY", "SUMMARY_FILENAME", "default_run_dir", "describe_procedure", "directory_lock", "run_lock"]

SUMMARY_FILENAME = "summary.json"
PROCEDURE_COPY = "procedure.toml"
LOCK_FILENAME = ".run.lock"


@contextmanager
def directory_lock(folder: Path, lock_name: str, busy: str) -> Iterator[None]:
    """One process at a time per directory, on every OS (:mod:`setmem_hil.os_support`);
    ``InputFormatError(folder, "", busy)`` when another holds it."""
    try:
        with os_support.directory_lock(folder, lock_name):
            yield
    except os_support.DirectoryBusy:
        raise InputFormatError(str(folder), "", busy) from None


@contextmanager
def run_lock(run_dir: Path, journal: Journal) -> Iterator[None]:
    """Two resumes of the same run would both append after the stored measurements."""
    try:
        with directory_lock(run_dir, LOCK_FILENAME, "another setmem-hil process is running this campaign; wait for it or stop it first"):
            yield
    except InputFormatError:
        if not journal.closed:
            journal.close()
        raise


def default_run_dir(procedure: Procedure, now: datetime | None = None) -> Path:
    """``runs/<name>-<YYYYmmddTHHMMSSZ>`` (name made file-system safe)."""
    now = now or datetime.now(timezone.utc)
    safe = re.sub(r"[^A-Za-z0-9._-]+", "-", procedure.name).strip("-.") or "run"
    return Path("runs") / f"{safe}-{now.strftime('%Y%m%dT%H%M%SZ')}"


def describe_procedure(procedure: Procedure, console: Console) -> None:
    p = procedure
    console.print(
        f"procedure {p.name!r}: backend {p.backend.kind}, {p.prior.n_modes} modes, "
        f"{len(p.initial_omegas_rad_s)} initial frequencies, strategy {p.input_design.strategy}, "
        f"goal mu-bar < {p.goal.mu_target:g} within {p.goal.max_experiments} added experiments, seed {p.seed}",
        highlight=False,
    )
