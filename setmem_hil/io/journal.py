"""The campaign journal: a crash-safe, append-only record of one run (SQLite, WAL).

One journal per run directory (``DIR/journal.sqlite``). It holds

* the run: procedure text (exactly as loaded), procedure name, seed, software version,
  backend kind, input-design strategy, creation time;
* every measurement, each committed in its own transaction *before the next dwell starts*
  (thesis chapter 5: the loop measures, identifies (eq. 5.4-5.5), analyses and chooses the next
  frequency; only the measurements are expensive, everything else is recomputed on resume);
* per iteration: the parameter bounds, mu-bar on the analysis grid, the peak, the
  mu-sensitivities (appendix B), the chosen frequency and the candidates' estimated
  improvement (figure 6-14), the safeguard branch of eq. 5.12;
* discrepancy results, events (faults, retries, interruptions, safeguard actions) and, at the
  end, the summary (the ``summary.json`` document) that marks the run finished.

Crash safety
------------
The database runs in WAL mode with ``synchronous=FULL``; each ``add_*`` call is one
``BEGIN IMMEDIATE ... COMMIT`` transaction, so a process killed at any instant (SIGKILL, power
loss) leaves either the whole record or nothing. Triggers reject ``UPDATE`` and ``DELETE``
on every table: the journal is append-only. A journal is created under a temporary name and
renamed into place, so a half-created journal never exists under the final name.

Resume (REPLAY design)
----------------------
``run --resume DIR`` re-reads procedure text, seed, backend and strategy from
:meth:`Journal.run_info` and reruns the deterministic loop; whenever the loop needs measurement
``n`` and the journal holds it, the stored one is used instead of measuring again.

Example
-------
>>> import tempfile, pathlib
>>> from setmem_hil.model.experiment import Measurement
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> j = Journal.create(d / "journal.sqlite", procedure_text="name = 'x'", procedure_name="x",
...                    seed=1, software_version="0.1.0", backend="sim", strategy="mu")
>>> j.add_measurement(Measurement(1.0, 0.5 - 0.1j, 0.01), iteration=0, role="initial")
1
>>> j.measurements()[0].response
(0.5-0.1j)
>>> j.close()
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import threading
from dataclasses import dataclass, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import InputFormatError, JournalError
from setmem_hil.io.atomic_file import json_safe
from setmem_hil.model.experiment import Measurement
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.model.mu_floor import floor_modes

__all__ = ["Journal", "IterationRecord", "JournalError", "JournalSnapshot", "read_snapshot", "JOURNAL_FILENAME", "journal_path", "ROLES"]

JOURNAL_FILENAME = "journal.sqlite"
APPLICATION_ID = 0x53454D48  # "SEMH": marks an SQLite file as a setmem-hil journal
SCHEMA_VERSION = 8  # 2: measurement.rig_s; 3: iteration.controller; 4: iteration.mu_peak_certified,
# mu_certified_intervals; 5: measurement.others, iteration.outputs; 6: iteration.common_gain; 7:
# run.design, iteration.design, floor_modes; 8: iteration.groups (older journals are upgraded when opened)
ROLES = ("initial", "added")


@dataclass(frozen=True)
class IterationRecord:
    """What one pass of the loop (chapter 5) computed, as stored in the journal.

    Attributes
    ----------
    k : int
        1-based iteration (identification with the data so far).
    n_points : int
        Number of measurements used.
    lower, upper : numpy.ndarray
        ``(n_modes, 4)`` parameter bounds in the order a1, a0, b1, b0 (eq. 5.4-5.5).
    mu_peak, mu_peak_omega, mu_lower_peak : float
        Peak of the mu upper bound, where it is attained, and the peak lower bound.
    omega, mu : numpy.ndarray
        Analysis grid and mu-bar upper bound on it (figure 6-13).
    sensitivities : dict
        ``'<param>_<mode>' -> float`` mu-sensitivities (appendix B).
    next_omega : float or None
        Frequency chosen for the next experiment; None when the loop stops.
    candidate_omega, estimated_improvement : numpy.ndarray
        Candidate frequencies and their estimated mu-bar improvement (figure 6-14).
    controller_order : int
        Order of the controller analysed.
    safeguard : str
        Branch of eq. 5.12: ``"new-design"``, ``"expanded"`` or ``"previous-controller"``.
    wall_s : float
        Compute time of the iteration.
    embedding_gamma, mismatch_ratio : numpy.ndarray
        ``(n_modes,)`` conservatism measures of the identification (section 3.2.3).
    controller : dict or None
        The compensator the safeguard kept, ``{"A", "B", "C", "D"}`` (lists of lists; rad/s time
        base, positive feedback ``u = K y``); None in journals written before it was stored.
    mu_peak_certified : bool or None
        Whether ``mu_peak`` was certified on the whole band, not only at grid points (issue 27);
        None in journals written before it was.
    mu_certified_intervals : int or None
        Number of frequency intervals in that certificate.
    common_gain : dict or None
        With sampled sensors whose calibration is one scale per output (issue 26:
        :mod:`setmem_hil.identification.calibration_scale`): ``{"gain": [k_lo, k_hi], "lower":
        [...], "upper": [...]}``, the plant is ``k`` times the model as measured (``lower``,
        ``upper``) with one ``k`` in the interval; ``mu_peak`` is of that set, and the
        iteration's ``lower``/``upper`` are its interval hull. None otherwise.
    outputs : dict or None
        With several sensors (issue 25): ``{"names": [...], "lower": [...], "upper": [...]}``,
        every output's ``(n_modes, 4)`` bounds (shared ``a1, a0``, own ``b1, b0``; the first is
        the control output, whose bounds are also ``lower``/``upper``); None with one sensor.
    design : str or None
        The design that made the compensator the safeguard kept: ``"robust"`` or ``"h2"``
        (issue 38). Journals from before it read ``"h2"`` (every compensator then was H2).
    floor_modes : tuple of int or None
        1-based modes whose box holds an undamped, zero-residue plant
        (:mod:`setmem_hil.model.mu_floor`); computed from ``lower``/``upper`` for older journals.
    """

    k: int
    n_points: int
    lower: np.ndarray
    upper: np.ndarray
    mu_peak: float
    mu_peak_omega: float
    mu_lower_peak: float
    omega: np.ndarray
    mu: np.ndarray
    sensitivities: dict
    next_omega: float | None
    candidate_omega: np.ndarray
    estimated_improvement: np.ndarray
    controller_order: int
    safeguard: str
    wall_s: float
    embedding_gamma: np.ndarray
    mismatch_ratio: np.ndarray
    controller: dict | None = None
    mu_peak_certified: bool | None = None
    mu_certified_intervals: int | None = None
    outputs: dict | None = None
    common_gain: dict | None = None
    design: str | None = None
    floor_modes: tuple[int, ...] | None = None
    groups: tuple[tuple[int, ...], ...] | None = None  # 0-based modes identified together (issue 47); None: not recorded


_ARRAY_FIELDS = ("lower", "upper", "omega", "mu", "candidate_omega", "estimated_improvement", "embedding_gamma", "mismatch_ratio")
_ITERATION_COLUMNS = tuple(f.name for f in fields(IterationRecord))

_SCHEMA = """
CREATE TABLE run (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    procedure_text TEXT NOT NULL,
    procedure_name TEXT NOT NULL,
    seed INTEGER NOT NULL,
    software_version TEXT NOT NULL,
    backend TEXT NOT NULL,
    strategy TEXT NOT NULL,
    created_utc TEXT NOT NULL,
    design TEXT NOT NULL DEFAULT 'h2'
);
CREATE TABLE measurement (
    seq INTEGER PRIMARY KEY CHECK (seq >= 1),
    iteration INTEGER NOT NULL,
    role TEXT NOT NULL CHECK (role IN ('initial', 'added')),
    omega_rad_s REAL NOT NULL,
    re REAL NOT NULL,
    im REAL NOT NULL,
    bound REAL NOT NULL,
    utc TEXT NOT NULL,
    rig_s REAL NOT NULL DEFAULT 0,
    others TEXT
);
CREATE TABLE iteration (
    k INTEGER PRIMARY KEY CHECK (k >= 1),
    n_points INTEGER NOT NULL,
    lower TEXT NOT NULL,
    upper TEXT NOT NULL,
    mu_peak REAL,
    mu_peak_omega REAL,
    mu_lower_peak REAL,
    omega TEXT NOT NULL,
    mu TEXT NOT NULL,
    sensitivities TEXT NOT NULL,
    next_omega REAL,
    candidate_omega TEXT NOT NULL,
    estimated_improvement TEXT NOT NULL,
    controller_order INTEGER NOT NULL,
    safeguard TEXT NOT NULL,
    wall_s REAL NOT NULL,
    embedding_gamma TEXT NOT NULL,
    mismatch_ratio TEXT NOT NULL,
    utc TEXT NOT NULL,
    controller TEXT,
    mu_peak_certified INTEGER,
    mu_certified_intervals INTEGER,
    outputs TEXT,
    common_gain TEXT,
    design TEXT,
    floor_modes TEXT,
    groups TEXT
);
CREATE TABLE discrepancy (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    iteration INTEGER NOT NULL,
    report TEXT NOT NULL,
    utc TEXT NOT NULL
);
CREATE TABLE event (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL,
    message TEXT NOT NULL,
    utc TEXT NOT NULL
);
CREATE TABLE finish (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    summary TEXT NOT NULL,
    utc TEXT NOT NULL
);
"""

_TABLES = ("run", "measurement", "iteration", "discrepancy", "event", "finish")


def _append_only_triggers() -> str:
    out = []
    for table in _TABLES:
        for op in ("UPDATE", "DELETE"):
            out.append(
                f"CREATE TRIGGER {table}_no_{op.lower()} BEFORE {op} ON {table} "
                f"BEGIN SELECT RAISE(ABORT, 'journal is append-only: {op} on {table} refused'); END;"
            )
    return "\n".join(out)


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _to_json(value: Any) -> str:
    """Strict JSON text (issue 39: SQLite's ``json_valid`` and every other reader accept it); a
    non-finite number is ``null``. An array keeps what its nulls were (:func:`_array_to_json`)."""
    if isinstance(value, np.ndarray):
        return _array_to_json(value)
    return json.dumps(json_safe(value), allow_nan=False, default=_json_default)


def _array_to_json(array: np.ndarray) -> str:
    """A finite array as a plain JSON list; one with non-finite entries as
    ``{"values": [... null ...], "nonfinite": [[flat index, "inf" | "-inf" | "nan"], ...]}``:
    valid JSON with nulls, and read back bit for bit (:func:`_array_from_json`)."""
    a = np.asarray(array, dtype=float)
    bad = np.flatnonzero(~np.isfinite(a.ravel()))
    if not bad.size:
        return json.dumps(a.tolist(), allow_nan=False)
    tags = [[int(i), "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")] for i, x in zip(bad, a.ravel()[bad])]
    return json.dumps({"values": json_safe(a.tolist()), "nonfinite": tags}, allow_nan=False)


def _floats_to_json(mapping: Mapping[str, float]) -> str:
    """A name -> number mapping (the mu-sensitivities) as :func:`_array_to_json` stores arrays."""
    values = {str(k): float(v) for k, v in mapping.items()}
    bad = [[k, "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")] for k, v in values.items() if not math.isfinite(v)]
    doc = {"values": json_safe(values), "nonfinite": bad} if bad else values
    return json.dumps(doc, allow_nan=False)


def _floats_from_json(text: str) -> dict[str, float]:
    doc = json.loads(text)
    if set(doc) == {"values", "nonfinite"} and isinstance(doc["values"], dict):
        values = {k: math.nan if v is None else float(v) for k, v in doc["values"].items()}
        values.update({k: float(tag) for k, tag in doc["nonfinite"]})
        return values
    return {k: float(x) for k, x in doc.items()}


def _array_from_json(text: str) -> np.ndarray:
    """An array stored by :func:`_array_to_json` (or, before issue 39, a list that may hold the
    ``NaN``/``Infinity`` tokens Python's json reads)."""
    doc = json.loads(text)
    if not isinstance(doc, dict):
        return np.asarray(doc, dtype=float)

    def nulls_as_nan(v):
        return [nulls_as_nan(x) for x in v] if isinstance(v, list) else (math.nan if v is None else v)

    a = np.asarray(nulls_as_nan(doc["values"]), dtype=float)
    flat = a.reshape(-1)
    for index, tag in doc["nonfinite"]:
        flat[int(index)] = float(tag)
    return a


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in the journal")


def _opt_float(value: Any) -> float | None:
    return None if value is None else float(value)


def journal_path(path: str | os.PathLike) -> Path:
    """``path`` itself, or ``path/journal.sqlite`` when ``path`` is a directory."""
    p = Path(path)
    return p / JOURNAL_FILENAME if p.is_dir() else p


class Journal:
    """Append-only SQLite journal of one campaign (see the module docstring).

    Use :meth:`create` for a new run and :meth:`open` for an existing one (resume, report,
    export). Every ``add_*`` method commits before it returns. Usable as a context manager.
    """

    def __init__(self, conn: sqlite3.Connection, path: Path):
        self._conn: sqlite3.Connection | None = conn
        self.path = path
        self._lock = threading.Lock()
        self._wrote = False

    # ------------------------------------------------------------------ opening
    @staticmethod
    def _connect(path: Path) -> sqlite3.Connection:
        conn = sqlite3.connect(str(path), isolation_level=None, check_same_thread=False, timeout=30.0)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        conn.execute("PRAGMA foreign_keys=ON")
        return conn

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        *,
        procedure_text: str,
        procedure_name: str,
        seed: int,
        software_version: str,
        backend: str,
        strategy: str,
        design: str = "robust",
    ) -> "Journal":
        """Create the journal of a new run; refuses to overwrite an existing one.

        Raises
        ------
        InputFormatError
            If a file already exists at ``path`` (or ``path/journal.sqlite`` for a directory).
        """
        p = journal_path(path)
        if p.exists():
            raise InputFormatError(str(p), "", "a journal already exists here; resume it with `setmem-hil run --resume` or choose another --out directory")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise InputFormatError(str(p), "seed", f"expected an integer, found {seed!r}")
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = p.with_name(p.name + ".creating")
        for stale in (tmp, Path(str(tmp) + "-wal"), Path(str(tmp) + "-shm"), Path(str(tmp) + "-journal")):
            if stale.exists():
                stale.unlink()
        # Build under a temporary name in rollback-journal mode, then rename: a crash here
        # never leaves a half-made journal under the final name.
        conn = sqlite3.connect(str(tmp), isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode=DELETE")
            conn.execute("BEGIN")
            for stmt in _SCHEMA.split(";"):
                if stmt.strip():
                    conn.execute(stmt)
            for stmt in _append_only_triggers().splitlines():
                conn.execute(stmt)
            conn.execute(
                "INSERT INTO run (id, procedure_text, procedure_name, seed, software_version, backend, strategy, created_utc, design)"
                " VALUES (1, ?, ?, ?, ?, ?, ?, ?, ?)",
                (str(procedure_text), str(procedure_name), int(seed), str(software_version), str(backend), str(strategy), _utc_now(),
                 str(design)),
            )
            conn.execute(f"PRAGMA application_id={APPLICATION_ID}")
            conn.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            conn.execute("COMMIT")
        except BaseException:
            conn.close()
            tmp.unlink(missing_ok=True)
            raise
        conn.close()
        if p.exists():  # lost a race with another creator
            tmp.unlink(missing_ok=True)
            raise InputFormatError(str(p), "", "a journal already exists here")
        os.replace(tmp, p)
        return cls(cls._connect(p), p)

    @classmethod
    def open(cls, path: str | os.PathLike) -> "Journal":
        """Open an existing journal (a file or a run directory).

        Raises
        ------
        InputFormatError
            If the file is missing or is not a setmem-hil journal.
        """
        p = journal_path(path)
        if not p.is_file():
            raise InputFormatError(str(p), "", "no journal here (expected a run directory holding journal.sqlite)")
        try:
            with open(p, "rb") as fh:
                header = fh.read(16)
        except OSError as exc:
            raise InputFormatError(str(p), "", f"cannot read: {exc}") from None
        if header != b"SQLite format 3\x00":
            raise InputFormatError(str(p), "", "not a journal (not an SQLite database)")
        try:
            conn = cls._connect(p)
            app_id = conn.execute("PRAGMA application_id").fetchone()[0]
            version = conn.execute("PRAGMA user_version").fetchone()[0]
        except sqlite3.DatabaseError as exc:
            raise InputFormatError(str(p), "", f"not a readable journal: {exc}") from None
        if app_id != APPLICATION_ID:
            conn.close()
            raise InputFormatError(str(p), "", "not a setmem-hil journal (SQLite application_id differs)")
        upgrades = {1: "ALTER TABLE measurement ADD COLUMN rig_s REAL NOT NULL DEFAULT 0",  # rig time: 0 for what it holds
                    2: "ALTER TABLE iteration ADD COLUMN controller TEXT",  # compensators: NULL for what it holds
                    3: "ALTER TABLE iteration ADD COLUMN mu_peak_certified INTEGER;"
                       "ALTER TABLE iteration ADD COLUMN mu_certified_intervals INTEGER",  # NULL: not known
                    4: "ALTER TABLE measurement ADD COLUMN others TEXT;"
                       "ALTER TABLE iteration ADD COLUMN outputs TEXT",  # NULL: one sensor
                    5: "ALTER TABLE iteration ADD COLUMN common_gain TEXT",  # NULL: no calibration scale
                    6: "ALTER TABLE run ADD COLUMN design TEXT NOT NULL DEFAULT 'h2';"  # every earlier run designed with H2
                       "ALTER TABLE iteration ADD COLUMN design TEXT;"
                       "ALTER TABLE iteration ADD COLUMN floor_modes TEXT",
                    7: "ALTER TABLE iteration ADD COLUMN groups TEXT"}  # NULL: written before groups were recorded
        while version in upgrades:
            try:
                for statement in upgrades[version].split(";"):
                    conn.execute(statement)
                conn.execute(f"PRAGMA user_version={version + 1}")
                conn.commit()
                version += 1
            except sqlite3.DatabaseError as exc:
                conn.close()
                raise InputFormatError(str(p), "", f"cannot upgrade the version-{version} journal: {exc}") from None
        if version != SCHEMA_VERSION:
            conn.close()
            raise InputFormatError(str(p), "", f"journal schema version {version}; this software reads version {SCHEMA_VERSION}")
        return cls(conn, p)

    def close(self) -> None:
        """Close the journal (idempotent). All records are already committed."""
        with self._lock:
            if self._conn is not None:
                if self._wrote:  # fold the WAL into the main file; readers (report, export) never wait for this
                    try:
                        self._conn.execute("PRAGMA busy_timeout = 200")
                        self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
                    except sqlite3.DatabaseError:
                        pass  # another connection is busy; the data is safe in the WAL regardless
                self._conn.close()
                self._conn = None

    @property
    def closed(self) -> bool:
        return self._conn is None

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Journal({str(self.path)!r}{', closed' if self.closed else ''})"

    # ------------------------------------------------------------------ plumbing
    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise JournalError(f"{self.path}: journal is closed")
        return self._conn

    def _write(self, sql: str, params: tuple) -> sqlite3.Cursor:
        """One statement in one committed transaction."""
        with self._lock:
            db = self._db()
            db.execute("BEGIN IMMEDIATE")
            try:
                cur = db.execute(sql, params)
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            self._wrote = True
            return cur

    def _query(self, sql: str, params: tuple = ()) -> list[sqlite3.Row]:
        with self._lock:
            db = self._db()
            try:
                cur = db.execute(sql, params)
                names = [d[0] for d in cur.description]
                return [dict(zip(names, row)) for row in cur.fetchall()]
            except sqlite3.DatabaseError as exc:  # damaged pages: found only when read (issue 40: was exit 1)
                raise InputFormatError(str(self.path), "", f"the journal is damaged ({exc}); `sqlite3 {self.path.name} .recover` "
                                       "may save what it holds") from None

    # ------------------------------------------------------------------ run
    def run_info(self) -> dict:
        """The run's identity: procedure text and name, seed, version, backend, strategy, state."""
        rows = self._query("SELECT * FROM run WHERE id = 1")
        if not rows:
            raise InputFormatError(str(self.path), "table run", "not a journal (no run record)")
        info = dict(rows[0])
        info.pop("id", None)
        fin = self._query("SELECT summary, utc FROM finish WHERE id = 1")
        info["finished"] = bool(fin)
        info["summary"] = json.loads(fin[0]["summary"]) if fin else None
        info["finished_utc"] = fin[0]["utc"] if fin else None
        return info

    def finish(self, summary: dict) -> None:
        """Store the summary (the ``summary.json`` document) and mark the run finished."""
        try:
            self._write("INSERT INTO finish (id, summary, utc) VALUES (1, ?, ?)", (_to_json(dict(summary)), _utc_now()))
        except sqlite3.IntegrityError:
            raise JournalError(f"{self.path}: run already finished") from None

    # ------------------------------------------------------------------ measurements
    def add_measurement(self, m: Measurement, *, iteration: int, role: str) -> int:
        """Append one measurement; committed before return. Returns its 1-based sequence number.

        Parameters
        ----------
        m : Measurement
            The measured frequency, response and error bound.
        iteration : int
            Loop iteration that requested it (0 for the initial points).
        role : {"initial", "added"}
            Initial design point or a point chosen by input design.
        """
        if role not in ROLES:
            raise JournalError(f"{self.path}: measurement role {role!r}; expected one of {', '.join(ROLES)}")
        omega, g, bound, rig_s = float(m.omega_rad_s), complex(m.response), float(m.bound), float(m.rig_s)
        others = [[complex(r).real, complex(r).imag, float(b)] for r, b in m.others]
        if not (math.isfinite(omega) and math.isfinite(g.real) and math.isfinite(g.imag) and math.isfinite(bound) and math.isfinite(rig_s)
                and all(math.isfinite(v) for row in others for v in row)):
            raise JournalError(f"{self.path}: refusing a non-finite measurement at omega {omega:g} rad/s")
        with self._lock:
            db = self._db()
            db.execute("BEGIN IMMEDIATE")
            try:
                seq = db.execute("SELECT COALESCE(MAX(seq), 0) + 1 FROM measurement").fetchone()[0]
                db.execute(
                    "INSERT INTO measurement (seq, iteration, role, omega_rad_s, re, im, bound, utc, rig_s, others) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (seq, int(iteration), role, omega, g.real, g.imag, bound, _utc_now(), rig_s, _to_json(others) if others else None),
                )
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")
            self._wrote = True
        return int(seq)

    def measurement_rows(self) -> list[dict]:
        """Rows ``seq, iteration, role, omega_rad_s, re, im, bound, utc, rig_s, others`` in sequence
        order (``others``: JSON ``[[re, im, bound], ...]`` of the other sensors, or None)."""
        return self._query("SELECT seq, iteration, role, omega_rad_s, re, im, bound, utc, rig_s, others FROM measurement ORDER BY seq")

    def measurements(self) -> list[Measurement]:
        """All stored measurements in sequence order."""
        return [Measurement(r["omega_rad_s"], complex(r["re"], r["im"]), r["bound"], r["rig_s"], _others(r["others"]))
                for r in self.measurement_rows()]

    def n_measurements(self) -> int:
        return int(self._query("SELECT COUNT(*) AS n FROM measurement")[0]["n"])

    # ------------------------------------------------------------------ iterations
    def add_iteration(self, record: IterationRecord) -> None:
        """Append one iteration's results; a second record for the same ``k`` is refused."""
        values = []
        for name in _ITERATION_COLUMNS:
            v = getattr(record, name)
            if name in _ARRAY_FIELDS:
                v = _to_json(np.asarray(v, dtype=float))
            elif name == "sensitivities":
                v = _floats_to_json(v)
            elif name in ("k", "n_points", "controller_order"):
                v = int(v)
            elif name == "safeguard":
                v = str(v)
            elif name == "controller":
                v = None if v is None else _to_json({key: np.asarray(v[key], dtype=float).tolist() for key in "ABCD"})
            elif name in ("mu_peak_certified", "mu_certified_intervals"):
                v = None if v is None else int(v)
            elif name in ("outputs", "common_gain"):
                v = None if v is None else _to_json(v)
            elif name == "design":
                v = None if v is None else str(v)
            elif name == "floor_modes":
                v = None if v is None else _to_json([int(m) for m in v])
            elif name == "groups":
                v = None if v is None else _to_json([[int(m) for m in group] for group in v])
            else:
                v = _opt_float(v)
            values.append(v)
        cols = ", ".join(_ITERATION_COLUMNS) + ", utc"
        marks = ", ".join("?" * (len(_ITERATION_COLUMNS) + 1))
        try:
            self._write(f"INSERT INTO iteration ({cols}) VALUES ({marks})", tuple(values) + (_utc_now(),))
        except sqlite3.IntegrityError as exc:
            raise JournalError(f"{self.path}: iteration {record.k} is already stored ({exc})") from None

    def iterations(self) -> list[IterationRecord]:
        """All stored iterations, ordered by ``k``."""
        out = []
        for row in self._query(f"SELECT {', '.join(_ITERATION_COLUMNS)} FROM iteration ORDER BY k"):
            kw: dict[str, Any] = {}
            for name in _ITERATION_COLUMNS:
                v = row[name]
                if name in _ARRAY_FIELDS:
                    v = _array_from_json(v)
                elif name == "sensitivities":
                    v = _floats_from_json(v)
                elif name in ("mu_peak", "mu_peak_omega", "mu_lower_peak", "wall_s"):
                    v = math.nan if v is None else float(v)
                elif name == "controller":
                    v = None if v is None else json.loads(v)
                elif name == "mu_peak_certified":
                    v = None if v is None else bool(v)
                elif name in ("outputs", "common_gain"):
                    v = None if v is None else json.loads(v)
                elif name == "floor_modes":
                    v = None if v is None else tuple(int(m) for m in json.loads(v))
                elif name == "groups":
                    v = None if v is None else tuple(tuple(int(m) for m in group) for group in json.loads(v))
                kw[name] = v
            for name in ("lower", "upper"):
                kw[name] = kw[name].reshape(-1, 4)
            if kw["design"] is None:  # written before issue 38: every compensator was an H2 design
                kw["design"] = "h2"
            if kw["floor_modes"] is None:
                kw["floor_modes"] = floor_modes(IntervalModel(kw["lower"], kw["upper"]))
            out.append(IterationRecord(**kw))
        return out

    # ------------------------------------------------------------------ discrepancy, events
    def add_discrepancy(self, iteration: int, report: dict) -> None:
        """Store the result of a discrepancy check (a JSON-able dict) for ``iteration``."""
        self._write("INSERT INTO discrepancy (iteration, report, utc) VALUES (?, ?, ?)", (int(iteration), _to_json(dict(report)), _utc_now()))

    def discrepancies(self) -> list[tuple[int, dict]]:
        return [(int(r["iteration"]), json.loads(r["report"])) for r in self._query("SELECT iteration, report FROM discrepancy ORDER BY id")]

    def add_event(self, kind: str, message: str) -> None:
        """Record a fault, retry, interruption, resume or safeguard action."""
        self._write("INSERT INTO event (kind, message, utc) VALUES (?, ?, ?)", (str(kind), str(message), _utc_now()))

    def events(self) -> list[dict]:
        """Events ``{"id", "kind", "message", "utc"}`` in the order recorded."""
        return self._query("SELECT id, kind, message, utc FROM event ORDER BY id")

    # ------------------------------------------------------------------ checks
    def integrity_problems(self) -> list[str]:
        """Problems found by SQLite's integrity check and the journal's own invariants (empty if sound)."""
        problems = [r["integrity_check"] for r in self._query("PRAGMA integrity_check") if r["integrity_check"] != "ok"]
        seqs = [r["seq"] for r in self._query("SELECT seq FROM measurement ORDER BY seq")]
        if seqs != list(range(1, len(seqs) + 1)):
            problems.append(f"measurement sequence numbers are not 1..{len(seqs)} without gaps")
        ks = [r["k"] for r in self._query("SELECT k FROM iteration ORDER BY k")]
        if ks != list(range(1, len(ks) + 1)):
            problems.append(f"iterations are not 1..{len(ks)} without gaps")
        return problems


@dataclass(frozen=True)
class JournalSnapshot:
    """Everything a journal holds, read in one go (report, export and live view all need it whole)."""

    info: dict
    measurements: list
    rows: list
    iterations: list
    discrepancies: list
    events: list


def read_snapshot(run_dir: str | os.PathLike) -> JournalSnapshot:
    """Open the journal of ``run_dir`` (or the file), read everything, close it."""
    j = Journal.open(run_dir)
    try:
        return JournalSnapshot(j.run_info(), j.measurements(), j.measurement_rows(), j.iterations(), j.discrepancies(), j.events())
    finally:
        j.close()


def _others(text: str | None) -> tuple[tuple[complex, float], ...]:
    """The ``others`` column back as ``((response, bound), ...)``."""
    if not text:
        return ()
    return tuple((complex(re, im), float(b)) for re, im, b in json.loads(text))
