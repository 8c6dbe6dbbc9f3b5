"""Inputs of ``setmem-hil analyze``: the control-design weights of a file, and a model the
analysis can mean (refused with a message naming mode and parameter otherwise)."""

from __future__ import annotations

import math
from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

__all__ = ["read_weights_table", "weights_for", "check_model"]

_WEIGHT_KEYS = ("w1_num", "w1_den", "w2_num", "w2_den", "w2_extra_pole_rad_s")


def read_weights_table(path: str) -> Weights:
    """The ``[weights]`` table of a TOML file that holds nothing else the analysis needs."""
    import tomllib

    try:
        doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputFormatError(path, "", f"cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputFormatError(path, "", f"invalid TOML: {exc}") from None
    table = doc.get("weights", {})
    if not isinstance(table, dict):
        raise InputFormatError(path, "[weights]", f"expected a table, found {type(table).__name__}")
    kwargs = {}
    for key, value in table.items():
        if key not in _WEIGHT_KEYS:
            raise InputFormatError(path, f"[weights] key '{key}'", f"unknown key; expected one of {', '.join(_WEIGHT_KEYS)}")
        if key == "w2_extra_pole_rad_s":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise InputFormatError(path, f"[weights] key '{key}'", f"expected a non-negative number, found {value!r}")
            kwargs[key] = float(value) or None
        else:
            if not isinstance(value, list) or not value or not all(
                isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in value
            ):
                raise InputFormatError(path, f"[weights] key '{key}'", f"expected a list of numbers, found {value!r}")
            kwargs[key] = tuple(float(c) for c in value)
    return Weights(**kwargs) if kwargs else THESIS_WEIGHTS


def weights_for(procedure_path: str | None) -> Weights:
    """Weights of a procedure file (``[weights]``; a file with only that table is enough), or the
    thesis's when no file is given. A full procedure is validated as a whole."""
    if procedure_path is None:
        return THESIS_WEIGHTS
    from setmem_hil.model.prior import load_toml

    if "mode" in load_toml(procedure_path):
        from setmem_hil.io.procedure_file import load_procedure

        return load_procedure(procedure_path).weights
    return read_weights_table(procedure_path)


def check_model(model, source: str) -> None:
    """Refuse a model the analysis cannot mean: non-finite or absurd bounds, natural frequencies
    not bounded away from zero (``a0 <= 0``), negative damping (``a1 < 0``)."""
    from setmem_hil.model.frequency_data import MAX_MAGNITUDE
    from setmem_hil.model.modal_model import PARAM_NAMES

    for i in range(model.n_modes):
        for j, name in enumerate(PARAM_NAMES):
            lo, hi = float(model.lower[i, j]), float(model.upper[i, j])
            where = f"mode {i + 1} {name}"
            if not (math.isfinite(lo) and math.isfinite(hi)) or max(abs(lo), abs(hi)) > MAX_MAGNITUDE:
                raise InputFormatError(source, where, f"[{lo:g}, {hi:g}]: the analysis needs finite bounds below {MAX_MAGNITUDE:g}")
        if model.lower[i, 1] <= 0:
            raise InputFormatError(source, f"mode {i + 1} a0", f"lower bound {model.lower[i, 1]:g} must be > 0 (a0 = omega_n^2 of a vibration mode)")
        if model.lower[i, 0] < 0:
            raise InputFormatError(source, f"mode {i + 1} a1", f"lower bound {model.lower[i, 0]:g} must be >= 0 (a1 = 2 zeta omega_n, no negative damping)")
