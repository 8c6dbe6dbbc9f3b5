"""Work on threads whose answer does not depend on which thread finished first.

A best-first search that lets each worker take the next task as soon as it is free makes its
choices on whatever results happen to be in: two runs on the same data disagree (the close pair
at 1 %: the same bounds from one worker every time, different bounds from two, and a campaign's
mu-bar 2.10 one run and 2.47 the next). Here the results are applied strictly in the order the
tasks were taken, and a task is taken only right after a result is applied (or at the start),
while fewer than ``lookahead`` are in flight. What is taken then depends only on the results
applied so far, in their order: the same tasks, in the same order, whatever the threads' timing,
and whatever the number of workers (``lookahead`` is the search's setting, not the machine's).

The price: a worker that finishes early waits while the task before its own is still running (it
cannot take the next until that one is applied).
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Callable, Generic, TypeVar

__all__ = ["run_in_order"]

Task = TypeVar("Task")
Result = TypeVar("Result")


class _InOrder(Generic[Task, Result]):
    def __init__(self, take, compute, apply, lookahead: int):
        self.take, self.compute, self.apply = take, compute, apply
        self.lookahead = max(1, int(lookahead))
        self.cond = threading.Condition()
        self.ready: deque[tuple[int, Task]] = deque()
        self.results: dict[int, tuple[Task, Result]] = {}
        self.n_taken = self.n_applied = 0
        self.error: BaseException | None = None

    def fill(self) -> None:
        """Take tasks while fewer than ``lookahead`` are in flight (under the lock)."""
        while self.n_taken - self.n_applied < self.lookahead:
            task = self.take()
            if task is None:
                break
            self.ready.append((self.n_taken, task))
            self.n_taken += 1

    def apply_in_order(self) -> None:
        """Apply every result whose predecessors are applied, refilling after each (under the lock)."""
        while self.n_applied in self.results:
            task, result = self.results.pop(self.n_applied)
            self.apply(task, result)
            self.n_applied += 1
            self.fill()

    @property
    def finished(self) -> bool:
        return self.error is not None or (not self.ready and self.n_applied == self.n_taken)

    def work(self) -> None:
        while True:
            with self.cond:
                while not self.ready and not self.finished:
                    self.cond.wait()
                if self.finished:
                    self.cond.notify_all()
                    return
                number, task = self.ready.popleft()
            try:
                result = self.compute(task)
                with self.cond:
                    if self.error is None:
                        self.results[number] = (task, result)
                        self.apply_in_order()
                    self.cond.notify_all()
            except BaseException as exc:  # noqa: BLE001 - handed to the caller of run_in_order
                with self.cond:
                    self.error = self.error or exc
                    self.cond.notify_all()
                return


def run_in_order(take: Callable[[], Task | None], compute: Callable[[Task], Result],
                 apply: Callable[[Task, Result], None], lookahead: int = 2, workers: int = 1) -> None:
    """Run ``compute`` on ``workers`` threads (the caller's among them), ``take`` and ``apply``
    under one lock, results applied in the order taken (module docstring).

    ``take()`` returns the next task or ``None`` when there is none for now (the run ends when
    nothing is in flight and ``take`` has none); ``apply(task, result)`` may make more tasks
    available. The first exception raised by any of them is raised here, after every thread ended.
    """
    pool = _InOrder(take, compute, apply, lookahead)
    with pool.cond:
        pool.fill()
    threads = [threading.Thread(target=pool.work, daemon=True) for _ in range(max(1, workers) - 1)]
    for t in threads:
        t.start()
    pool.work()
    for t in threads:
        t.join()
    if pool.error is not None:
        raise pool.error
