"""Frequencies in the user's unit: Hz keys beside the rad/s keys of procedure and prior files.

Every file key that holds a frequency in rad/s (``omega_min``, ``omega_min_rad_s``,
``omega_rad_s``, ``log_spaced.min``...) may instead be given in hertz by the same name with
``_hz`` (``omega_min_hz``, ``omega_min_hz``, ``omega_hz``, ``min_hz``): the value (or each value
of a list) is multiplied by 2 pi and stored under the rad/s key. Giving both is an error.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

from setmem_hil.errors import InputFormatError

__all__ = ["hz_keys_to_rad_s", "HZ_SUFFIX"]

HZ_SUFFIX = "_hz"


def _twin(key: str, known: set[str]) -> str | None:
    stem = key[: -len(HZ_SUFFIX)]
    for candidate in (stem + "_rad_s", stem):
        if candidate in known:
            return candidate
    return None


def hz_keys_to_rad_s(doc: Any, known_by_table: Mapping[str, Iterable[str]], source: str, table: str = "") -> Any:
    """``doc`` with every ``<x>_hz`` key converted to its rad/s twin, table by table
    (``known_by_table`` maps a dotted table name, ``""`` for the top level, to its keys)."""
    if isinstance(doc, list):
        return [hz_keys_to_rad_s(v, known_by_table, source, table) for v in doc]
    if not isinstance(doc, Mapping):
        return doc
    known = set(known_by_table.get(table, ()))
    out: dict[str, Any] = {}
    for key, value in doc.items():
        name = str(key)
        twin = _twin(name, known) if name.endswith(HZ_SUFFIX) else None
        if twin is None:
            sub = f"{table}.{name}" if table else name
            out[name] = hz_keys_to_rad_s(value, known_by_table, source, sub) if isinstance(value, (Mapping, list)) else value
            continue
        if twin in doc:
            raise InputFormatError(source, f"key '{name}'", f"give {twin} (rad/s) or {name} (Hz), not both")
        out[twin] = _to_rad_s(value, source, name)
    return out


def _to_rad_s(value: Any, source: str, key: str) -> Any:
    def one(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputFormatError(source, f"key '{key}'", f"expected a frequency in Hz, found {v!r}")
        return float(v) * 2.0 * math.pi

    return [one(v) for v in value] if isinstance(value, list) else one(value)
