"""``RUN_DIR/raw.h5``: what every measurement was computed from (issue 39), in HDF5 (h5py).

Layout (``docs/raw-records.md``)::

    raw.h5                          the index every tool opens
      /measurements/<seq>           one group per record, named by the first measurement it
                                    served (its journal ``seq``); an HDF5 external link to:
    raw/<seq>.h5                    the record itself, at its root:
      attrs  kind                   the estimator that turns it into points
             seqs                   every measurement it served (a multisine record: several)
             format_version         1
             <setting>              the stored settings (numbers, strings; structures as JSON
                                    text, their names listed in attr ``json_attrs``)
      datasets                      samples, readings, times as read (gzip + shuffle, chunked)

**Crash safety.** HDF5 does not survive a process killed inside a write, so nothing is ever
written in place: each record goes to its own file (``raw/.<seq>.h5.partial``, flushed and
fsynced, then renamed), and the index is rebuilt from the folder the same way. A kill at any
moment leaves the previous index and every earlier record intact; the engine commits a
measurement to the journal only after its record is in place, so every committed measurement
has its record (a record written just before a kill, its point never committed, is measured and
written again on resume, under the same name). Copy the run directory whole: the index links to
``raw/`` by relative path.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.model.experiment import RawRecord

__all__ = ["RAW_INDEX", "RAW_FOLDER", "RawStore", "StoredRawRecord", "read_raw_records", "FORMAT_VERSION"]

RAW_INDEX = "raw.h5"
RAW_FOLDER = "raw"
FORMAT_VERSION = 1
COMPRESS_ABOVE = 256  # elements: smaller arrays are stored plain (chunking them costs more than it saves)
RESERVED_ATTRS = ("kind", "seqs", "format_version", "json_attrs", "positions")


@dataclass(frozen=True)
class StoredRawRecord:
    """A record read back: the measurements it served and the record itself."""

    seqs: tuple[int, ...]
    record: RawRecord


class RawStore:
    """Writes a run's raw records (see the module docstring)."""

    def __init__(self, run_dir: str | os.PathLike):
        self.run_dir = Path(run_dir)
        self.folder = self.run_dir / RAW_FOLDER

    def write(self, seqs: tuple[int, ...], record: RawRecord) -> Path:
        """Store ``record`` as serving measurements ``seqs``; returns its file."""
        import h5py

        self.folder.mkdir(parents=True, exist_ok=True)
        target = self.folder / f"{seqs[0]}.h5"
        partial = self.folder / f".{seqs[0]}.h5.partial"
        with h5py.File(partial, "w") as f:
            _write_record(f, seqs, record)
        _fsync_and_rename(partial, target)
        self.rebuild_index()
        return target

    def rebuild_index(self) -> None:
        """``raw.h5`` with one external link per record file in ``raw/`` (atomically replaced)."""
        import h5py

        partial = self.run_dir / f".{RAW_INDEX}.partial"
        with h5py.File(partial, "w") as f:
            f.attrs["format_version"] = FORMAT_VERSION
            group = f.create_group("measurements")
            for first in sorted(int(p.stem) for p in self.folder.glob("*.h5") if p.stem.isdigit()):
                group[str(first)] = h5py.ExternalLink(f"{RAW_FOLDER}/{first}.h5", "/")
        _fsync_and_rename(partial, self.run_dir / RAW_INDEX)


def _fsync_and_rename(partial: Path, target: Path) -> None:
    with open(partial, "rb+") as handle:
        os.fsync(handle.fileno())
    os.replace(partial, target)


def _write_record(f, seqs: tuple[int, ...], record: RawRecord) -> None:
    f.attrs["kind"] = record.kind
    f.attrs["seqs"] = np.asarray(seqs, dtype=np.int64)
    f.attrs["format_version"] = FORMAT_VERSION
    structured = []
    for name, value in record.attrs.items():
        if name in RESERVED_ATTRS:
            raise ValueError(f"raw record attribute {name!r} is reserved")
        if isinstance(value, (str, bool, int, float, np.integer, np.floating)):
            f.attrs[name] = value
        else:
            f.attrs[name] = json.dumps(value)
            structured.append(name)
    f.attrs["json_attrs"] = json.dumps(structured)
    for name, data in record.datasets.items():
        array = np.asarray(data)
        options = dict(compression="gzip", compression_opts=4, shuffle=True, chunks=True) if array.size > COMPRESS_ABOVE else {}
        f.create_dataset(name, data=array, **options)


def read_raw_records(run_dir: str | os.PathLike) -> list[StoredRawRecord]:
    """Every record the index ``RUN_DIR/raw.h5`` lists, in ``seq`` order.

    Raises :class:`~setmem_hil.errors.InputFormatError` when the index is missing or a record
    cannot be read (naming the file)."""
    return list(iter_raw_records(run_dir))


def iter_raw_records(run_dir: str | os.PathLike) -> Iterator[StoredRawRecord]:
    """As :func:`read_raw_records`, one record in memory at a time."""
    import h5py

    index = Path(run_dir) / RAW_INDEX
    if not index.is_file():
        raise InputFormatError(str(index), "", "no raw records: the run kept none (written by setmem-hil before raw records, "
                                               "or its raw.h5 was removed)")
    try:
        with h5py.File(index, "r") as f:
            names = sorted(f["measurements"].keys(), key=int)
    except (OSError, KeyError, ValueError) as exc:
        raise InputFormatError(str(index), "/measurements", f"unreadable raw-record index ({exc})") from None
    for name in names:
        yield _read_record(Path(run_dir) / RAW_FOLDER / f"{name}.h5")


def _read_record(path: Path) -> StoredRawRecord:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            structured = set(json.loads(f.attrs["json_attrs"]))
            attrs: dict[str, Any] = {}
            for key, value in f.attrs.items():
                if key in RESERVED_ATTRS:
                    continue
                attrs[key] = json.loads(value) if key in structured else _plain(value)
            datasets = {name: f[name][()] for name in f.keys()}
            seqs = tuple(int(s) for s in f.attrs["seqs"])
            return StoredRawRecord(seqs, RawRecord(str(f.attrs["kind"]), datasets, attrs))
    except (OSError, KeyError, ValueError) as exc:
        raise InputFormatError(str(path), "", f"unreadable raw record ({exc})") from None


def _plain(value: Any) -> Any:
    """HDF5 attributes come back as numpy scalars: the Python value (exact for floats)."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value
