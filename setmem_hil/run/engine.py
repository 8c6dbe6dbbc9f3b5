"""The run engine: performs a plan's requests and sends the run's documents (Bluesky's RunEngine).

A plan is a generator: it ``yield``\\ s a request and receives the engine's reply as the value of
the ``yield`` expression. The plan says *what* to do; the engine runs it, whichever plan it is:

* **commands**: each request type has a handler, ``handler(engine, request) -> reply``. The
  engine knows two (:class:`Emit`, :class:`Checkpoint`); a plan brings its
  own with :meth:`RunEngine.register_command` (e.g. the thesis loop's, in ``measurement_service``)
  without touching this module;
* **errors go back into the plan**: a handler that raises has its exception thrown into the plan
  at its ``yield``, so the plan's ``try/finally`` runs; unhandled, it leaves :meth:`RunEngine.run`
  unchanged;
* **one lifecycle in the documents**: ``start`` (plan name, its arguments as JSON, software
  version, seed, run id, the planned number of points, UTC time) before the first request
  and ``stop`` (run id, ``exit_status`` ``success``, ``abort`` or ``fail``, ``reason``, UTC time)
  after the last, however the run ends;
* **pause points the plan declares** (:class:`Checkpoint`): the operator's pause holds there with
  the rig made safe (``make_safe``), reported as ``note`` documents ``paused`` and ``unpaused``;
  an abort raises there;
* **replay marks** (:class:`Emit` ``key``): a document whose key the stopped run already holds is
  sent marked ``replayed`` (stores do not store it twice), and its ``check`` values must equal the
  stored ones, else :class:`~setmem_hil.errors.ReplayError`;
* **a stop signal Python dropped** (it landed in a finaliser) is raised before the next request
  (:mod:`setmem_hil.run.signal_latch`), so it stops the run as if it had been delivered;
* **the plan's own computation** runs inside ``compute`` (by default single-threaded BLAS,
  :func:`setmem_hil.numerics.blas_threads.blas_one_thread`: small matrices, results independent of
  the machine's thread count); the handlers run outside it. The engine clocks it: every document
  a plan emits carries ``plan_s`` and ``plan_cpu_s``, the wall and CPU seconds the plan has
  computed since the run started (not counting its requests' handlers), so a store
  times a step of the plan as the difference of two documents' clocks and the plan holds no clock.

Subscribers are called in order as ``subscriber(name, **info)``; stores come first so that
displays and checks that read them see every document's effect.
"""

from __future__ import annotations

import json
import math
import time
import uuid
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from datetime import datetime, timezone
from typing import Any, Callable, Generator, Hashable, Mapping, Sequence

from setmem_hil.errors import ReplayError, RunAborted
from setmem_hil.run import signal_latch
from setmem_hil.numerics.blas_threads import blas_one_thread

__all__ = ["RunEngine", "RunStart", "Emit", "Checkpoint", "Subscriber", "START", "STOP", "NOTE",
           "EXIT_SUCCESS", "EXIT_ABORT", "EXIT_FAIL"]

Subscriber = Callable[..., None]
Handler = Callable[["RunEngine", Any], Any]

START, STOP, NOTE = "start", "stop", "note"
"""Documents: the run's start and stop, and a note (``kind``, ``message``, ``replayed``) for the record."""
EXIT_SUCCESS, EXIT_ABORT, EXIT_FAIL = "success", "abort", "fail"


@dataclass(frozen=True)
class Emit:
    """A document for the subscribers: ``subscriber(name, **info)``.

    ``key`` names what the document records (e.g. ``("k", 3)``): when the stopped run being
    replayed holds that key, the document is sent with ``replayed=True``; ``check`` holds values
    that must then equal the stored ones (a replay that chooses differently stops)."""

    name: str
    info: dict = field(default_factory=dict)
    key: Hashable | None = None
    check: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Checkpoint:
    """A point where the run may pause (the rig made safe first) or be aborted; ``before`` says
    what comes next, for the pause's note (e.g. ``"point 4"``)."""

    before: str = ""


@dataclass(frozen=True)
class RunStart:
    """What the ``start`` document says about a run: the plan's name and arguments (JSON-able),
    the seed, and the number of points it plans (the progress display's total)."""

    plan: str
    arguments: Mapping[str, Any] = field(default_factory=dict)
    seed: int | None = None
    planned: int = 0


