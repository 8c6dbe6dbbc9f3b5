"""CSV export of a run's journal (``setmem-hil export DIR --csv OUT/``).

Files written to ``OUT/`` (UTF-8, comma-separated, header row, floats with full precision,
empty cell for "none", ``inf``/``nan`` spelled so):

``measurements.csv``
    ``seq, iteration, role, omega_rad_s, re, im, bound, utc, rig_s``: every measurement in order;
    ``iteration`` is the loop iteration that asked for it (0 = initial design), ``rig_s`` the
    device seconds its dwell took.
``data.csv``
    ``omega, re, im, bound``: the same measurements in the data-CSV format that
    ``setmem-hil identify --data`` reads, in ascending frequency (``measurements.csv`` keeps the
    measurement order; a plot of ``data.csv`` is a curve, not a zigzag).
``bounds.csv``
    ``k, n_points, mode, parameter, lower, upper, name``: the parameter intervals of every iteration
    (``name`` is the parameter's one name, ``a1_1``, as in RESULT.json and sensitivities.csv)
    (modes from 1; parameters a1, a0, b1, b0 of eq. 2.24), as the appendix B tables.
``mu.csv``
    ``k, omega_rad_s, mu``: mu-bar (upper bound) on the analysis grid per iteration (figure 6-13).
``iterations.csv``
    ``k, n_points, mu_peak, mu_peak_omega, mu_lower_peak, next_omega, safeguard,
    controller_order, wall_s, design, floor_modes``: one row per iteration (figure 6-12);
    ``design`` is ``robust`` or ``h2`` (the design that made the kept compensator, issue 38),
    ``floor_modes`` the modes whose box blocks every compensator, joined by ``;`` (empty: none).
``sensitivities.csv``
    ``k, parameter, sensitivity``: mu-sensitivities per iteration (appendix B).
``candidates.csv``
    ``k, omega_rad_s, estimated_improvement``: the input-design scores (figure 6-14).
``events.csv``
    ``id, utc, kind, message``: faults, retries, interruptions, resumes, safeguard actions.

Several sensors (issue 25): ``measurements.csv`` gains an ``output`` column, one row per
sensor per dwell (the same ``seq``), the control output first; ``bounds.csv`` gains ``output``
with every output's intervals; ``data.csv`` holds the control output and ``data_<k>.csv`` the
k-th output (k from 2), each ready for ``setmem-hil identify --data data.csv --data data_2.csv ...``.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Iterable, Sequence

from setmem_hil.io.atomic_file import write_text_atomic
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.io.journal import read_snapshot
from setmem_hil.model.modal_model import PARAM_NAMES

__all__ = ["export_csv", "EXPORT_FILES"]

EXPORT_FILES = (
    "measurements.csv", "data.csv", "bounds.csv", "mu.csv", "iterations.csv",
    "sensitivities.csv", "candidates.csv", "events.csv",
)


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    return str(v)


def _csv_text(header: Sequence[str], rows: Iterable[Sequence]) -> str:
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow([_cell(v) for v in row])
    return out.getvalue()


def _write(path: Path, text: str) -> None:
    write_text_atomic(path, text)


def export_csv(run_dir: str | os.PathLike, out_dir: str | os.PathLike) -> list[Path]:
    """Write the CSV files listed in the module docstring; returns their paths.

    Parameters
    ----------
    run_dir : path
        A run directory (or its ``journal.sqlite``).
    out_dir : path
        Created if missing; existing files of the same names are replaced.

    Raises
    ------
    InputFormatError
        If ``run_dir`` holds no journal.
    """
    snap = read_snapshot(run_dir)
    rows, measurements, iterations, events = snap.rows, snap.measurements, snap.iterations, snap.events
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, str] = {}
    cols = ("seq", "iteration", "role", "omega_rad_s", "re", "im", "bound", "utc", "rig_s")
    names = _output_names(snap)
    if names:
        files["measurements.csv"] = _csv_text(cols + ("output",), _rows_per_output(rows, cols, names))
        from setmem_hil.io.data_file import format_data_csv

        for k in range(1, len(names)):
            files[f"data_{k + 1}.csv"] = format_data_csv(FrequencyData.from_measurements(measurements, output=k).sorted_by_frequency())
    else:
        files["measurements.csv"] = _csv_text(cols, ([r[c] for c in cols] for r in rows))
    if measurements:
        from setmem_hil.io.data_file import format_data_csv

        files["data.csv"] = format_data_csv(FrequencyData.from_measurements(measurements).sorted_by_frequency())
    else:
        files["data.csv"] = "omega,re,im,bound\n"
    if names:
        files["bounds.csv"] = _csv_text(
            ("k", "n_points", "mode", "parameter", "lower", "upper", "name", "output"),
            (
                (rec.k, rec.n_points, i + 1, name, float(lo[i][j]), float(hi[i][j]), f"{name}_{i + 1}", out_name)
                for rec in iterations if rec.outputs
                for out_name, lo, hi in zip(rec.outputs["names"], rec.outputs["lower"], rec.outputs["upper"])
                for i in range(len(lo)) for j, name in enumerate(PARAM_NAMES)
            ),
        )
    else:
        files["bounds.csv"] = _csv_text(
            ("k", "n_points", "mode", "parameter", "lower", "upper", "name"),
            (
                (rec.k, rec.n_points, i + 1, name, float(rec.lower[i, j]), float(rec.upper[i, j]), f"{name}_{i + 1}")
                for rec in iterations for i in range(rec.lower.shape[0]) for j, name in enumerate(PARAM_NAMES)
            ),
        )
    files["mu.csv"] = _csv_text(
        ("k", "omega_rad_s", "mu"),
        ((rec.k, float(w), float(m)) for rec in iterations for w, m in zip(rec.omega, rec.mu)),
    )
    files["iterations.csv"] = _csv_text(
        ("k", "n_points", "mu_peak", "mu_peak_omega", "mu_lower_peak", "next_omega", "safeguard", "controller_order", "wall_s",
         "design", "floor_modes"),
        (
            (rec.k, rec.n_points, float(rec.mu_peak), float(rec.mu_peak_omega), float(rec.mu_lower_peak),
             None if rec.next_omega is None else float(rec.next_omega), rec.safeguard, rec.controller_order, float(rec.wall_s),
             rec.design, ";".join(str(m) for m in rec.floor_modes or ()))
            for rec in iterations
        ),
    )
    files["sensitivities.csv"] = _csv_text(
        ("k", "parameter", "sensitivity"),
        ((rec.k, name, float(v)) for rec in iterations for name, v in sorted(rec.sensitivities.items(), key=lambda kv: _param_order(kv[0]))),
    )
    files["candidates.csv"] = _csv_text(
        ("k", "omega_rad_s", "estimated_improvement"),
        ((rec.k, float(w), float(e)) for rec in iterations for w, e in zip(rec.candidate_omega, rec.estimated_improvement)),
    )
    files["events.csv"] = _csv_text(("id", "utc", "kind", "message"), ((e["id"], e["utc"], e["kind"], e["message"]) for e in events))
    paths = []
    for name in EXPORT_FILES + tuple(sorted(n for n in files if n not in EXPORT_FILES)):
        _write(out / name, files[name])
        paths.append(out / name)
    return paths


def _output_names(snap) -> tuple[str, ...]:
    """The outputs' names (control first) of a run with several sensors, else ``()``."""
    if not any(m.others for m in snap.measurements):
        return ()
    from setmem_hil.io.procedure_file import parse_procedure_text

    return parse_procedure_text(snap.info["procedure_text"], "stored procedure").backend.output_order()


def _rows_per_output(rows, cols, names):
    """One row per sensor per dwell: the stored row for the control output, then the others."""
    import json

    for r in rows:
        yield [r[c] for c in cols] + [names[0]]
        for k, (re, im, bound) in enumerate(json.loads(r["others"] or "[]"), start=1):
            yield [r["seq"], r["iteration"], r["role"], r["omega_rad_s"], re, im, bound, r["utc"], r["rig_s"], names[k]]


def _param_order(key: str) -> tuple[int, int, str]:
    """Sort ``a1_1, a0_1, b1_1, b0_1, a1_2, ...`` (mode, then parameter order of eq. 2.24)."""
    name, _, mode = key.rpartition("_")
    try:
        return (int(mode), PARAM_NAMES.index(name), key)
    except ValueError:
        return (10**9, 0, key)
