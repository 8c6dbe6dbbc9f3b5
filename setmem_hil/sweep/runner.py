"""Sweeps: many Algorithm 5.1 campaigns over seeds x input-design strategies, on Dask.

Engineers compare input-design strategies (the thesis's mu-based design of eq. 5.3 and the
baselines of :mod:`setmem_hil.design.strategies`), noise levels and rigs over many seeds before booking
a real rig: the figure of merit is the number of added experiments until mu-bar < 1 (the stopping
rule of Algorithm 5.1, step 4; thesis section 6.3). One campaign is a few seconds on the
simulated backend; a study is hundreds to thousands of them.

Execution
    Every (seed, strategy) campaign is one task, the top-level function :func:`sweep_campaign`
    taking plain data (a :class:`~setmem_hil.io.procedure.Procedure`, the seed, the strategy and the
    output directory), so it runs unchanged in this process (``serial=True``), on an embedded
    ``dask.distributed.LocalCluster`` (worker processes bound to 127.0.0.1, one thread each) or on
    a remote ``dask scheduler`` (``scheduler="tcp://HOST:PORT"``). Remote workers must import
    ``setmem_hil`` and see ``out_dir`` at the same path (a shared filesystem).

Storage (``DIR/runs/<strategy>-seed<N>/``)
    A campaign writes its journal and ``summary.json`` into a fresh directory under
    ``DIR/runs/.partial/`` and renames it into place when finished, so a killed sweep never leaves
    a half run that looks done. A run is done when its ``summary.json`` exists; re-running the
    sweep with the same arguments skips it. A campaign that raises leaves ``error.json`` (type,
    message, traceback) beside its partial journal instead and does not stop the sweep; the next
    run of the sweep retries it. ``summary.json`` carries the procedure's fingerprint: a re-run
    with a different procedure or goal into the same ``DIR`` is refused rather than mixed.

Determinism
    Nothing in a campaign depends on a global RNG or the wall clock (the simulated noise of the
    n-th measurement derives from (seed, n), the random baseline from (seed, k)), and every task
    runs with single-threaded BLAS (:func:`setmem_hil.numerics.blas_threads.blas_one_thread`): multithreaded
    BLAS changes reduction orders and hence the last digits of mu-bar (we measured 2e-5 on the 6.3.2
    campaign), which could flip a close input choice. So a (seed, strategy) campaign takes the
    same measurements and choices serially, on the local cluster and on remote workers.

Modules
    :mod:`setmem_hil.sweep.task` (the task), :mod:`setmem_hil.sweep.storage` (layout, atomic
    install, skip-done planning), :mod:`setmem_hil.sweep.summary` (statistics, table),
    :mod:`setmem_hil.sweep.plot` (figure); this module parses the arguments and orchestrates.

Results
    ``DIR/sweep.json`` = ``{"runs": [...], "summary": {strategy: {...}}, ...}`` (see
    :func:`summarize_runs`) and ``DIR/sweep.png`` (:mod:`setmem_hil.sweep.plot`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from setmem_hil.run.run_directory import directory_lock
from setmem_hil.errors import InputFormatError
from setmem_hil.os_support import kill_process
from setmem_hil.io.procedure import DESIGN_METHODS, STRATEGIES, Procedure
from setmem_hil.sweep.storage import (
    clean_partials,
    error_record,
    plan_runs,
    procedure_fingerprint,
    read_run,
    record_failure,
    run_name,
    run_record,
    write_json_atomic,
)
from setmem_hil.sweep.summary import format_summary_table, summarize_runs
from setmem_hil.sweep.task import check_sweep_procedure, open_sim_experiment, sweep_campaign

LOCK_NAME = ".sweep.lock"
THREAD_ENV_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
WORKER_WAIT_S = 60.0
"""How long to wait for workers to connect to a remote scheduler."""
CONNECT_TIMEOUT_S = 30.0
"""How long to try to reach a remote scheduler."""

TaskFn = Callable[[Procedure, int, str, str], dict]
ProgressFn = Callable[[int, int, int, dict], None]


# ---------------------------------------------------------------------------- arguments
def parse_seeds(text: str) -> tuple[int, ...]:
    """Seeds from ``"A-B"`` (inclusive), ``"N"`` or a comma list of those (``"1-5,9"``).

    Raises
    ------
    InputFormatError
        Naming ``--seeds`` and the offending part.
    """
    seeds: list[int] = []
    parts = [p.strip() for p in str(text).split(",")]
    for part in parts:
        if not part:
            raise InputFormatError("--seeds", "", f"expected A-B, N or a comma list of those, found {text!r}")
        lo_text, sep, hi_text = part.partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if sep else lo
        except ValueError:
            raise InputFormatError("--seeds", "", f"expected integers in A-B, found {part!r}") from None
        if lo < 0 or hi < lo:
            raise InputFormatError("--seeds", "", f"expected 0 <= A <= B in A-B, found {part!r}")
        seeds.extend(range(lo, hi + 1))
    if len(set(seeds)) != len(seeds):
        raise InputFormatError("--seeds", "", f"a seed appears twice in {text!r}")
    return tuple(seeds)


def parse_strategies(text: str | Sequence[str]) -> tuple[str, ...]:
    """Strategies from ``"mu,log-sweep"`` (or a sequence); each must be in ``STRATEGIES``.

    Raises
    ------
    InputFormatError
        Naming ``--strategies``, the unknown name and the allowed ones.
    """
    return _parse_names(text, "--strategies", STRATEGIES, "strategy")


def parse_designs(text: str | Sequence[str]) -> tuple[str, ...]:
    """Compensator designs from ``"h2,robust"`` (or a sequence); each must be in ``DESIGN_METHODS``.

    Raises
    ------
    InputFormatError
        Naming ``--designs``, the unknown name and the allowed ones.
    """
    return _parse_names(text, "--designs", DESIGN_METHODS, "design")


def _parse_names(text: str | Sequence[str], option: str, allowed: Sequence[str], what: str) -> tuple[str, ...]:
    """A comma list (or a sequence) of names from ``allowed``, each once."""
    items = [s.strip() for s in (text.split(",") if isinstance(text, str) else text)]
    if not items or any(not s for s in items):
        raise InputFormatError(option, "", f"expected a comma list of {', '.join(allowed)}, found {text!r}")
    for s in items:
        if s not in allowed:
            raise InputFormatError(option, "", f"expected one of {', '.join(allowed)}, found {s!r}")
    if len(set(items)) != len(items):
        raise InputFormatError(option, "", f"a {what} appears twice in {text!r}")
    return tuple(items)


# ---------------------------------------------------------------------------- orchestration
@dataclass(frozen=True)
class SweepResult:
    """Outcome of :func:`run_sweep`.

    Attributes
    ----------
    out_dir : Path
    runs : tuple of dict
        ``sweep.json`` rows, seed-major in the order of ``seeds`` then ``strategies``.
    summary : dict
        :func:`summarize_runs`.
    executed, skipped, failed : tuple of str
        Run names (``<strategy>-seed<N>``) run by this invocation, found done on disk, and that
        failed in this invocation.
    wall_s : float
        Wall time of this invocation (planning, cluster start, campaigns, summary, plot).
    mode : str
        ``"serial"``, ``"local"`` or ``"remote"``.
    """

    out_dir: Path
    runs: tuple[dict, ...]
    summary: dict
    executed: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: tuple[str, ...]
    wall_s: float
    mode: str
    document: dict


def _sweep_lock(out_dir: Path):
    """One sweep per directory at a time (``flock``; released by the OS when the process dies)."""
    return directory_lock(out_dir, LOCK_NAME, "another sweep is writing this directory")


class _RichProgress:
    """Rich progress bar on stderr: campaigns done / total and failures."""

    def __init__(self, total: int, done: int, description: str):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

        self.console = Console(stderr=True, soft_wrap=True)
        self.progress = Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
            TextColumn("campaigns, [red]{task.fields[failures]} failed"), TimeElapsedColumn(), TimeRemainingColumn(),
            console=self.console, transient=False,
        )
        self.progress.start()
        self.task = self.progress.add_task(description, total=total, completed=done, failures=0)

    def __call__(self, done: int, total: int, failures: int, record: dict) -> None:
        if record.get("status") == "failed":
            self.progress.console.print(f"[red]campaign {run_name(record['strategy'], record['seed'])} failed:[/] {record['error']}")
        self.progress.update(self.task, completed=done, failures=failures)

    def close(self) -> None:
        self.progress.stop()


def worker_environment() -> dict[str, str]:
    """Environment of the sweep's worker processes: one BLAS/OpenMP thread each, nothing else.

    Dask's nanny also sets ``MALLOC_TRIM_THRESHOLD_=65536`` by default (its
    ``distributed.nanny.pre-spawn-environ``). Setting it makes glibc serve every allocation
    above 128 kB with a fresh ``mmap``; the campaign loop allocates many such arrays and ran 1.5x
    slower in CPU time (measured: 2.75 s vs 1.8 s per campaign), so the sweep's workers do without it.
    Remote ``dask worker`` processes should be started with the same environment, e.g.
    ``DASK_DISTRIBUTED__NANNY__PRE_SPAWN_ENVIRON='{"OMP_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1,
    "MKL_NUM_THREADS": 1}'`` (the results are the same either way; only the speed differs).
    """
    return {v: "1" for v in THREAD_ENV_VARS}


def _start_local_cluster(workers: int | None):
    """Embedded ``LocalCluster``: worker processes on 127.0.0.1, one thread each, no dashboard."""
    import dask
    from distributed import LocalCluster

    n = int(workers) if workers else (os.cpu_count() or 1)
    # The worker's statistical profiler samples the task thread every 10 ms and competes for the
    # GIL with the Python-heavy campaign loop; campaigns need no profile. Spawned workers inherit
    # this configuration.
    config = {"distributed.worker.profile.enabled": False,
              "distributed.nanny.pre-spawn-environ": worker_environment()}
    with dask.config.set(config):
        return LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
            silence_logs=logging.CRITICAL, env=worker_environment(),
        )


def run_sweep(
    procedure: Procedure,
    seeds: Sequence[int],
    strategies: Sequence[str],
    out_dir: str | os.PathLike,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    serial: bool = False,
    task: TaskFn = sweep_campaign,
    progress: bool | ProgressFn = False,
    plot: bool = True,
    designs: Sequence[str] | None = None,
) -> SweepResult:
    """Run every (seed, strategy, design) campaign not yet done in ``out_dir`` and write the summary.

    Parameters
    ----------
    procedure : Procedure
        The campaign (backend kind ``"sim"``); its seed is replaced per campaign.
    seeds, strategies : sequences
        The grid; see :func:`parse_seeds`, :func:`parse_strategies`.
    out_dir : path
        Sweep directory; created if missing. Must be on a filesystem the workers share.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running ``dask scheduler``; default: an embedded
        ``LocalCluster`` (processes on 127.0.0.1, one thread each).
    workers : int, optional
        Local cluster: number of worker processes (default: CPU count). Remote scheduler: wait
        until this many workers are connected (default 1) before submitting.
    serial : bool
        Run the campaigns one after the other in this process (no Dask).
    task : callable
        ``task(procedure, seed, strategy, out_dir) -> dict``, a picklable top-level function
        (default :func:`sweep_campaign`); replaceable for tests.
    progress : bool or callable
        ``True``: rich progress bar on stderr; a callable gets ``(done, total, failures, record)``
        after each campaign.
    plot : bool
        Write ``sweep.png``.
    designs : sequence of str, optional
        The compensator designs to compare (``"h2"``, ``"robust"``), a third axis of the grid;
        default: the procedure's ``[design] method`` alone (runs named as before). With any
        other list each run is named ``<strategy>-<design>-seed<N>`` and ``sweep.json``'s
        ``summary`` is keyed ``<strategy>-<design>`` (``by_design`` holds each design's
        per-strategy summary).

    Returns
    -------
    SweepResult

    Raises
    ------
    InputFormatError
        Bad arguments, a finished run in ``out_dir`` from another procedure, or another sweep
        writing ``out_dir``.
    ProcedureError
        The procedure's backend is not ``"sim"``.
    TimeoutError
        The remote scheduler cannot be reached within ``CONNECT_TIMEOUT_S``, or fewer than
        ``workers`` workers connected to it within ``WORKER_WAIT_S``.
    KeyboardInterrupt
        Propagates after cancelling the tasks and closing the cluster; finished campaigns stay.

    Examples
    --------
    >>> from setmem_hil.io.procedure_file import load_procedure
    >>> result = run_sweep(load_procedure("procedures/beam_6_3_2.toml"), range(1, 11),
    ...                    ["mu", "random"], "study", workers=2)  # doctest: +SKIP
    >>> result.summary["mu"]["median_experiments"]  # doctest: +SKIP
    6.0
    """
    t0 = time.perf_counter()
    check_sweep_procedure(procedure)
    seeds = tuple(int(s) for s in seeds)
    strategies = parse_strategies(strategies)
    designs = parse_designs(designs or (procedure.design_method,))
    named = None if designs == (procedure.design_method,) else designs  # the run names carry the design
    if not seeds:
        raise InputFormatError("--seeds", "", "no seeds given")
    if workers is not None and int(workers) < 1:
        raise InputFormatError("--workers", "", f"expected >= 1, found {workers}")
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    mode = "serial" if serial else ("remote" if scheduler else "local")
    executed: list[str] = []
    failed: list[str] = []
    with _sweep_lock(out):
        pending, done = plan_runs(procedure, seeds, strategies, out, named or (None,))
        clean_partials(out)
        total = len(seeds) * len(strategies) * len(designs)
        bar: _RichProgress | None = None
        if progress is True:
            bar = _RichProgress(total, len(done), f"sweep {procedure.name} ({mode})")
            report: ProgressFn | None = bar
        else:
            report = progress or None
        n_done, n_failed = len(done), 0

        def finished(rec: dict) -> None:
            nonlocal n_done, n_failed
            n_done += 1
            name = run_name(rec["strategy"], rec["seed"], rec.get("design"))
            if rec.get("status") != "skipped":
                executed.append(name)
            if rec.get("status") == "failed":
                n_failed += 1
                failed.append(name)
            if report is not None:
                report(n_done, total, n_failed, rec)

        try:
            if pending and serial:
                for seed, strategy, design in pending:
                    try:
                        rec = task(procedure, seed, strategy, str(out), *(() if design is None else (design,)))
                    except Exception as exc:
                        rec = record_failure(out, seed, strategy, exc, "sweep (serial)", design)
                    finished(rec)
            elif pending:
                _run_on_dask(procedure, pending, out, scheduler, workers, task, finished)
        finally:
            if bar is not None:
                bar.close()

    document = _sweep_document(procedure, seeds, strategies, designs, named, out)
    runs, summary = document["runs"], document["summary"]
    write_json_atomic(document, out / "sweep.json")
    if plot:
        from setmem_hil.sweep.plot import plot_experiments_to_goal

        plot_experiments_to_goal(document, out / "sweep.png")
    return SweepResult(out_dir=out, runs=tuple(runs), summary=summary, executed=tuple(executed),
                       skipped=tuple(run_name(st, s, d) for s, st, d in done), failed=tuple(failed),
                       wall_s=time.perf_counter() - t0, mode=mode, document=document)


def _sweep_document(procedure: Procedure, seeds, strategies, designs, named, out: Path) -> dict:
    """``sweep.json``: every run's row (its design named), the summary per strategy (per
    ``<strategy>-<design>`` over several designs) and per design."""
    runs = []
    for seed in seeds:
        for strategy in strategies:
            for design in named or (None,):
                rec = read_run(out, seed, strategy, design)
                rec = rec if rec is not None else error_record(seed, strategy, "not run", design)
                runs.append({**rec, "design": design or procedure.design_method})
    lanes = [s if named is None else f"{s}-{d}" for s in strategies for d in designs]
    summary = summarize_runs(runs, lanes, key=lambda r: r["strategy"] if named is None else f"{r['strategy']}-{r['design']}")
    return {
        "runs": runs,
        "summary": summary,
        "by_design": {d: summarize_runs([r for r in runs if r["design"] == d], strategies) for d in designs},
        "procedure": procedure.name,
        "procedure_fingerprint": procedure_fingerprint(procedure),
        "seeds": list(seeds),
        "strategies": list(strategies),
        "designs": list(designs),
        "lanes": lanes,
        "goal": {"mu_target": float(procedure.goal.mu_target), "max_experiments": int(procedure.goal.max_experiments)},
        "failures": sum(1 for r in runs if r.get("error")),
    }


def _prepare_local_worker() -> int:
    """Run on each local worker process (in its main thread): leave Ctrl-C to the sweep process.

    A terminal's Ctrl-C reaches the whole process group. A worker would otherwise print a
    traceback and then linger until its running campaign ends; instead the sweep process stops
    its workers at once (:func:`_run_on_dask`). Returns the worker's pid.
    """
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    return os.getpid()


def _run_on_dask(procedure: Procedure, pending: list[tuple[int, str, str | None]], out: Path, scheduler: str | None,
                 workers: int | None, task: TaskFn, finished: Callable[[dict], None]) -> None:
    """Submit the pending campaigns and collect them as they complete."""
    from distributed import Client, as_completed

    cluster = None
    client = None
    futures: dict = {}
    local_pids: list[int] = []
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except (OSError, TimeoutError) as exc:
                raise TimeoutError(f"--scheduler {scheduler}: cannot reach the scheduler within "
                                   f"{CONNECT_TIMEOUT_S:g} s ({exc})") from None
            want = int(workers) if workers else 1
            try:
                client.wait_for_workers(n_workers=want, timeout=WORKER_WAIT_S)
            except (TimeoutError, OSError) as exc:
                raise TimeoutError(f"--scheduler {scheduler}: fewer than {want} worker(s) connected within "
                                   f"{WORKER_WAIT_S:g} s ({exc})") from None
        else:
            cluster = _start_local_cluster(workers)
            client = Client(cluster)
            local_pids = [int(pid) for pid in client.run(_prepare_local_worker).values()]
        for seed, strategy, design in pending:
            fut = client.submit(task, procedure, seed, strategy, str(out), *(() if design is None else (design,)), pure=False)
            futures[fut] = (seed, strategy, design)
        for fut in as_completed(list(futures)):
            seed, strategy, design = futures[fut]
            try:
                rec = fut.result()
            except Exception as exc:  # the task itself failed (worker died, unpicklable, ...)
                rec = record_failure(out, seed, strategy, exc, f"dask ({scheduler or 'local cluster'})", design)
            finished(rec)
            fut.release()
    except KeyboardInterrupt:
        # Stop our own workers now rather than after their running campaigns: what they were
        # writing is under runs/.partial and is discarded by the next run of the sweep.
        for pid in local_pids:
            with contextlib.suppress(OSError):
                kill_process(pid)
        raise
    finally:
        if client is not None:
            with contextlib.suppress(Exception):
                client.cancel(list(futures))
            with contextlib.suppress(Exception):
                client.close()
        if cluster is not None:
            with contextlib.suppress(Exception):
                cluster.close()


__all__ = [
    "SweepResult",
    "check_sweep_procedure",
    "error_record",
    "format_summary_table",
    "open_sim_experiment",
    "parse_designs",
    "parse_seeds",
    "parse_strategies",
    "procedure_fingerprint",
    "read_run",
    "record_failure",
    "run_name",
    "run_record",
    "run_sweep",
    "summarize_runs",
    "sweep_campaign",
    "write_json_atomic",
]