class RunEngine:
    """Runs plans (see the module docstring).

    ``stored``: the keys of a stopped run's documents, each with the values a replay must repeat;
    ``control``: the operator's pause/abort (``checkpoint(make_safe)``, the live view);
    ``make_safe``: what a pause does first (e.g. confirm every exciter output off), described by
    ``safe_state`` in the pause's note.
    """

    def __init__(self, subscribers: Sequence[Subscriber] = (), *, control=None, stored: Mapping[Hashable, Mapping] | None = None,
                 make_safe: Callable[[], None] | None = None, safe_state: str = "the rig made safe",
                 compute: Callable[[], AbstractContextManager] = blas_one_thread, source: str = "the stored run"):
        self.subscribers = list(subscribers)
        self.control, self.make_safe, self.safe_state = control, make_safe, safe_state
        self.stored = dict(stored or {})
        self.compute, self.source = compute, source
        self.run_id: str | None = None
        self.plan_s = self.plan_cpu_s = 0.0  # the plan's own computation so far (see the module docstring)
        self._commands: dict[type, Handler] = {}
        self.register_command(Emit, RunEngine._emit_request)
        self.register_command(Checkpoint, RunEngine._checkpoint)

    def register_command(self, request_type: type, handler: Handler) -> None:
        """Perform every ``request_type`` request with ``handler(engine, request)``; its return
        value is the plan's reply. A later registration replaces an earlier one."""
        self._commands[request_type] = handler

    @property
    def elapsed_s(self) -> float:
        """Wall seconds since the current run's ``start`` document (0 before any run)."""
        started = getattr(self, "_started", None)
        return 0.0 if started is None else time.perf_counter() - started

    def subscribe(self, subscriber: Subscriber) -> None:
        self.subscribers.append(subscriber)

    def emit(self, name: str, **info: Any) -> None:
        for subscriber in self.subscribers:
            subscriber(name, **info)

    # -- running a plan ---------------------------------------------------------------------------
    def run(self, plan: Generator, start: RunStart | None = None) -> Any:
        """Perform every request of ``plan`` between a ``start`` and a ``stop`` document and
        return the plan's return value; an exception that leaves the plan leaves here too."""
        start = start or RunStart(getattr(plan, "__name__", "plan"))
        self.run_id = uuid.uuid4().hex
        self.plan_s = self.plan_cpu_s = 0.0
        self._started = time.perf_counter()
        self.emit(START, **_start_document(start, self.run_id))
        try:
            result = self._drive(plan)
        except BaseException as exc:
            try:
                self._stop(EXIT_ABORT if isinstance(exc, (KeyboardInterrupt, RunAborted)) else EXIT_FAIL, _reason(exc))
            except Exception as store_error:  # noqa: BLE001 - a store that fails now must not hide why the run stopped
                _add_note(exc, f"the run's stop document could not be stored: {_reason(store_error)}")
            raise
        self._stop(EXIT_SUCCESS, "")
        return result

    def _drive(self, plan: Generator) -> Any:
        reply: Any = None
        error: BaseException | None = None
        while True:
            wall, cpu = time.perf_counter(), time.process_time()
            try:
                with self.compute():
                    request = plan.send(reply) if error is None else plan.throw(error)
            except StopIteration as done:
                return done.value
            finally:
                self.plan_s += time.perf_counter() - wall
                self.plan_cpu_s += time.process_time() - cpu
            try:
                signal_latch.raise_pending()  # a stop signal dropped in a finaliser stops the run here
                reply, error = self._perform(request), None
            except BaseException as exc:  # noqa: BLE001 - thrown into the plan, so its finally runs
                reply, error = None, exc

    def _perform(self, request: Any) -> Any:
        for kind in type(request).__mro__:
            handler = self._commands.get(kind)
            if handler is not None:
                return handler(self, request)
        raise TypeError(f"the run engine has no command for {type(request).__name__} (register_command)")

    def _stop(self, status: str, reason: str) -> None:
        self.emit(STOP, run_id=self.run_id, exit_status=status, reason=reason, utc=_utc_now())

    # -- the built-in commands --------------------------------------------------------------------
    def _emit_request(self, request: Emit) -> None:
        info = dict(request.info, plan_s=self.plan_s, plan_cpu_s=self.plan_cpu_s)
        if request.key is not None:
            info["replayed"] = request.key in self.stored
            if info["replayed"]:
                self._check_replay(request.key, request.check)
        self.emit(request.name, **info)

    def _check_replay(self, key: Hashable, check: Mapping[str, Any]) -> None:
        stored = self.stored[key]
        for name, now in check.items():
            if not _same(stored.get(name), now):
                where = " ".join(str(part) for part in key) if isinstance(key, tuple) else str(key)
                raise ReplayError(self.source, where, f"stored {name} {stored.get(name)} but the replay gave {now}")

    def _checkpoint(self, request: Checkpoint) -> None:
        """The operator's pause holds here with the rig made safe, reported when it holds and when
        it ends, each with its time; an abort raises here."""
        if self.control is None:
            return
        held_since: list[float] = []

        def safe_and_reported() -> None:
            if self.make_safe is not None:
                self.make_safe()
            held_since.append(time.monotonic())
            where = f" before {request.before}" if request.before else ""
            self.emit(NOTE, kind="paused", message=f"paused{where}: {self.safe_state}", replayed=False)

        # The pause's end is journaled however it ends: a Resume followed at once by Abort wakes the
        # checkpoint with the abort already set, and the pause still held until then.
        try:
            self.control.checkpoint(safe_and_reported)  # may wait (paused) or raise (abort)
        except RunAborted:
            if held_since:
                self.emit(NOTE, kind="unpaused", message=f"ended by abort after {time.monotonic() - held_since[0]:.1f} s paused", replayed=False)
            raise
        if held_since:
            self.emit(NOTE, kind="unpaused", message=f"went on after {time.monotonic() - held_since[0]:.1f} s paused", replayed=False)


def _start_document(start: RunStart, run_id: str) -> dict:
    from setmem_hil import __version__

    return dict(run_id=run_id, plan=start.plan, arguments=json.dumps(dict(start.arguments), sort_keys=True, default=str),
                version=__version__, seed=start.seed, planned=int(start.planned), utc=_utc_now())


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _add_note(exc: BaseException, note: str) -> None:
    if hasattr(exc, "add_note"):  # Python 3.11+
        exc.add_note(note)


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12)
    return a == b
