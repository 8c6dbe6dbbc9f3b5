"""``setmem-hil run PROCEDURE.toml [--out DIR]`` and ``setmem-hil run --resume DIR``.

Runs a campaign (thesis Algorithm 5.1) from a procedure file with live progress, journaling
every measurement before the next dwell starts (``DIR/journal.sqlite``), and writes
``DIR/summary.json`` at the end. Ctrl-C (or SIGTERM) stops cleanly: the exciter is commanded
to zero, the journal is closed, the command prints how to resume and exits with 130. SIGKILL
or a power cut cannot be caught; the journal still holds every completed measurement.

``--resume DIR`` continues a stopped run exactly where it stopped: the procedure text, seed,
backend and strategy are read from the journal (never from the possibly edited file), and the
campaign replays the stored measurements instead of measuring them again.

Exit codes: 0 done (or already finished); 2 bad procedure or arguments; 3 data inconsistent
with the prior; 4 device fault (exciter at zero; resume once fixed); 130 interrupted.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

from rich.console import Console

from setmem_hil import __version__
from setmem_hil.errors import DeviceError, InputFormatError, SetmemError
from setmem_hil.io.journal import JOURNAL_FILENAME, Journal
from setmem_hil.io.procedure import STRATEGIES, Procedure
from setmem_hil.io.procedure_file import load_procedure, parse_procedure_text
from setmem_hil.cli.progress import CampaignProgress
from setmem_hil.io.result_file import write_json

__all__ = ["register", "run", "start_run", "resume_run", "default_run_dir", "RunOutcome", "open_backend"]

SUMMARY_FILENAME = "summary.json"
PROCEDURE_COPY = "procedure.toml"


@dataclass(frozen=True)
class RunOutcome:
    """What :func:`start_run` / :func:`resume_run` did."""

    run_dir: Path
    summary: dict
    already_finished: bool = False


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "run",
        help="run a campaign from a procedure file (or resume one)",
        description="Run a campaign (thesis Algorithm 5.1) from a procedure file with live progress, journaling every "
        "measurement in DIR/journal.sqlite; or continue a stopped run with --resume DIR. Ctrl-C stops cleanly "
        "(exciter to zero, journal closed, exit 130).",
        epilog="examples: setmem-hil run procedures/serial_loopback.toml --out runs/serial;  "
        "setmem-hil run --resume runs/serial;  setmem-hil run --check procedures/beam_6_3_2.toml",
    )
    p.add_argument("procedure", nargs="?", metavar="PROCEDURE.toml", help="procedure file (see docs/procedures.md)")
    p.add_argument("--out", metavar="DIR", help="run directory (default: runs/<name>-<UTC time>)")
    p.add_argument("--resume", metavar="DIR", help="continue the run stored in DIR")
    p.add_argument("--seed", type=int, help="override the procedure's seed (stored with the run)")
    p.add_argument("--strategy", choices=STRATEGIES, help="override the procedure's input-design strategy")
    p.add_argument("--check", action="store_true", help="validate the procedure and exit")
    p.add_argument("--report", action="store_true", help="write DIR/report.html when the run finishes")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def _arguments_error(problem: str) -> InputFormatError:
    return InputFormatError("setmem-hil run", "arguments", problem)


def run(args: argparse.Namespace) -> int:
    console = Console(stderr=False, quiet=bool(args.quiet), soft_wrap=True)
    if args.resume:
        if args.procedure or args.out or args.seed is not None or args.strategy or args.check:
            raise _arguments_error("--resume DIR takes no procedure, --out, --seed, --strategy or --check: the run's own are stored in its journal")
        outcome = resume_run(args.resume, console=console)
    else:
        if not args.procedure:
            raise _arguments_error("give a procedure file, or --resume DIR")
        procedure = load_procedure(args.procedure)
        if args.check:
            _describe(procedure, console)
            console.print(f"{args.procedure}: OK", highlight=False)
            return 0
        out = Path(args.out) if args.out else default_run_dir(procedure)
        outcome = start_run(procedure, out, seed=args.seed, strategy=args.strategy, console=console)
    if args.report:
        from setmem_hil.report.document import write_report

        path = write_report(outcome.run_dir)
        console.print(f"report: {path}", highlight=False)
    return 0


def default_run_dir(procedure: Procedure, now: datetime | None = None) -> Path:
    """``runs/<name>-<YYYYmmddTHHMMSSZ>`` (name made file-system safe)."""
    now = now or datetime.now(timezone.utc)
    safe = re.sub(r"[^A-Za-z0-9._-]+", "-", procedure.name).strip("-.") or "run"
    return Path("runs") / f"{safe}-{now.strftime('%Y%m%dT%H%M%SZ')}"


def _describe(procedure: Procedure, console: Console) -> None:
    p = procedure
    console.print(
        f"procedure {p.name!r}: backend {p.backend.kind}, {p.prior.n_modes} modes, "
        f"{len(p.initial_omegas_rad_s)} initial frequencies, strategy {p.input_design.strategy}, "
        f"goal mu-bar < {p.goal.mu_target:g} within {p.goal.max_experiments} added experiments, seed {p.seed}",
        highlight=False,
    )


def start_run(
    procedure: Procedure,
    run_dir: str | os.PathLike,
    *,
    seed: int | None = None,
    strategy: str | None = None,
    console: Console | None = None,
) -> RunOutcome:
    """Create ``run_dir`` with a new journal and run the campaign (see the module docstring).

    The procedure's text (``procedure.source_text``, or its :func:`format_procedure` rendering
    for a programmatic procedure) is stored in the journal with the seed, strategy, backend and
    software version, so the run can be resumed and reported later.
    """
    from setmem_hil.io.procedure_file import format_procedure

    console = console or Console()
    run_dir = Path(run_dir)
    seed = procedure.seed if seed is None else int(seed)
    if seed < 0:
        raise _arguments_error(f"--seed {seed} must be >= 0")
    strategy = strategy or procedure.input_design.strategy
    if strategy not in STRATEGIES:
        raise _arguments_error(f"strategy {strategy!r} is not one of {', '.join(STRATEGIES)}")
    text = procedure.source_text or format_procedure(procedure)
    if run_dir.exists() and not run_dir.is_dir():
        raise InputFormatError(str(run_dir), "", "exists and is not a directory")
    if (run_dir / JOURNAL_FILENAME).exists():
        raise InputFormatError(str(run_dir), "", f"already holds a run; continue it with `setmem-hil run --resume {run_dir}` or choose another --out")
    # Open the rig first: a transport option the driver rejects, or a device that does not
    # start, must not leave behind a journal whose stored procedure can never run.
    experiment = open_backend(procedure, seed)
    try:
        journal = Journal.create(
            run_dir / JOURNAL_FILENAME,
            procedure_text=text,
            procedure_name=procedure.name,
            seed=seed,
            software_version=__version__,
            backend=procedure.backend.kind,
            strategy=strategy,
        )
    except BaseException:
        experiment.close()
        raise
    with _run_lock(run_dir, journal):
        _write_text_atomically(run_dir / PROCEDURE_COPY, text)
        console.print(f"run directory: {run_dir}", highlight=False)
        _describe(procedure, console)
        return _run_with_journal(procedure, journal, run_dir, seed=seed, strategy=strategy, console=console, experiment=experiment)


def resume_run(run_dir: str | os.PathLike, *, console: Console | None = None) -> RunOutcome:
    """Continue the run in ``run_dir`` from its journal (REPLAY; see the module docstring)."""
    console = console or Console()
    run_dir = Path(run_dir)
    journal = Journal.open(run_dir)
    try:
        info = journal.run_info()
        source = f"{journal.path} (stored procedure)"
        if not info["procedure_text"].strip():
            raise InputFormatError(str(journal.path), "table run", "the journal holds no procedure text; this run cannot be resumed")
        procedure = parse_procedure_text(info["procedure_text"], source)
        if procedure.backend.kind != info["backend"]:
            raise InputFormatError(source, "[backend]", f"kind {procedure.backend.kind!r} differs from the run's backend {info['backend']!r}")
    except BaseException:
        journal.close()
        raise
    if info["finished"]:
        journal.close()
        summary = info["summary"] or {}
        if not (run_dir / SUMMARY_FILENAME).exists():
            write_json(_finite(summary), run_dir / SUMMARY_FILENAME)
        console.print(f"{run_dir}: the run is already finished; nothing to do", highlight=False)
        return RunOutcome(run_dir, summary, already_finished=True)
    if info["software_version"] != __version__:
        console.print(
            f"warning: the run was started with setmem-hil {info['software_version']}, this is {__version__}; "
            "the replay stops with an error if the loop now makes different choices",
            highlight=False,
        )
    with _run_lock(run_dir, journal):
        stored = journal.n_measurements()
        journal.add_event("resumed", f"resumed with {stored} stored measurements and {len(journal.iterations())} iterations (setmem-hil {__version__})")
        console.print(f"resuming {run_dir}: {stored} measurements stored, seed {info['seed']}, strategy {info['strategy']}", highlight=False)
        return _run_with_journal(procedure, journal, run_dir, seed=int(info["seed"]), strategy=str(info["strategy"]), console=console)


def open_backend(procedure: Procedure, seed: int) -> Any:
    """The procedure's experiment via :func:`setmem_hil.drivers.backends.open_experiment`."""
    try:
        from setmem_hil.drivers.backends import open_experiment
    except ModuleNotFoundError as exc:
        if exc.name not in ("setmem_hil.drivers.backends",):
            raise
        if procedure.backend.kind != "sim":
            raise InputFormatError(procedure.source_path or procedure.name, "[backend]",
                                   f"kind {procedure.backend.kind!r}: transport backends are not available in this installation") from None
        from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

        sim = procedure.backend.simulation
        return SimulatedBeamExperiment(
            noise_profile=sim.noise_profile, seed=seed, unmodelled_dynamics=sim.unmodelled_dynamics,
            n_modelled=procedure.prior.n_modes, noise_scale=sim.noise_scale,
            w1_num=procedure.weights.w1_num, w1_den=procedure.weights.w1_den,
        )
    return open_experiment(procedure, seed)


