"""What differs between operating systems, in one place (issue 40: most rig PCs run Windows).

* :func:`directory_lock`: one process at a time per directory, through ``filelock`` (``flock``
  on POSIX, ``msvcrt.locking`` on Windows, a lock file with its owner's pid where neither
  exists: a lock left by a killed process is taken over, not obeyed forever);
* :func:`kill_process`: stop a process at once (``SIGKILL`` on POSIX; Windows has no such
  signal, and ``os.kill`` with ``SIGTERM`` calls ``TerminateProcess`` there).

Elsewhere the code uses only what every OS has: instrument sockets are peeked after
``select`` says they are readable (not with ``MSG_DONTWAIT``, which Windows lacks).
"""

from __future__ import annotations

import os
import signal
import warnings
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["DirectoryBusy", "directory_lock", "kill_process"]


class DirectoryBusy(Exception):
    """Another process holds the directory's lock."""


@contextmanager
def directory_lock(folder: Path, lock_name: str) -> Iterator[None]:
    """Hold ``folder/lock_name`` for the block; :class:`DirectoryBusy` at once if another
    process holds it (released when the block ends or the process dies, also on SIGKILL)."""
    with warnings.catch_warnings():  # "only soft file lock is available": what we want there
        warnings.simplefilter("ignore")
        import filelock
    lock = filelock.FileLock(str(Path(folder) / lock_name), timeout=0)
    try:
        lock.acquire()
    except filelock.Timeout:
        raise DirectoryBusy(str(folder)) from None
    try:
        yield
    finally:
        lock.release()


def kill_process(pid: int) -> None:
    """End process ``pid`` at once (it gets no chance to clean up)."""
    os.kill(pid, getattr(signal, "SIGKILL", signal.SIGTERM))
