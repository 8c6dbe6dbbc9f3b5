"""A TOML table checked against a schema: the procedure format's and the verification's share it.

One reader for every TOML input of the project (:mod:`setmem_hil.io.procedure_file`,
:mod:`setmem_hil.io.target_file`), so a key is checked and a bad value named the same way in both:
the file, the table, the key, what was found and what was expected.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Any, Mapping

from setmem_hil.errors import ProcedureError

__all__ = ["REQUIRED", "CheckedTable", "KeySpec", "describe_value", "type_name", "unknown_key"]

REQUIRED = "required"  # a KeySpec's default when the key must be given


@dataclass(frozen=True)
class KeySpec:
    """One key of a TOML format (its table, name, kind, unit, default, meaning and range).

    ``kind``: ``number`` (finite float), ``integer``, ``bool``, ``string``, ``choice`` (one of
    ``choices``), ``numbers`` (non-empty list of finite floats), ``strings``, ``table``
    (sub-table with its own keys), ``free-table`` (passed through unchecked), ``tables``
    (array of tables). Bounds ``gt``/``ge``/``le`` apply to numbers and integers.
    """

    table: str
    key: str
    kind: str
    unit: str
    default: Any
    meaning: str
    choices: tuple = ()
    gt: float | None = None
    ge: float | None = None
    le: float | None = None


def describe_value(v: Any) -> str:
    """A value as a message shows it (numbers short, long texts cut)."""
    if isinstance(v, float):
        return f"{v:g}"
    text = repr(v) if isinstance(v, str) else str(v)
    return text if len(text) <= 60 else text[:57] + "..."


def unknown_key(mapping: Mapping, allowed: list[str]) -> str | None:
    """The first key of ``mapping`` not in ``allowed``, as a message naming the closest allowed
    one and listing them in the order given; ``None`` when every key is known."""
    for key in mapping:
        if key not in allowed:
            close = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            return f"unknown key {key!r}{hint} (allowed: {', '.join(allowed)})"
    return None


def type_name(v: Any) -> str:
    """'a number', 'a string', ...: what a value is, for messages."""
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string", list: "an array", dict: "a table"}.get(type(v), type(v).__name__)


class CheckedTable:
    """A parsed TOML table checked against ``schema`` (table name -> key -> :class:`KeySpec`), plus
    where it is, for messages: an unknown key is named with the closest known one, a value of the
    wrong type or out of its range with what was expected."""

    def __init__(self, source: str, name: str, mapping: Any, schema: Mapping[str, Mapping[str, KeySpec]],
                 location: str | None = None):
        self.source, self.name, self.schema = source, name, schema
        self.location = location or (f"[{name}]" if name else "top level")
        if not isinstance(mapping, Mapping):
            raise self.error(f"expected a table, found {type_name(mapping)} {describe_value(mapping)}")
        self.mapping = mapping
        problem = unknown_key(mapping, list(schema.get(name, {})))
        if problem:
            raise self.error(problem)

    def error(self, problem: str) -> ProcedureError:
        return ProcedureError(self.source, self.location, problem)

    def has(self, key: str) -> bool:
        return key in self.mapping

    def sub(self, key: str) -> "CheckedTable":
        return CheckedTable(self.source, f"{self.name}.{key}" if self.name else key, self.mapping.get(key, {}), self.schema)

    def value(self, key: str) -> Any:
        """The key's value, or its schema's default when absent (an error when it is required)."""
        default = self.schema[self.name][key].default
        return self.get(key, None if default == REQUIRED else default)

    def get(self, key: str, default: Any = None) -> Any:
        """The key's value checked, ``default`` when absent (an error when the schema requires it
        and no default is given)."""
        spec = self.schema[self.name][key]
        if key not in self.mapping:
            if default is None and spec.default == REQUIRED:
                raise self.error(f"missing key {key!r} ({spec.meaning})")
            return default
        v = self.mapping[key]
        kind = spec.kind
        if kind == "number":
            return self._bounded(spec, self._number(key, v))
        if kind == "integer":
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.error(f"{key}: expected an integer, found {type_name(v)} {describe_value(v)}")
            return int(self._bounded(spec, v))
        if kind == "bool":
            if not isinstance(v, bool):
                raise self.error(f"{key}: expected true or false, found {type_name(v)} {describe_value(v)}")
            return v
        if kind in ("string", "choice"):
            if not isinstance(v, str):
                raise self.error(f"{key}: expected a string, found {type_name(v)} {describe_value(v)}")
            if kind == "choice" and v not in spec.choices:
                raise self.error(f"{key} {v!r} is not one of {', '.join(repr(c) for c in spec.choices)}")
            return v
        if kind == "numbers":
            if not isinstance(v, list) or not v:
                raise self.error(f"{key}: expected a non-empty array of numbers, found {type_name(v)} {describe_value(v)}")
            return tuple(self._bounded(spec, self._number(f"{key}[{i}]", x), f"{key}[{i}]") for i, x in enumerate(v))
        if kind == "output":  # an output by index from 1 or by name
            if isinstance(v, str) and v:
                return v
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.error(f"{key}: expected an index from 1 or a name, found {type_name(v)} {describe_value(v)}")
            return int(self._bounded(spec, v))
        if kind == "names":  # one name, or an array of distinct names
            names = [v] if isinstance(v, str) else v
            if not isinstance(names, list) or not names or not all(isinstance(x, str) and x for x in names):
                raise self.error(f"{key}: expected a name or a non-empty array of names, found {type_name(v)} {describe_value(v)}")
            if len(set(names)) != len(names):
                raise self.error(f"{key}: each name once, found {describe_value(v)}")
            return tuple(names)
        if kind == "strings":
            if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                raise self.error(f"{key}: expected an array of strings, found {type_name(v)} {describe_value(v)}")
            return tuple(v)
        raise AssertionError(f"schema kind {kind!r} read through get()")  # pragma: no cover (programming error)

    def _number(self, key: str, v: Any) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.error(f"{key}: expected a number, found {type_name(v)} {describe_value(v)}")
        x = float(v)
        if not math.isfinite(x):
            raise self.error(f"{key}: expected a finite number, found {describe_value(v)}")
        return x

    def _bounded(self, spec: KeySpec, x: float, label: str | None = None) -> float:
        label = label or spec.key
        if spec.gt is not None and not x > spec.gt:
            raise self.error(f"{label} {describe_value(x)} must be > {describe_value(spec.gt)}")
        if spec.ge is not None and not x >= spec.ge:
            raise self.error(f"{label} {describe_value(x)} must be >= {describe_value(spec.ge)}")
        if spec.le is not None and not x <= spec.le:
            raise self.error(f"{label} {describe_value(x)} must be <= {describe_value(spec.le)}")
        return x
