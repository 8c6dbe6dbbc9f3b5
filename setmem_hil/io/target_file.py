"""The closed-loop verification's procedure: ``[target]``, ``[target.emulation]`` and ``[verify]``
(``setmem-hil verify RUN_DIR --procedure TARGET.toml``; docs/real-time-target.md).

The structure, its box and the compensator come from the run (its stored procedure and
journal); this file says what runs the compensator and how the loop is measured. Every key is
checked as the campaign's procedure's are: an unknown key is named with the closest known one,
a value outside its range with the range.
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from setmem_hil.errors import ProcedureError
from setmem_hil.io.toml_table import REQUIRED, CheckedTable, KeySpec

__all__ = ["is_verification_procedure", "TargetSettings", "TargetEmulationSettings", "VerifySettings", "VerifyProcedure", "load_target_procedure",
           "parse_target_text", "SCHEMA", "TARGET_KINDS", "MEASURE_KINDS"]

TARGET_KINDS = ("emulated", "serial")
MEASURE_KINDS = ("recorder", "analyser")
"""How a point is measured: ``recorder``, the rig's recorder of injection, drive and response (the
emulated rig's; samples kept), or ``analyser``, the target's own analyser (its sums kept)."""


@dataclass(frozen=True)
class TargetEmulationSettings:
    """Hidden effects of the emulated rig (tests of what the model leaves out) and its faults."""

    extra_delay_samples: int = 0
    dac_gain: float = 1.0
    antialias_corner_hz: float | None = None
    drop_link_after_lines: int | None = None
    undamped: bool = False
    noise_rms: float = 1e-5
    force_channel: bool = False


@dataclass(frozen=True)
class TargetSettings:
    kind: str
    fs_hz: float
    delay_samples: int
    drive_limit: float
    port: str = ""
    baudrate: int = 115200
    watchdog_s: float = 0.5
    measure: str = "recorder"  # MEASURE_KINDS
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


def _key(table: str, key: str, kind: str, unit: str, default: Any, meaning: str, **bounds) -> KeySpec:
    return KeySpec(table, key, kind, unit, default, meaning, **bounds)


SCHEMA: tuple[KeySpec, ...] = (
    _key("", "name", "string", "", "closed-loop", "the verification's name"),
    _key("", "description", "string", "", "", "free text"),
    _key("", "target", "table", "", REQUIRED, "what runs the compensator"),
    _key("", "verify", "table", "", {}, "how the loop is engaged and measured"),
    _key("target", "kind", "choice", "", REQUIRED, "the target", choices=TARGET_KINDS),
    _key("target", "fs_hz", "number", "Hz", REQUIRED, "the target's sample rate", gt=0.0),
    _key("target", "delay_samples", "integer", "samples", 1, "computation delay: u[k] written at tick k + delay", ge=0, le=64),
    _key("target", "drive_limit", "number", "drive units", REQUIRED, "the largest |drive| before the target trips", gt=0.0),
    _key("target", "port", "string", "", "", "serial port (kind = \"serial\")"),
    _key("target", "baudrate", "integer", "bit/s", 115200, "serial line rate", gt=0),
    _key("target", "watchdog_s", "number", "s", 0.5, "bypass when the host is silent this long", ge=0.0),
    _key("target", "measure", "choice", "", None, "how a point is measured (default: \"recorder\" for an emulated target, "
         "\"analyser\" for a serial one)", choices=MEASURE_KINDS),
    _key("target", "emulation", "table", "", {}, "the emulated rig's hidden effects (kind = \"emulated\")"),
    _key("target.emulation", "extra_delay_samples", "integer", "samples", 0, "delay the model does not know", ge=0, le=64),
    _key("target.emulation", "dac_gain", "number", "", 1.0, "drive gain the model does not know", gt=0.0),
    _key("target.emulation", "antialias_corner_hz", "number", "Hz", None, "first-order lag the model does not know", gt=0.0),
    _key("target.emulation", "drop_link_after_lines", "integer", "lines", None, "the link dies after this many lines", gt=0),
    _key("target.emulation", "undamped", "bool", "", False, "every mode's damping removed"),
    _key("target.emulation", "noise_rms", "number", "", 1e-5, "sensor noise", ge=0.0),
    _key("target.emulation", "force_channel", "bool", "", False, "the board's second ADC reads the force at the structure's input "
         "(SUMS? F: the side of an effect is told)"),
    _key("verify", "gains", "numbers", "", (0.25, 0.5, 1.0), "gain steps, ascending", gt=0.0, le=2.0),
    _key("verify", "injection_amplitude", "number", "drive units", 0.05, "the injected sine's amplitude", gt=0.0),
    _key("verify", "periods", "integer", "periods", 20, "periods recorded per point", gt=2),
    _key("verify", "settle_s", "number", "s", None, "wait before recording (default: the predicted loop's slowest pole)", gt=0.0),
    _key("verify", "frequencies_rad_s", "numbers", "rad/s", (), "points (default: chosen from the prediction)", gt=0.0),
    _key("verify", "response_limit", "number", "", None, "bypass when |y| exceeds it", gt=0.0),
)
_BY_TABLE: dict[str, dict[str, KeySpec]] = {}
for _spec in SCHEMA:
    _BY_TABLE.setdefault(_spec.table, {})[_spec.key] = _spec


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
    top = CheckedTable(source, "", doc, _BY_TABLE)
    if "target" not in doc:
        raise top.error("missing table [target] (kind, fs_hz, delay_samples, drive_limit)")
    t, v = top.sub("target"), top.sub("verify")
    e = t.sub("emulation")
    kind = t.value("kind")
    if kind == "serial" and not t.value("port"):
        raise t.error("kind = \"serial\" needs port (e.g. \"/dev/ttyACM0\")")
    if kind == "serial" and e.mapping:
        raise t.error("[target.emulation] is for kind = \"emulated\" only")
    measure = t.value("measure") or ("analyser" if kind == "serial" else "recorder")
    if kind == "serial" and measure == "recorder":
        raise t.error("measure = \"recorder\" needs a recorder beside the rig, which a serial target does not have yet: "
                      "use measure = \"analyser\" (the target's own)")
    emulation = TargetEmulationSettings(
        extra_delay_samples=e.value("extra_delay_samples"), dac_gain=e.value("dac_gain"), antialias_corner_hz=e.value("antialias_corner_hz"),
        drop_link_after_lines=e.value("drop_link_after_lines"), undamped=e.value("undamped"), noise_rms=e.value("noise_rms"),
        force_channel=e.value("force_channel"))
    target = TargetSettings(kind=kind, fs_hz=t.value("fs_hz"), delay_samples=t.value("delay_samples"), drive_limit=t.value("drive_limit"),
                            port=t.value("port"), baudrate=t.value("baudrate"), watchdog_s=t.value("watchdog_s"), measure=measure,
                            emulation=emulation)
    gains = v.value("gains")
    if list(gains) != sorted(gains):
        raise v.error(f"gains {list(gains)} must ascend (each step engaged after the one before)")
    verify = VerifySettings(gains=gains, injection_amplitude=v.value("injection_amplitude"), periods=v.value("periods"),
                            settle_s=v.value("settle_s"), frequencies_rad_s=v.value("frequencies_rad_s"), response_limit=v.value("response_limit"))
    if verify.injection_amplitude >= target.drive_limit:
        raise v.error(f"injection_amplitude {verify.injection_amplitude:g} must be below [target] drive_limit {target.drive_limit:g}")
    return VerifyProcedure(top.value("name"), target, verify, text)


def load_target_procedure(path: str | os.PathLike) -> VerifyProcedure:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProcedureError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    return parse_target_text(text, str(p))