class _CounterLogger:
    """Logs changes of the experiment's fault/retry counters to the journal as events."""

    def __init__(self, experiment: Any, journal: Journal):
        self.experiment, self.journal = experiment, journal
        self.seen = dict(getattr(experiment, "counters", {}) or {})

    def __call__(self, event: str, **info: Any) -> None:
        counters = getattr(self.experiment, "counters", None)
        if not isinstance(counters, dict):
            return
        for key, value in counters.items():
            delta = int(value) - int(self.seen.get(key, 0))
            if delta > 0:
                self.journal.add_event(str(key), f"{delta} x {key} (total {value}) before event {event!r}")
        self.seen = dict(counters)


class _DiscrepancyChecker:
    """``[discrepancy] check_each_iteration``: after each stored iteration, run the discrepancy
    workflow (:func:`setmem_hil.discrepancy.workflow.check_discrepancy`) on the data used and the bounds
    identified, and journal the result. It only observes: the campaign's choices do not depend
    on it, so a replayed run is unchanged; iterations already checked are not checked again."""

    def __init__(self, procedure: Procedure, journal: Journal):
        self.procedure, self.journal = procedure, journal
        self.done = {k for k, _ in journal.discrepancies()}

    def __call__(self, event: str, **info: Any) -> None:
        if event not in ("chosen", "finished"):  # the iteration record is stored by then
            return
        from setmem_hil.discrepancy.workflow import check_discrepancy
        from setmem_hil.model.frequency_data import FrequencyData
        from setmem_hil.model.modal_model import IntervalModel

        measurements = None
        for rec in self.journal.iterations():
            if rec.k in self.done:
                continue
            measurements = measurements or self.journal.measurements()
            data = FrequencyData.from_measurements(measurements[: rec.n_points])
            try:
                report = check_discrepancy(data, IntervalModel(rec.lower, rec.upper), self.procedure.prior).to_document()
            except (SetmemError, ValueError, ArithmeticError) as exc:  # a failed check must not stop the campaign
                self.journal.add_event("discrepancy-error", f"iteration {rec.k}: {type(exc).__name__}: {exc}")
            else:
                self.journal.add_discrepancy(rec.k, report)
            self.done.add(rec.k)


