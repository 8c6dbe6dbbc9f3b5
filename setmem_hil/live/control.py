"""Pause, Resume and Abort of a running campaign, checked by the runner between dwells."""

from __future__ import annotations

import threading
from typing import Callable

from setmem_hil.errors import CampaignAborted

__all__ = ["LiveControl"]


class LiveControl:
    """A :class:`setmem_hil.model.experiment.CampaignControl` the live view's buttons set.

    Pause is honest about the rig: the status is ``pausing`` from the button until the dwell in
    progress has finished and the runner reached its checkpoint, where ``make_safe`` confirms
    every exciter output off; only then is it ``paused`` (no measurement is added while paused,
    and the output is off). Abort stops before the next dwell, or at once while paused.
    """

    def __init__(self):
        self._run = threading.Event()
        self._run.set()
        self._abort = threading.Event()
        self._lock = threading.Lock()
        self._held = False  # the runner waits at its checkpoint with the outputs confirmed off

    @property
    def status(self) -> str:
        if self._abort.is_set():
            return "aborted"
        if self._run.is_set():
            return "running"
        return "paused" if self._held else "pausing"

    def pause(self) -> None:
        self._run.clear()

    def resume(self) -> None:
        self._run.set()

    def abort(self) -> None:
        self._abort.set()
        self._run.set()  # wake a paused checkpoint so it can raise

    def checkpoint(self, make_safe: Callable[[], object] | None = None) -> None:
        if not self._run.is_set():
            if make_safe is not None:
                make_safe()  # raises if an output cannot be confirmed off: then it is no pause but a fault
            self._held = True
            try:
                while not self._run.wait(0.2):
                    pass
            finally:
                self._held = False
        if self._abort.is_set():
            raise CampaignAborted("Abort pressed in the live view")
