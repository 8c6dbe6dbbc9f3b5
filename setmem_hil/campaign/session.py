"""The application layer of a campaign run: directories, journal, lock, signals, resume.

:func:`start_run` creates a run directory with a new journal and runs the campaign;
:func:`resume_run` continues a stopped one from its journal (REPLAY, see
:mod:`setmem_hil.campaign.runner`). Both go through :func:`run_journaled_campaign`, the one way
a journaled campaign is run (also by the sweep task), so every procedure setting means the same
everywhere: the runner plus the standard subscribers of :mod:`setmem_hil.campaign.observers`
plus whatever display the caller adds (terminal progress, live view).

Ctrl-C (or SIGTERM) stops cleanly: the exciter is commanded to zero, the journal is closed, the
message says how to resume, and ``KeyboardInterrupt`` propagates (exit 130 in the CLI). SIGKILL
or a power cut cannot be caught; the journal still holds every completed measurement.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import sys
import threading
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, ContextManager, Iterator, Sequence

from rich.console import Console

from setmem_hil import __version__, os_support
from setmem_hil.campaign.observers import Observer, broadcast, standard_observers
from setmem_hil.campaign.runner import CampaignSummary, run_campaign
from setmem_hil.errors import CampaignAborted, DeviceError, InconsistentDataError, InputFormatError, RunInterrupted, SetmemError
from setmem_hil.io.atomic_file import write_json_atomic, write_text_atomic
from setmem_hil.io.journal import JOURNAL_FILENAME, Journal
from setmem_hil.io.procedure import DESIGN_METHODS, STRATEGIES, Procedure
from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text

__all__ = [
    "RunOutcome", "start_run", "resume_run", "run_journaled_campaign", "default_run_dir", "describe_procedure",
    "directory_lock", "preflight", "SUMMARY_FILENAME", "PROCEDURE_COPY", "Display",
]

SUMMARY_FILENAME = "summary.json"
PROCEDURE_COPY = "procedure.toml"
LOCK_FILENAME = ".run.lock"

Display = Callable[[Any], ContextManager[Observer]]
"""``display(experiment)``: a context manager yielding an observer that shows the campaign."""

ExperimentOpener = Callable[[Procedure, int], Any]


@dataclass(frozen=True)
class RunOutcome:
    """What :func:`start_run` / :func:`resume_run` did."""

    run_dir: Path
    summary: dict
    already_finished: bool = False


def _arguments_error(problem: str) -> InputFormatError:
    return InputFormatError("setmem-hil run", "arguments", problem)


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
def _run_lock(run_dir: Path, journal: Journal) -> Iterator[None]:
    """Two resumes of the same run would both append after the stored measurements."""
    try:
        with directory_lock(run_dir, LOCK_FILENAME, "another setmem-hil process is running this campaign; wait for it or stop it first"):
            yield
    except InputFormatError:
        if not journal.closed:
            journal.close()
        raise


def preflight(procedure: Procedure) -> None:
    """Every check a run makes before its first dwell that does not need the rig (``run --check``).

    The procedure file is validated when it is loaded (schema, keys, transport options, safety
    limits); this adds what depends on the prior and the initial design together: the residues of
    modes without ``b0`` bounds must be boundable from measurements at the ``[initial]``
    frequencies (the residue bootstrap's coupling depends on the frequencies and the prior's poles
    only, so it is decided before measuring), else the campaign would measure every initial point
    and then stop.
    """
    import numpy as np

    from setmem_hil.identification.residue_bootstrap import bootstrap_residue_bounds
    from setmem_hil.model.frequency_data import FrequencyData

    source = procedure.source_path or procedure.name
    if procedure.backend.kind == "instruments":  # every profile loads and fits its role
        from setmem_hil.drivers.instruments.instrument_set import check_instruments

        check_instruments(procedure)
    modes = procedure.prior.modes
    w = np.asarray(procedure.initial_omegas_rad_s, dtype=float)
    probe = FrequencyData(w, np.zeros(w.size, complex), np.zeros(w.size))
    try:
        bootstrap_residue_bounds(probe, procedure.prior.initial_bounds())
    except InputFormatError as exc:
        overlaps = [f"[[mode]] {i} and {i + 1} ({modes[i - 1].omega_min:g}-{modes[i - 1].omega_max:g} and "
                    f"{modes[i].omega_min:g}-{modes[i].omega_max:g} rad/s)"
                    for i in range(1, len(modes)) if modes[i].omega_min < modes[i - 1].omega_max]
        cause = f"; the bands of {', '.join(overlaps)} overlap" if overlaps else ""
        cause += _looks_like_hz(w, [(m.omega_min, m.omega_max) for m in modes])
        import re

        coupling = re.search(r"mode coupling [^)]*", exc.problem)
        raise InputFormatError(source, "[[mode]] / [initial]",
                               f"the residues cannot be bounded from measurements at the [initial] frequencies"
                               f"{f' ({coupling.group(0)})' if coupling else ''}{cause}; give b0_min/b0_max, separate the "
                               "bands or move initial points nearer the resonances") from None


def _looks_like_hz(initial, bands: list[tuple[float, float]]) -> str:
    """A cause to name when the [initial] frequencies or the [[mode]] bands look like hertz: the
    initial points sit far more often at a mode's band (within a factor 1.5) once one side is
    multiplied by 2 pi (issue 40: a Hz list was caught, but explained as a mode coupling)."""
    import numpy as np

    def near(w) -> float:
        return float(np.mean([any(lo / 1.5 <= x <= hi * 1.5 for lo, hi in bands) for x in w])) if len(w) else 0.0

    given, initial_hz, bands_hz = near(initial), near(np.asarray(initial) * 2 * np.pi), near(np.asarray(initial) / (2 * np.pi))
    if max(initial_hz, bands_hz) < 0.6 or max(initial_hz, bands_hz) < given + 0.3:
        return ""
    if initial_hz >= bands_hz:
        return ("; the [initial] frequencies look like Hz: times 2 pi they sit at the modes' bands (they are rad/s; "
                "or give them in Hz as omega_hz = [...])")
    return ("; the [[mode]] bands look like Hz: the [initial] frequencies sit at them divided by 2 pi (omega_min and "
            "omega_max are rad/s; or give omega_min_hz / omega_max_hz)")


def run_journaled_campaign(procedure: Procedure, experiment: Any, journal: Journal, *, seed: int, strategy: str,
                           observers: Sequence[Observer] = (), continue_stored: bool = False, control=None) -> CampaignSummary:
    """Algorithm 5.1 on ``experiment`` into ``journal`` with the standard subscribers plus ``observers``."""
    subscribers = [*observers, *standard_observers(procedure, experiment, journal)]
    return run_campaign(procedure, experiment, journal, seed=seed, strategy=strategy, progress=broadcast(subscribers),
                        continue_stored=continue_stored, control=control)


PROCEDURE_CHANGED = "procedure-changed"
"""Journal event of ``run --resume DIR --procedure FILE``: its message ends with the new procedure text."""


def _changed_procedure_text(journal: Journal) -> str | None:
    """The procedure text of the latest ``run --resume --procedure`` of this run, if any."""
    changed = [e for e in journal.events() if e["kind"] == PROCEDURE_CHANGED]
    return changed[-1]["message"].split("\n", 1)[1] if changed else None


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


def start_run(
    procedure: Procedure,
    run_dir: str | os.PathLike,
    *,
    seed: int | None = None,
    strategy: str | None = None,
    console: Console | None = None,
    opener: ExperimentOpener,
    display: Display | None = None,
    quiet_report_hint: bool = False,
    control=None,
    observers: Sequence[Observer] = (),
    design: str | None = None,
) -> RunOutcome:
    """Create ``run_dir`` with a new journal and run the campaign (see the module docstring).

    The procedure's text (``procedure.source_text``, or its :func:`format_procedure` rendering
    for a programmatic procedure) is stored in the journal with the seed, strategy, backend and
    software version, so the run can be resumed and reported later. ``opener(procedure, seed)``
    builds the experiment (:func:`setmem_hil.experiment_factory.open_experiment`); ``display``
    adds a view of the campaign (terminal progress, live view). ``design`` overrides the
    procedure's ``[design] method`` (``--design``); the journal keeps it for a resume.
    """
    console = console or Console(soft_wrap=True)
    run_dir = Path(run_dir)
    if design is not None:
        if design not in DESIGN_METHODS:
            raise _arguments_error(f"design {design!r} is not one of {', '.join(DESIGN_METHODS)}")
        procedure = replace(procedure, design_method=design)
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
        raise InputFormatError(str(run_dir), "", f"already holds a run (it already holds a journal.sqlite); continue it with `setmem-hil run --resume {run_dir}` or choose another --out")
    preflight(procedure)
    # Open the rig first: a transport option the driver rejects, or a device that does not
    # start, must not leave behind a journal whose stored procedure can never run.
    experiment = opener(procedure, seed)
    try:
        journal = Journal.create(
            run_dir / JOURNAL_FILENAME,
            procedure_text=text,
            procedure_name=procedure.name,
            seed=seed,
            software_version=__version__,
            backend=procedure.backend.kind,
            strategy=strategy,
            design=procedure.design_method,
        )
    except BaseException:
        experiment.close()
        raise
    with _run_lock(run_dir, journal):
        write_text_atomic(run_dir / PROCEDURE_COPY, text)
        console.print(f"run directory: {run_dir}", highlight=False)
        describe_procedure(procedure, console)
        return _run_with_journal(procedure, journal, run_dir, seed=seed, strategy=strategy, console=console,
                                 experiment=experiment, opener=opener, display=display, quiet_report_hint=quiet_report_hint,
                                 control=control, observers=observers)


def resume_run(run_dir: str | os.PathLike, *, console: Console | None = None, opener: ExperimentOpener,
               display: Display | None = None, procedure_path: str | os.PathLike | None = None, control=None,
               observers: Sequence[Observer] = ()) -> RunOutcome:
    """Continue the run in ``run_dir`` from its journal (REPLAY; see the module docstring).

    With ``procedure_path`` the run continues with that (corrected) procedure: every stored
    measurement is reused as data, iterations go on after the last stored one, and the change
    (old and new text's SHA-256, the new text) is journaled as a ``procedure-changed`` event, so a
    later plain resume continues with the corrected procedure too.
    """
    console = console or Console(soft_wrap=True)
    run_dir = Path(run_dir)
    journal = Journal.open(run_dir)
    try:
        info = journal.run_info()
        source = f"{journal.path} (stored procedure)"
        if not info["procedure_text"].strip():
            raise InputFormatError(str(journal.path), "table run", "the journal holds no procedure text; this run cannot be resumed")
        changed = _changed_procedure_text(journal)
        procedure = parse_procedure_text(changed or info["procedure_text"], source if changed is None else f"{journal.path} (changed procedure)")
        if procedure_path is not None:
            from setmem_hil.io.procedure_file import load_procedure

            procedure = load_procedure(procedure_path)
            preflight(procedure)
        if procedure_path is None and changed is None:  # the design the run started with (--design)
            procedure = replace(procedure, design_method=str(info.get("design") or "h2"))
        if procedure.backend.kind != info["backend"]:
            raise InputFormatError(source, "[backend]", f"kind {procedure.backend.kind!r} differs from the run's backend {info['backend']!r}")
    except BaseException:
        journal.close()
        raise
    if info["finished"]:
        journal.close()
        summary = info["summary"] or {}
        if not (run_dir / SUMMARY_FILENAME).exists():
            write_json_atomic(summary, run_dir / SUMMARY_FILENAME)
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
        continue_stored = procedure_path is not None or changed is not None
        if procedure_path is not None:
            import hashlib

            old_text = changed or info["procedure_text"]
            new_text = procedure.source_text or format_procedure(procedure)
            digest = lambda t: hashlib.sha256(t.encode("utf-8")).hexdigest()[:16]  # noqa: E731
            journal.add_event(PROCEDURE_CHANGED, f"procedure replaced by {procedure_path} (sha256 {digest(new_text)}, was "
                                                 f"{digest(old_text)}); the {stored} stored measurements are reused as data\n{new_text}")
            console.print(f"continuing {run_dir} with {procedure_path}: the {stored} stored measurements are reused", highlight=False)
        console.print(f"resuming {run_dir}: {stored} measurements stored, seed {info['seed']}, strategy {info['strategy']}", highlight=False)
        return _run_with_journal(procedure, journal, run_dir, seed=int(info["seed"]), strategy=str(info["strategy"]), console=console,
                                 opener=opener, display=display, continue_stored=continue_stored, control=control,
                                 observers=observers)


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


def _run_with_journal(procedure: Procedure, journal: Journal, run_dir: Path, *, seed: int, strategy: str, console: Console,
                      opener: ExperimentOpener, display: Display | None, experiment: Any = None,
                      continue_stored: bool = False, quiet_report_hint: bool = False, control=None,
                      observers: Sequence[Observer] = ()) -> RunOutcome:
    with _sigterm_as_interrupt():
        return _run_campaign_in(procedure, journal, run_dir, seed=seed, strategy=strategy, console=console,
                                opener=opener, display=display, experiment=experiment, continue_stored=continue_stored,
                                quiet_report_hint=quiet_report_hint, control=control, observers=observers)


INSTRUMENTS_EVENT = "instruments"
"""Journal event: the instruments a session drove and what each answered to its identity query."""


def _journal_identities(journal: Journal, experiment: Any) -> None:
    from setmem_hil.model.experiment import IdentifiedExperiment

    if isinstance(experiment, IdentifiedExperiment) and experiment.identities:
        journal.add_event(INSTRUMENTS_EVENT, "; ".join(f"{name}: {answer}" for name, answer in experiment.identities.items()))


EXCITER_ARMED_EVENT = "exciter-armed"
"""Journal event: a session with an exciter began (its output may be switched on from here)."""
OUTPUT_OFF_EVENT = "output-off"
"""Journal event at the end of a session: whether the exciter's output was confirmed off; its
message starts with ``confirmed`` or ``NOT confirmed``. An ``exciter-armed`` event with no
``output-off ... confirmed`` after it is a session that ended without a confirmed output-off
(SIGKILL, power loss, a dead link): the next ``run --resume`` switches the output off first."""


def unconfirmed_output_off(journal: Journal) -> str | None:
    """Why the journal's last session did not end with a confirmed output-off (None if it did,
    or never drove an exciter)."""
    last = None
    for event in journal.events():
        if event["kind"] in (EXCITER_ARMED_EVENT, OUTPUT_OFF_EVENT):
            last = event
    if last is None or (last["kind"] == OUTPUT_OFF_EVENT and last["message"].startswith("confirmed")):
        return None
    if last["kind"] == EXCITER_ARMED_EVENT:
        return f"the session started {last['utc']} ended without a confirmed output-off (killed, power loss?)"
    return f"its last session could not confirm the output off ({last['message']})"


def _arm_exciter(journal: Journal, experiment: Any, console: Console, previous_unconfirmed: str | None) -> None:
    from setmem_hil.model.experiment import OutputConfirmingExperiment

    if not isinstance(experiment, OutputConfirmingExperiment):
        return
    if previous_unconfirmed is not None:
        experiment.confirm_output_off()  # opening forced it off already: read it back once more, and say so
        line = f"output switched off: {experiment.exciter} (read back), because {previous_unconfirmed}"
        if console.quiet:  # a safety action is always said, --quiet or not
            print(f"setmem-hil: {line}", file=sys.stderr, flush=True)
        else:
            console.print(line, highlight=False)
        journal.add_event(OUTPUT_OFF_EVENT, f"confirmed at resume: {line}")
    journal.add_event(EXCITER_ARMED_EVENT, f"{experiment.exciter}: the output may be switched on from here")


def _run_campaign_in(procedure: Procedure, journal: Journal, run_dir: Path, *, seed: int, strategy: str, console: Console,
                     opener: ExperimentOpener, display: Display | None, experiment: Any = None,
                     continue_stored: bool = False, quiet_report_hint: bool = False, control=None,
                     observers: Sequence[Observer] = ()) -> RunOutcome:
    resume = f"continue with `setmem-hil run --resume {run_dir}`"
    try:
        previous_unconfirmed = unconfirmed_output_off(journal)
        if experiment is None:
            experiment = opener(procedure, seed)
        _journal_identities(journal, experiment)
        _arm_exciter(journal, experiment, console, previous_unconfirmed)
        with (display(experiment) if display is not None else contextlib.nullcontext(None)) as shown:
            summary = run_journaled_campaign(procedure, experiment, journal, seed=seed, strategy=strategy,
                                             observers=([shown] if shown is not None else []) + list(observers),
                                             continue_stored=continue_stored, control=control)
        doc = summary.to_document()
    except KeyboardInterrupt as exc:
        why = "SIGTERM: stopped by a signal" if isinstance(exc, _Terminated) else "Ctrl-C: stopped by the operator"
        with _sigint_deferred():
            safety, _ = _shutdown(experiment, journal, "interrupted", why)
        # one line says what was made safe, what is kept and how to go on (the CLI prints it)
        raise RunInterrupted(f"interrupted ({why.split(':')[0]}); {safety}, journal closed with "
                             f"{_stored(journal)} measurements; {resume}") from exc
    except CampaignAborted as exc:
        with _sigint_deferred():
            safety, _ = _shutdown(experiment, journal, "aborted", f"aborted: {exc}")
        raise CampaignAborted(f"aborted ({exc}); {safety}, journal closed with {_stored(journal)} measurements; {resume}") from exc
    except DeviceError as exc:
        with _sigint_deferred():
            safety, _ = _shutdown(experiment, journal, "device-fault", str(exc))
        exc.safety_note = safety  # the first fault stays the message; what the clean-up achieved follows it
        exc.resume_hint = f"journal closed with {_stored(journal)} measurements; after fixing the rig {resume}"
        raise
    except BaseException as exc:
        with _sigint_deferred():
            safety, _ = _shutdown(experiment, journal, "error", f"{type(exc).__name__}: {exc}")
        if isinstance(exc, Exception):
            fix = " --procedure FIXED.toml" if isinstance(exc, (InconsistentDataError, InputFormatError)) else ""
            exc.resume_hint = (f"{safety}, journal closed with {_stored(journal)} measurements; continue with "
                               f"`setmem-hil run --resume {run_dir}{fix}`")
        raise
    with _sigint_deferred():
        safety, close_error = _shutdown(experiment, journal, None, "")
    write_json_atomic(doc, run_dir / SUMMARY_FILENAME)
    console.print(f"summary: {run_dir / SUMMARY_FILENAME}" + ("" if quiet_report_hint else f" (report: setmem-hil report {run_dir})"),
                  highlight=False)
    if close_error is not None:  # every point is kept; the rig is not known to be safe
        raise DeviceError(f"the campaign finished, but {safety}") from close_error
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


def _shutdown(experiment: Any, journal: Journal, kind: str | None, message: str) -> tuple[str, BaseException | None]:
    """Exciter to zero first, then record why we stopped and whether the output is confirmed
    off, then close the journal. A failing clean-up never replaces the cause: it is returned
    (with the sentence that says what state the rig is in) for the caller's message."""
    close_error: BaseException | None = None
    try:
        if experiment is not None:
            experiment.close()
    except BaseException as exc:  # noqa: BLE001 - reported in the safety sentence, never raised over the cause
        close_error = exc
    safety, confirmed = output_safety(experiment, close_error)
    try:
        if kind is not None and not journal.closed:
            journal.add_event(kind, message)
        if confirmed is not None and not journal.closed:
            journal.add_event(OUTPUT_OFF_EVENT, f"{'confirmed' if confirmed else 'NOT confirmed'}: {safety}")
    finally:
        journal.close()
    return safety, close_error


def output_safety(experiment: Any, close_error: BaseException | None) -> tuple[str, bool | None]:
    """The sentence that says what state the exciter was left in, and whether its output is
    confirmed off (None: the experiment cannot read its output back)."""
    from setmem_hil.errors import OutputNotConfirmedOffError
    from setmem_hil.model.experiment import OutputConfirmingExperiment

    if isinstance(close_error, OutputNotConfirmedOffError):
        return " ".join(str(close_error).split()), False
    if isinstance(experiment, OutputConfirmingExperiment):
        if experiment.output_confirmed_off:
            return f"output of {experiment.exciter} confirmed off", True
        cause = f" ({' '.join(str(close_error).split())})" if close_error is not None else ""
        return (f"the output of {experiment.exciter} could not be confirmed off{cause}: it may still be on: "
                "switch it off at the instrument or at the amplifier"), False
    if close_error is not None:
        return (f"the exciter could not be commanded to zero ({' '.join(str(close_error).split())}): "
                "switch it off at the instrument or at the amplifier"), None
    return "exciter at zero", None
