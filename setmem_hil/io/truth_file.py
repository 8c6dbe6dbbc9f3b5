"""A simulated structure's truth file (issue 47, item 4; public contract).

``[backend.simulation] truth = "FILE.toml"`` (a path relative to the procedure file) replaces the
simulated cantilever with the file's modes, so that a lab can rehearse a campaign on its own
structure. One ``[[mode]]`` table per mode:

- ``omega_rad_s`` (or ``omega_hz``, not both): the natural frequency, positive;
- ``zeta``: the damping ratio, in ``[0, 1)``;
- ``b0``, and optionally ``b1`` (default 0): the residue of ``(b1 s + b0) / (s^2 + 2 zeta omega s +
  omega^2)``, the force-to-displacement receptance at the sensor.

The modes are sorted by frequency; the prior models the lowest ``n`` (its number of modes), and
every higher mode is unmodelled dynamics (see :mod:`setmem_hil.sim_backends.simulated_beam`).

**Several exciters and sensors** (issue 64): top-level ``exciters = ["x", ...]`` and
``sensors = ["x", ...]`` (names, each once), and per mode ``shape_in`` (one number per exciter)
and ``shape_out`` (one per sensor): the mode's shape there, so that its residue from exciter
``l`` to sensor ``k`` is ``shape_out[k] * shape_in[l] * (b1 s + b0)``
(:class:`~setmem_hil.model.modal_matrix.ModalMatrix`, :func:`read_truth_matrix`). Such a file is
a structure for several exciters; the one-exciter reader refuses it by name.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from setmem_hil.errors import ProcedureError
from setmem_hil.model.prior import load_toml

TRUTH_MODE_KEYS = ("omega_rad_s", "omega_hz", "zeta", "b0", "b1")
SHAPE_KEYS = ("shape_in", "shape_out")
PLACES = ("exciters", "sensors")


def _number(value: Any, source: str, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise ProcedureError(source, f"{where} key '{key}'", f"expected a finite number, found {value!r}")
    return float(value)


def parse_truth_modes(doc: Any, source: str) -> tuple[tuple[float, float, float, float], ...]:
    """``((omega_rad_s, zeta, b0, b1), ...)`` sorted by frequency, from a parsed truth file."""
    modes = doc.get("mode") if isinstance(doc, dict) else None
    if not isinstance(modes, list) or not modes:
        raise ProcedureError(source, "[[mode]]", "expected at least one [[mode]] table with omega_rad_s (or omega_hz), zeta and b0")
    if any(k in doc for k in PLACES) or any(isinstance(m, dict) and any(k in m for k in SHAPE_KEYS) for m in modes):
        raise ProcedureError(source, "exciters / sensors", "this truth file gives mode shapes at several exciters and sensors: "
                             "a structure for several exciters (read_truth_matrix), not a one-exciter simulation's")
    extra = [k for k in doc if k != "mode"]
    if extra:
        raise ProcedureError(source, f"key '{extra[0]}'", "unknown top-level key (a truth file holds [[mode]] tables only)")
    out = []
    for i, mode in enumerate(modes, start=1):
        where = f"[[mode]] {i}"
        if not isinstance(mode, dict):
            raise ProcedureError(source, where, f"expected a table, found {mode!r}")
        unknown = [k for k in mode if k not in TRUTH_MODE_KEYS]
        if unknown:
            raise ProcedureError(source, f"{where} key '{unknown[0]}'", f"unknown key (known: {', '.join(TRUTH_MODE_KEYS)})")
        if ("omega_rad_s" in mode) == ("omega_hz" in mode):
            raise ProcedureError(source, f"{where} key 'omega_rad_s'", "give the natural frequency once: omega_rad_s or omega_hz")
        omega = (_number(mode["omega_rad_s"], source, where, "omega_rad_s") if "omega_rad_s" in mode
                 else 2 * math.pi * _number(mode["omega_hz"], source, where, "omega_hz"))
        if not omega > 0:
            raise ProcedureError(source, f"{where} key '{'omega_rad_s' if 'omega_rad_s' in mode else 'omega_hz'}'", f"expected a positive frequency, found {omega:g} rad/s")
        for key in ("zeta", "b0"):
            if key not in mode:
                raise ProcedureError(source, f"{where} key '{key}'", "missing")
        zeta = _number(mode["zeta"], source, where, "zeta")
        if not 0.0 <= zeta < 1.0:
            raise ProcedureError(source, f"{where} key 'zeta'", f"expected a damping ratio in [0, 1), found {zeta:g}")
        b0 = _number(mode["b0"], source, where, "b0")
        b1 = _number(mode.get("b1", 0.0), source, where, "b1")
        out.append((omega, zeta, b0, b1))
    return tuple(sorted(out))


def read_truth_file(path: str | Path, source: str) -> tuple[tuple[float, float, float, float], ...]:
    """Read and validate a truth file; errors name the file, the mode and the key."""
    path = Path(path)
    if not path.is_file():
        raise ProcedureError(source, "[backend.simulation] key 'truth'", f"no truth file at {path}")
    return parse_truth_modes(load_toml(path), str(path))  # a TOML syntax error names its line


def _names(doc: dict, key: str, source: str) -> tuple[str, ...]:
    names = doc.get(key)
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n.strip() for n in names):
        raise ProcedureError(source, f"key '{key}'", f"expected a list of names, found {names!r}")
    if len(set(names)) != len(names):
        raise ProcedureError(source, f"key '{key}'", f"each name once, found {names!r}")
    return tuple(names)


def parse_truth_matrix(doc: Any, source: str):
    """A :class:`~setmem_hil.model.modal_matrix.ModalMatrix` from a parsed truth file with
    ``exciters``, ``sensors`` and each mode's ``shape_in`` / ``shape_out`` (module docstring);
    errors name the file, the mode and the key."""
    from setmem_hil.model.modal_matrix import ModalMatrix
    from setmem_hil.model.modal_model import ModalParameters

    if not isinstance(doc, dict):
        raise ProcedureError(source, "", "expected a TOML table")
    exciters, sensors = _names(doc, "exciters", source), _names(doc, "sensors", source)
    extra = [k for k in doc if k not in ("mode",) + PLACES]
    if extra:
        raise ProcedureError(source, f"key '{extra[0]}'", "unknown top-level key (known: exciters, sensors, [[mode]])")
    modes = doc.get("mode")
    if not isinstance(modes, list) or not modes:
        parse_truth_modes({}, source)  # its error: at least one [[mode]]
    rows, shapes = [], []
    for i, mode in enumerate(modes, start=1):
        if not isinstance(mode, dict):
            raise ProcedureError(source, f"[[mode]] {i}", f"expected a table, found {mode!r}")
        try:  # the mode's own keys, validated as a one-exciter file's
            (row,) = parse_truth_modes({"mode": [{k: v for k, v in mode.items() if k not in SHAPE_KEYS}]}, source)
        except ProcedureError as exc:
            raise ProcedureError(source, exc.location.replace("[[mode]] 1", f"[[mode]] {i}"), exc.problem) from None
        shape = []
        for key, names in (("shape_out", sensors), ("shape_in", exciters)):
            values = mode.get(key)
            if not isinstance(values, list) or len(values) != len(names):
                raise ProcedureError(source, f"[[mode]] {i} key '{key}'", f"expected {len(names)} numbers (one per name in "
                                     f"{'sensors' if key == 'shape_out' else 'exciters'}), found {values!r}")
            shape.append([_number(v, source, f"[[mode]] {i}", key) for v in values])
        rows.append(row)
        shapes.append(shape)
    order = sorted(range(len(rows)), key=lambda k: rows[k])  # as ModalParameters.from_mode_table sorts (stable)
    rows = [rows[k] for k in order]
    shape_out = np.array([shapes[k][0] for k in order])
    shape_in = np.array([shapes[k][1] for k in order])
    return ModalMatrix(ModalParameters.from_mode_table(rows), shape_out, shape_in, sensors, exciters)


def read_truth_matrix(path: str | Path, source: str):
    """Read and validate a truth file of several exciters and sensors (:func:`parse_truth_matrix`)."""
    path = Path(path)
    if not path.is_file():
        raise ProcedureError(source, "truth", f"no truth file at {path}")
    return parse_truth_matrix(load_toml(path), str(path))
