"""One campaign of a sweep, as a Dask task (see :mod:`setmem_hil.sweep.runner`).

:func:`sweep_campaign` is a picklable top-level function of plain data (procedure, seed,
strategy, output directory): it runs thesis Algorithm 5.1 (:func:`setmem_hil.campaign.runner.run_campaign`)
on the simulated beam with single-threaded BLAS and stores the result with
:mod:`setmem_hil.sweep.storage`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import socket
from pathlib import Path

from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import Procedure
from setmem_hil.sweep.storage import (
    ERROR_NAME,
    JOURNAL_NAME,
    RUNS_DIRNAME,
    SUMMARY_NAME,
    error_document,
    error_record,
    install_run,
    new_partial_dir,
    procedure_fingerprint,
    run_name,
    run_record,
    write_json_atomic,
)


def check_sweep_procedure(procedure: Procedure) -> None:
    """Sweeps run on the simulated backend only.

    Raises
    ------
    ProcedureError
        When ``[backend] kind`` is not ``"sim"``.
    """
    if procedure.backend.kind != "sim":
        raise ProcedureError(
            procedure.source_path or procedure.name, "[backend] kind",
            f"a sweep runs campaigns on the simulated backend (kind = \"sim\"), found {procedure.backend.kind!r}",
        )


def open_sim_experiment(procedure: Procedure, seed: int):
    """The simulated experiment of ``procedure`` with noise seed ``seed``.

    :func:`setmem_hil.experiment_factory.open_experiment`, so a sweep campaign equals
    ``setmem-hil run`` with the same procedure and seed.
    """
    check_sweep_procedure(procedure)
    from setmem_hil.experiment_factory import open_experiment  # noqa: F811

    return open_experiment(procedure, int(seed))


def sweep_campaign(procedure: Procedure, seed: int, strategy: str, out_dir: str, design: str | None = None) -> dict:
    """Run one campaign of a sweep and store it in ``out_dir/runs/<strategy>-seed<N>`` (the Dask task;
    ``<strategy>-<design>-seed<N>`` with ``design``, the compensator design of a sweep over designs).

    Algorithm 5.1 (:func:`setmem_hil.campaign.journaled_run.run_journaled_campaign`: the runner with the
    same subscribers as ``setmem-hil run``) on the simulated experiment with
    noise seed ``seed``, input choice ``strategy`` (eq. 5.3 for ``"mu"``) and single-threaded
    BLAS. Skips a run whose ``summary.json`` exists. Writes into a temporary directory that is
    renamed into place when done (:mod:`setmem_hil.sweep.storage`).

    Parameters
    ----------
    procedure : Procedure
        Everything but the seed (``procedure.seed`` is replaced by ``seed``).
    seed : int
        Noise seed of the simulated beam and of the ``"random"`` baseline.
    strategy : str
        One of :data:`setmem_hil.io.procedure.STRATEGIES`.
    out_dir : str
        The sweep directory (absolute path, visible to the worker).
    design : str, optional
        ``"h2"`` or ``"robust"`` instead of the procedure's ``[design] method`` (named in the run).

    Returns
    -------
    dict
        The ``sweep.json`` row (:func:`run_record` or :func:`error_record`) plus ``"status"``:
        ``"done"``, ``"skipped"`` or ``"failed"``. Exceptions of the campaign are caught and
        recorded in ``error.json``; only ``KeyboardInterrupt`` / ``SystemExit`` propagate (the
        partial directory is then removed).
    """
    from setmem_hil import __version__
    from setmem_hil.run.engine import NOTE
    from setmem_hil.campaign.journaled_run import run_journaled_campaign
    from setmem_hil.campaign.persistence import JournalWriter
    from setmem_hil.numerics.blas_threads import blas_one_thread

    seed = int(seed)
    runs_dir = Path(out_dir) / RUNS_DIRNAME
    final = runs_dir / run_name(strategy, seed, design)
    done_file = final / SUMMARY_NAME
    if done_file.is_file():
        summary = json.loads(done_file.read_text(encoding="utf-8"))
        return {**run_record(seed, strategy, summary, design), "status": "skipped"}
    tmp = new_partial_dir(runs_dir, final.name)
    store = None
    try:
        proc = dataclasses.replace(procedure, seed=seed)
        fingerprint = procedure_fingerprint(proc)  # the sweep's procedure: every design of it shares the fingerprint
        if design is not None:
            proc = dataclasses.replace(proc, design_method=design)
        store = JournalWriter(tmp / JOURNAL_NAME)  # the journal is made from the run's start document
        store(NOTE, kind="sweep", message=f"sweep campaign {final.name}: goal mu-bar < {proc.goal.mu_target:g}, "
                                   f"at most {proc.goal.max_experiments} added experiments, "
                                   f"procedure fingerprint {fingerprint[:16]}, "
                                   f"host {socket.gethostname()} pid {os.getpid()}")
        with blas_one_thread():
            experiment = open_sim_experiment(proc, seed)
            try:
                # the same runner and subscribers as `setmem-hil run` (e.g. [discrepancy] checks)
                result = run_journaled_campaign(proc, experiment, store, seed=seed, strategy=strategy)
            finally:
                experiment.close()
        store.close()
        doc = result.to_document()
        doc["sweep"] = {"procedure_fingerprint": fingerprint, "procedure_name": proc.name,
                        "seed": seed, "strategy": strategy, "design": proc.design_method, "host": socket.gethostname(),
                        "pid": os.getpid(), "software_version": __version__}
        write_json_atomic(doc, tmp / SUMMARY_NAME)
        install_run(tmp, final)
        return {**run_record(seed, strategy, doc, design), "status": "done"}
    except Exception as exc:  # recorded, not fatal to the sweep (issue 9, item 3)
        err = error_document(seed, strategy, exc, f"{socket.gethostname()} pid {os.getpid()}")
        if store is not None:
            with contextlib.suppress(Exception):
                store(NOTE, kind="error", message=err["error"])
            with contextlib.suppress(Exception):
                store.close()
        write_json_atomic(err, tmp / ERROR_NAME)
        install_run(tmp, final)
        return {**error_record(seed, strategy, err["error"], design), "status": "failed"}
    except BaseException:
        if store is not None:
            with contextlib.suppress(Exception):
                store.close()
        shutil.rmtree(tmp, ignore_errors=True)
        raise


__all__ = ["check_sweep_procedure", "open_sim_experiment", "sweep_campaign"]
