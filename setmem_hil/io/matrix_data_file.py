"""The FRF matrix CSV: header ``sensor,exciter,omega,re,im,bound`` (public contract, issue 64).

One row per measured point of one input-output pair: the sensor's and the exciter's names, then
the columns of the data CSV (:mod:`setmem_hil.io.data_file`: ``omega`` in rad/s, ``re``/``im`` the
measured ``G_kl(j omega)``, ``bound`` the absolute bound on its total error). Sensors and exciters
are numbered in the order they first appear. Errors name the file, the line and the column.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.io.data_file import parse_cell
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["MATRIX_COLUMNS", "MatrixData", "parse_matrix_csv", "read_matrix_csv", "matrix_csv_text"]

MATRIX_COLUMNS = ("sensor", "exciter", "omega", "re", "im", "bound")


class MatrixData:
    """The pairs' data: ``columns[(k, l)]`` for sensor ``k`` driven by exciter ``l``."""

    def __init__(self, sensors: tuple[str, ...], exciters: tuple[str, ...], columns: dict[tuple[int, int], FrequencyData]):
        self.sensors, self.exciters, self.columns = sensors, exciters, columns

    @property
    def n_points(self) -> int:
        return sum(d.omega_rad_s.size for d in self.columns.values())


def parse_matrix_csv(text: str, source: str = "<matrix>") -> MatrixData:
    """Parse an FRF matrix CSV; raise :class:`InputFormatError` naming line and column."""
    text = text.removeprefix("\ufeff")
    try:
        rows = [(i + 1, r) for i, r in enumerate(csv.reader(io.StringIO(text, newline=""))) if any(c.strip() for c in r)]
    except csv.Error as exc:
        raise InputFormatError(source, "", f"not a CSV file: {exc}") from None
    if not rows:
        raise InputFormatError(source, "", f"empty file; expected header {','.join(MATRIX_COLUMNS)}")
    header_line, header = rows[0]
    if [h.strip().lower() for h in header] != list(MATRIX_COLUMNS):
        raise InputFormatError(source, f"line {header_line}", f"expected header {','.join(MATRIX_COLUMNS)}, found {','.join(header)}")
    sensors: dict[str, int] = {}
    exciters: dict[str, int] = {}
    points: dict[tuple[int, int], list[tuple[float, complex, float]]] = {}
    for line, row in rows[1:]:
        if len(row) != len(MATRIX_COLUMNS):
            raise InputFormatError(source, f"line {line}", f"expected {len(MATRIX_COLUMNS)} columns, found {len(row)}")
        sensor, exciter = row[0].strip(), row[1].strip()
        for name, value in (("sensor", sensor), ("exciter", exciter)):
            if not value:
                raise InputFormatError(source, f"line {line}", f"column {name}: expected a name, found an empty cell")
        w, re_, im_, bound = (parse_cell(c, n, source, line) for c, n in zip(row[2:], MATRIX_COLUMNS[2:]))
        if w <= 0:
            raise InputFormatError(source, f"line {line}", f"column omega: expected a positive frequency, found {w:g}")
        if bound < 0:
            raise InputFormatError(source, f"line {line}", f"column bound: expected a non-negative bound, found {bound:g}")
        key = (sensors.setdefault(sensor, len(sensors)), exciters.setdefault(exciter, len(exciters)))
        points.setdefault(key, []).append((w, complex(re_, im_), bound))
    if not points:
        raise InputFormatError(source, "", "no data rows after the header")
    columns = {}
    for key, rows_ in points.items():
        order = sorted(range(len(rows_)), key=lambda k: rows_[k][0])
        columns[key] = FrequencyData(np.array([rows_[k][0] for k in order]), np.array([rows_[k][1] for k in order]),
                                     np.array([rows_[k][2] for k in order]))
    return MatrixData(tuple(sensors), tuple(exciters), columns)


def read_matrix_csv(path: str | Path) -> MatrixData:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputFormatError(str(path), "", "no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(str(path), "", f"cannot be read as text: {exc}") from None
    return parse_matrix_csv(text, str(path))


def matrix_csv_text(data: MatrixData) -> str:
    """The CSV of ``data`` (every pair, sensors then exciters in order; full precision)."""
    out = [",".join(MATRIX_COLUMNS)]
    for (k, l) in sorted(data.columns):
        d = data.columns[(k, l)]
        for w, g, b in zip(d.omega_rad_s, d.response, d.bound):
            out.append(f"{data.sensors[k]},{data.exciters[l]},{float(w)!r},{float(g.real)!r},{float(g.imag)!r},{float(b)!r}")
    return "\n".join(out) + "\n"