def _observers(*fns):
    def call(event: str, **info: Any) -> None:
        for fn in fns:
            fn(event, **info)

    return call


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Ignore Ctrl-C and SIGTERM while shutting down, so a second one cannot skip the exciter stop."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    previous_term = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)


class _Terminated(KeyboardInterrupt):
    """SIGTERM (``kill PID``, a service manager stopping us): handled exactly like Ctrl-C."""


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """Turn SIGTERM into an interrupt for the duration of the campaign, so the exciter is
    zeroed and the journal closed (the default action would end the process on the spot)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise _Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


LOCK_FILENAME = ".run.lock"


@contextmanager
def _run_lock(run_dir: Path, journal: Journal) -> Iterator[None]:
    """One process at a time per run directory: two resumes of the same run would both append
    the measurements after the stored ones. POSIX advisory lock, released when the process ends
    (also on SIGKILL); where ``fcntl`` is missing there is no lock."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover (not POSIX)
        yield
        return
    fh = open(run_dir / LOCK_FILENAME, "a+")
    try:
        try:
            fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            journal.close()
            raise InputFormatError(str(run_dir), "", "another setmem-hil process is running this campaign; wait for it or stop it first") from None
        yield
    finally:
        fh.close()


def _run_with_journal(procedure: Procedure, journal: Journal, run_dir: Path, *, seed: int, strategy: str, console: Console,
                      experiment: Any = None) -> RunOutcome:
    with _sigterm_as_interrupt():
        return _run_campaign_in(procedure, journal, run_dir, seed=seed, strategy=strategy, console=console, experiment=experiment)


