"""The one atomic file writer and the one JSON sanitiser of setmem-hil.

Every file a command produces (RESULT.json, summary.json, report.html, CSV exports, figures,
sweep records) is written through :func:`atomic_path`: into a uniquely named temporary file in
the same directory, flushed and ``fsync``-ed, renamed over the target with ``os.replace``
(atomic on one filesystem), and the directory entry ``fsync``-ed. A crash or a kill leaves
either the old file or the new one, never half a file, and two writers never share a
temporary name.

:func:`json_safe` is the one rule for values JSON cannot hold: non-finite floats (an unbounded
embedding ratio, an unstable loop's mu-bar) become ``null``; numpy scalars and arrays become
Python numbers and lists.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import uuid
from pathlib import Path
from typing import Any, Iterator

__all__ = ["atomic_path", "write_text_atomic", "write_json_atomic", "json_safe"]


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # not possible on every platform; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a unique temporary path beside ``path``; on success make it ``path`` atomically.

    The caller writes the temporary file (any writer: text, bytes, ``savefig``); on leaving the
    block it is fsync-ed and renamed into place. On an exception it is removed and ``path`` is
    untouched.
    """
    target = Path(path)
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json_atomic(doc: Any, path: str | os.PathLike, *, indent: int = 2) -> Path:
    """Write ``json_safe(doc)`` to ``path`` atomically (``allow_nan=False``: strict JSON)."""
    return write_text_atomic(path, json.dumps(json_safe(doc), indent=indent, allow_nan=False) + "\n")


def json_safe(obj: Any) -> Any:
    """A JSON-ready copy of ``obj``: non-finite floats become ``None``, numpy values plain Python."""
    if isinstance(obj, bool) or obj is None or isinstance(obj, (str, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if hasattr(obj, "tolist") and callable(obj.tolist):  # numpy arrays and scalars
        return json_safe(obj.tolist())
    return obj
