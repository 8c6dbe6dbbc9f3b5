"""The closed-loop verification's procedure: ``[target]``, ``[target.emulation]`` and ``[verify]``
(``setmem-hil verify RUN_DIR --procedure TARGET.toml``; docs/real-time-target.md).

The structure, its box and the compensator come from the run (its stored procedure and
journal); this file says what runs the compensator and how the loop is measured. Every key is
checked as the campaign's procedure's are: an unknown key is named with the closest known one,
a value outside its range with the range.
"""

from __future__ import annotations

import difflib
import math
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from setmem_hil.errors import ProcedureError

__all__ = ["is_verification_procedure", "TargetSettings", "TargetEmulationSettings", "VerifySettings", "VerifyProcedure", "load_target_procedure",
           "parse_target_text", "TARGET_KINDS"]

TARGET_KINDS = ("emulated", "serial")


@dataclass(frozen=True)
class TargetEmulationSettings:
    """Hidden effects of the emulated rig (tests of what the model leaves out) and its faults."""

    extra_delay_samples: int = 0
    dac_gain: float = 1.0
    antialias_corner_hz: float | None = None
    drop_link_after_lines: int | None = None
    undamped: bool = False
    noise_rms: float = 1e-5


@dataclass(frozen=True)
class TargetSettings:
    kind: str
    fs_hz: float
    delay_samples: int
    drive_limit: float
    port: str = ""
    baudrate: int = 115200
    watchdog_s: float = 0.5
    emulation: TargetEmulationSettings = field(default_factory=TargetEmulationSettings)


@dataclass(frozen=True)
class VerifySettings:
    """How the loop is engaged and measured."""

    gains: tuple[float, ...] = (0.25, 0.5, 1.0)
    injection_amplitude: float = 0.05
    periods: int = 20
    settle_s: float | None = None  # default: from the predicted closed loop's slowest pole
    frequencies_rad_s: tuple[float, ...] = ()  # default: chosen from the prediction
    response_limit: float | None = None  # bypass when |y| exceeds it (the structure's safe travel)


@dataclass(frozen=True)
class VerifyProcedure:
    name: str
    target: TargetSettings
    verify: VerifySettings
    source_text: str = ""


REQUIRED = "required"
# table -> key -> (kind, default (REQUIRED: must be given), lower bound (exclusive), upper bound (inclusive))
_KEYS: dict[str, dict[str, tuple]] = {
    "": {"name": ("string", "closed-loop"), "description": ("string", ""), "target": ("table", REQUIRED), "verify": ("table", {})},
    "target": {"kind": ("choice", REQUIRED), "fs_hz": ("number", REQUIRED, 0.0), "delay_samples": ("integer", 1, -1, 64),
               "drive_limit": ("number", REQUIRED, 0.0), "port": ("string", ""), "baudrate": ("integer", 115200, 0),
               "watchdog_s": ("number", 0.5, -1e-300), "emulation": ("table", {})},
    "target.emulation": {"extra_delay_samples": ("integer", 0, -1, 64), "dac_gain": ("number", 1.0, 0.0),
                         "antialias_corner_hz": ("number", None, 0.0), "drop_link_after_lines": ("integer", None, 0),
                         "undamped": ("bool", False), "noise_rms": ("number", 1e-5, -1e-300)},
    "verify": {"gains": ("numbers", (0.25, 0.5, 1.0), 0.0, 2.0), "injection_amplitude": ("number", 0.05, 0.0),
               "periods": ("integer", 20, 2), "settle_s": ("number", None, 0.0), "frequencies_rad_s": ("numbers", (), 0.0),
               "response_limit": ("number", None, 0.0)},
}