def _run_campaign_in(procedure: Procedure, journal: Journal, run_dir: Path, *, seed: int, strategy: str, console: Console,
                     experiment: Any = None) -> RunOutcome:
    from setmem_hil.campaign.runner import run_campaign

    try:
        if experiment is None:
            experiment = open_backend(procedure, seed)
        planned = None
        if callable(getattr(experiment, "plan", None)):
            def planned(w: float, _e=experiment) -> float:
                plan = _e.plan(w)
                return float(plan.skip_s + plan.window_s)
        observers = [_CounterLogger(experiment, journal)]
        if procedure.discrepancy_check:
            observers.append(_DiscrepancyChecker(procedure, journal))
        with CampaignProgress(console, planned_dwell_s=planned, on_event=_observers(*observers)) as progress:
            summary = run_campaign(procedure, experiment, journal, seed=seed, strategy=strategy, progress=progress)
        doc = summary.to_document()
    except KeyboardInterrupt as exc:
        why = "SIGTERM: stopped by a signal" if isinstance(exc, _Terminated) else "Ctrl-C: stopped by the operator"
        with _sigint_deferred():
            _shutdown(experiment, journal, "interrupted", why)
        print(f"setmem-hil: stopped; {_stored(journal)} measurements are in the journal. Continue with:\n"
              f"    setmem-hil run --resume {run_dir}", file=sys.stderr)
        raise
    except DeviceError as exc:
        with _sigint_deferred():
            _shutdown(experiment, journal, "device-fault", str(exc))
        print(f"setmem-hil: after fixing the rig, continue with: setmem-hil run --resume {run_dir}", file=sys.stderr)
        raise
    except BaseException as exc:
        with _sigint_deferred():
            _shutdown(experiment, journal, "error", f"{type(exc).__name__}: {exc}")
        raise
    with _sigint_deferred():
        _shutdown(experiment, journal, None, "")
    write_json(_finite(doc), run_dir / SUMMARY_FILENAME)
    console.print(f"summary: {run_dir / SUMMARY_FILENAME}", highlight=False)
    console.print(f"report:  setmem-hil report {run_dir}", highlight=False)
    return RunOutcome(run_dir, doc)


def _stored(journal: Journal) -> str:
    try:
        j = Journal.open(journal.path)
        try:
            return str(j.n_measurements())
        finally:
            j.close()
    except SetmemError:
        return "all completed"


def _shutdown(experiment: Any, journal: Journal, kind: str | None, message: str) -> None:
    """Exciter to zero first, then record why we stopped, then close the journal."""
    try:
        if experiment is not None:
            experiment.close()
    finally:
        try:
            if kind is not None and not journal.closed:
                journal.add_event(kind, message)
        finally:
            journal.close()


def _finite(obj: Any) -> Any:
    """JSON-safe copy: non-finite floats (an unstable nominal loop's mu-bar) become None."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        return _finite(obj.item())
    return obj


def _write_text_atomically(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
