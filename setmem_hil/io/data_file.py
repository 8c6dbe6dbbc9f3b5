"""The data CSV: header ``omega,re,im,bound`` (public contract, see README).

``omega`` in rad/s, ``re``/``im`` the measured ``G(j omega)``, ``bound`` the absolute bound on
its total error (noise plus unmodelled dynamics). All rows are used. Errors name the file and
line (:class:`setmem_hil.errors.InputFormatError`).
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.model.frequency_data import MAX_MAGNITUDE, FrequencyData

DATA_COLUMNS = ("omega", "re", "im", "bound")


def parse_cell(cell: str, name: str, source: str, line: int) -> float:
    """One numeric cell of a data file: a finite number within the identification's range
    (:data:`~setmem_hil.model.frequency_data.MAX_MAGNITUDE`), else an error naming line and column."""
    try:
        v = float(cell)
    except ValueError:
        raise InputFormatError(source, f"line {line}", f"column {name}: expected a number, found {cell.strip()!r}") from None
    if not math.isfinite(v):
        raise InputFormatError(source, f"line {line}", f"column {name}: expected a finite number, found {cell.strip()}")
    if abs(v) > MAX_MAGNITUDE:
        raise InputFormatError(source, f"line {line}", f"column {name}: {cell.strip()} is outside the range the "
                               f"identification computes with (|x| <= {MAX_MAGNITUDE:g}; check the units)")
    return v


def parse_data_csv(text: str, source: str = "<data>") -> FrequencyData:
    """Parse the text of a data CSV; raise :class:`InputFormatError` naming line and column.

    A byte-order mark (spreadsheets write one) is ignored."""
    text = text.removeprefix("\ufeff")
    try:
        rows = list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as exc:
        raise InputFormatError(source, "", f"not a CSV file: {exc}") from None
    rows = [(i + 1, r) for i, r in enumerate(rows) if any(cell.strip() for cell in r)]
    if not rows:
        raise InputFormatError(source, "", f"empty file; expected header {','.join(DATA_COLUMNS)}")
    header_line, header = rows[0]
    names = [h.strip().lower() for h in header]
    if names != list(DATA_COLUMNS):
        raise InputFormatError(source, f"line {header_line}", f"expected header {','.join(DATA_COLUMNS)}, found {','.join(header)}")
    values = []
    for line, row in rows[1:]:
        if len(row) != 4:
            raise InputFormatError(source, f"line {line}", f"expected 4 columns, found {len(row)}")
        parsed = [parse_cell(cell, name, source, line) for name, cell in zip(DATA_COLUMNS, row)]
        if parsed[0] <= 0:
            raise InputFormatError(source, f"line {line}", f"column omega: expected a positive frequency, found {parsed[0]:g}")
        if parsed[3] < 0:
            raise InputFormatError(source, f"line {line}", f"column bound: expected a non-negative bound, found {parsed[3]:g}")
        values.append(parsed)
    if not values:
        raise InputFormatError(source, "", "no data rows after the header")
    arr = np.array(values)
    return FrequencyData(arr[:, 0], arr[:, 1] + 1j * arr[:, 2], arr[:, 3])


def read_data_csv(path: str | os.PathLike) -> FrequencyData:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(str(path), "", f"cannot read: {exc}") from None
    return parse_data_csv(text, str(path))


def format_data_csv(data: FrequencyData) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(DATA_COLUMNS)
    for w, g, r in zip(data.omega_rad_s, data.response, data.bound):
        writer.writerow([repr(float(w)), repr(float(g.real)), repr(float(g.imag)), repr(float(r))])
    return out.getvalue()


def write_data_csv(data: FrequencyData, path: str | os.PathLike) -> None:
    Path(path).write_text(format_data_csv(data), encoding="utf-8")