class _Table:
    def __init__(self, source: str, name: str, mapping: Any):
        self.source, self.name = source, name
        if not isinstance(mapping, Mapping):
            raise self.error(f"expected a table, found {mapping!r}")
        self.mapping = mapping
        for key in mapping:
            if key not in _KEYS[name]:
                close = difflib.get_close_matches(str(key), list(_KEYS[name]), n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                raise self.error(f"unknown key {key!r}{hint} (allowed: {', '.join(_KEYS[name])})")

    def error(self, problem: str) -> ProcedureError:
        return ProcedureError(self.source, f"[{self.name}]" if self.name else "top level", problem)

    def get(self, key: str) -> Any:
        kind, default, *bounds = _KEYS[self.name][key]
        if key not in self.mapping:
            if default is REQUIRED:
                raise self.error(f"missing key {key!r}")
            return default
        v = self.mapping[key]
        if kind == "table":
            return v
        if kind in ("string", "choice"):
            if not isinstance(v, str):
                raise self.error(f"{key}: expected a string, found {v!r}")
            if kind == "choice" and v not in TARGET_KINDS:
                raise self.error(f"{key} {v!r} is not one of {', '.join(repr(k) for k in TARGET_KINDS)}")
            return v
        if kind == "bool":
            if not isinstance(v, bool):
                raise self.error(f"{key}: expected true or false, found {v!r}")
            return v
        if kind == "numbers":
            if not isinstance(v, list) or not v:
                raise self.error(f"{key}: expected a non-empty array of numbers, found {v!r}")
            return tuple(self._number(f"{key}[{i}]", x, bounds) for i, x in enumerate(v))
        if kind == "integer":
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.error(f"{key}: expected an integer, found {v!r}")
            return int(self._number(key, v, bounds))
        return self._number(key, v, bounds)

    def _number(self, key: str, v: Any, bounds) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise self.error(f"{key}: expected a finite number, found {v!r}")
        if bounds and not float(v) > bounds[0]:
            raise self.error(f"{key} {v!r} must be > {max(bounds[0], 0):g}" if bounds[0] >= 0 else f"{key} {v!r} must be >= 0")
        if len(bounds) > 1 and not float(v) <= bounds[1]:
            raise self.error(f"{key} {v!r} must be <= {bounds[1]:g}")
        return float(v)


def is_verification_procedure(text: str) -> bool:
    """Does this TOML text have a top-level ``[target]`` table (a verification procedure, not a campaign's)?"""
    try:
        return isinstance(tomllib.loads(text).get("target"), Mapping)
    except tomllib.TOMLDecodeError:
        return False


def parse_target_text(text: str, source: str = "<target>") -> VerifyProcedure:
    """Validate a TARGET.toml text (see the module docstring)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProcedureError(source, "", f"not valid TOML: {exc}") from None
    top = _Table(source, "", doc)
    if "target" not in doc:
        raise top.error("missing table [target] (kind, fs_hz, delay_samples, drive_limit)")
    if "verify" not in doc:
        doc = {**doc, "verify": {}}
    t = _Table(source, "target", top.get("target"))
    e = _Table(source, "target.emulation", t.get("emulation"))
    v = _Table(source, "verify", top.get("verify"))
    kind = t.get("kind")
    if kind == "serial" and not t.get("port"):
        raise t.error("kind = \"serial\" needs port (e.g. \"/dev/ttyACM0\")")
    if kind == "serial" and e.mapping:
        raise t.error("[target.emulation] is for kind = \"emulated\" only")
    emulation = TargetEmulationSettings(
        extra_delay_samples=e.get("extra_delay_samples"), dac_gain=e.get("dac_gain"), antialias_corner_hz=e.get("antialias_corner_hz"),
        drop_link_after_lines=e.get("drop_link_after_lines"), undamped=e.get("undamped"), noise_rms=e.get("noise_rms"))
    target = TargetSettings(kind=kind, fs_hz=t.get("fs_hz"), delay_samples=t.get("delay_samples"), drive_limit=t.get("drive_limit"),
                            port=t.get("port"), baudrate=t.get("baudrate"), watchdog_s=t.get("watchdog_s"), emulation=emulation)
    gains = v.get("gains")
    if list(gains) != sorted(gains):
        raise v.error(f"gains {list(gains)} must ascend (each step engaged after the one before)")
    verify = VerifySettings(gains=gains, injection_amplitude=v.get("injection_amplitude"), periods=v.get("periods"),
                            settle_s=v.get("settle_s"), frequencies_rad_s=v.get("frequencies_rad_s"), response_limit=v.get("response_limit"))
    if verify.injection_amplitude >= target.drive_limit:
        raise v.error(f"injection_amplitude {verify.injection_amplitude:g} must be below [target] drive_limit {target.drive_limit:g}")
    return VerifyProcedure(top.get("name"), target, verify, text)


def load_target_procedure(path: str | os.PathLike) -> VerifyProcedure:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProcedureError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    return parse_target_text(text, str(p))
