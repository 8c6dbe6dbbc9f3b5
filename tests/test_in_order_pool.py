"""run_in_order: threads whose timing cannot change the answer (issue 47's irreproducible runs)."""

from __future__ import annotations

import random
import threading
import time
from collections import deque

import pytest

from setmem_hil.numerics.in_order_pool import run_in_order


class ToySearch:
    """A search whose next task depends on the results applied so far: each result spawns children
    whose labels depend on a running total, and take picks the largest open label."""

    def __init__(self, delays: bool, seed: int = 0):
        self.open = [1]
        self.total = 0
        self.trace: list[tuple[int, int]] = []
        self.delays = random.Random(seed) if delays else None
        self.lock = threading.Lock()

    def take(self):
        if not self.open or len(self.trace) > 60:
            return None
        best = max(self.open)
        self.open.remove(best)
        return best

    def compute(self, label):
        if self.delays is not None:
            with self.lock:
                pause = self.delays.uniform(0.0, 0.004)
            time.sleep(pause)
        return (label * 7 + 3) % 23

    def apply(self, label, result):
        self.total += result
        self.trace.append((label, result))
        if result % 3:
            self.open.extend([(self.total + label) % 31 + 1, (self.total * label) % 29 + 1])


def sequential_reference(search: ToySearch, lookahead: int) -> None:
    """The rule written out on one thread: tasks in flight form a queue; the oldest is computed
    and applied, then tasks are taken while fewer than ``lookahead`` are in flight."""
    flight: deque = deque()

    def fill():
        while len(flight) < lookahead:
            task = search.take()
            if task is None:
                return
            flight.append(task)

    fill()
    while flight:
        task = flight.popleft()
        search.apply(task, search.compute(task))
        fill()


@pytest.mark.parametrize("lookahead", [1, 2, 4])
def test_the_trace_is_the_sequential_rules_whatever_the_threads_timing(lookahead):
    reference = ToySearch(delays=False)
    sequential_reference(reference, lookahead)
    assert len(reference.trace) > 20  # the toy search branches for a while
    for workers, seed in [(1, 0), (2, 1), (3, 2), (4, 3)]:
        threaded = ToySearch(delays=True, seed=seed)
        run_in_order(threaded.take, threaded.compute, threaded.apply, lookahead, workers)
        assert threaded.trace == reference.trace, (workers, seed)


def test_workers_really_run_at_once():
    inside, most = [0], [0]
    lock = threading.Lock()
    tasks = list(range(8))

    def compute(task):
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        time.sleep(0.05)
        with lock:
            inside[0] -= 1
        return task

    done = []
    run_in_order(lambda: tasks.pop(0) if tasks else None, compute, lambda t, r: done.append(r), lookahead=2, workers=2)
    assert done == list(range(8)) and most[0] == 2


def test_an_error_in_a_worker_is_raised_after_every_thread_ended():
    tasks = list(range(20))
    before = threading.active_count()

    def compute(task):
        if task == 5:
            raise ZeroDivisionError("task 5")
        time.sleep(0.002)
        return task

    with pytest.raises(ZeroDivisionError, match="task 5"):
        run_in_order(lambda: tasks.pop(0) if tasks else None, compute, lambda t, r: None, lookahead=3, workers=3)
    assert threading.active_count() == before


def test_an_error_in_apply_is_raised_too():
    tasks = list(range(5))

    def apply(task, result):
        if task == 2:
            raise KeyError("apply 2")

    with pytest.raises(KeyError, match="apply 2"):
        run_in_order(lambda: tasks.pop(0) if tasks else None, lambda t: t, apply, lookahead=2, workers=2)
