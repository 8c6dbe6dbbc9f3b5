"""Pause, Resume and Abort of a running campaign, checked by the runner between dwells."""

from __future__ import annotations

import threading

from setmem_hil.errors import CampaignAborted

__all__ = ["LiveControl"]


class LiveControl:
    """A :class:`setmem_hil.model.experiment.CampaignControl` the live view's buttons set.

    Pause takes effect when the current dwell has finished (the dwell stops its exciter at its end:
    the output is off while paused); Abort stops before the next dwell, or at once while paused.
    """

    def __init__(self):
        self._run = threading.Event()
        self._run.set()
        self._abort = threading.Event()
        self._lock = threading.Lock()

    @property
    def status(self) -> str:
        if self._abort.is_set():
            return "aborted"
        return "running" if self._run.is_set() else "paused"

    def pause(self) -> None:
        self._run.clear()

    def resume(self) -> None:
        self._run.set()

    def abort(self) -> None:
        self._abort.set()
        self._run.set()  # wake a paused checkpoint so it can raise

    def checkpoint(self) -> None:
        while not self._run.wait(0.2):
            pass
        if self._abort.is_set():
            raise CampaignAborted("Abort pressed in the live view")
