"""Instrument profiles: what a driver needs to know about an instrument model, as a TOML file.

A profile describes one model: how to check its identity, the init sequence (output off first),
the command templates and how to read them back, the error query, and the instrument's own
limits. The generic drivers interpret it, so a lab adds an instrument by writing a profile, not
code. Shipped profiles live in ``profiles/`` beside this module (``keysight-33500b``,
``rigol-dg800``, ``srs-sr830``, ``srs-sr860``, ``modbus-shaker-controller``); a procedure names
one, or gives a path to its own file (relative to the procedure file).

Three kinds (``kind = ...``); the keys of each are in :data:`PROFILE_KEYS` and documented in
``docs/instrument-profiles.md``:

``scpi-generator``
    A function generator driving the shaker amplifier (SCPI over PyVISA).
``scpi-lockin``
    A lock-in amplifier returning the phasor (X, Y) of its input at the reference frequency.
``modbus``
    A shaker controller or PLC: ``device_id`` and the roles ``identity`` (with ``expect``),
    ``frequency_hz``, ``amplitude_v`` (peak volts), ``output`` (and optionally ``watchdog_s``),
    each ``{ table, address, type, scale, word_order }``; physical value = raw x scale.

Every problem raises :class:`setmem_hil.errors.ProcedureError` naming the profile file, the
table and the key (unknown keys with a did-you-mean), so ``run --check`` and ``probe`` report it
before anything is opened.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from setmem_hil.drivers.instruments.scpi_commands import fill_fields, template_fields
from setmem_hil.errors import ProcedureError
from setmem_hil.io.toml_table import unknown_key
from setmem_hil.model.prior import parse_toml_text

__all__ = [
    "SHIPPED_PROFILE_DIR", "shipped_profiles", "load_profile", "parse_profile", "Setting", "ScpiGeneratorProfile",
    "LockInProfile", "RegisterSpec", "ModbusProfile", "ScopeProfile", "SCOPE_COMMANDS", "Profile", "REGISTER_TYPES", "REGISTER_TABLES",
]

SHIPPED_PROFILE_DIR = Path(__file__).with_name("profiles")
REGISTER_TYPES = ("uint16", "int16", "uint32", "int32", "float32")
REGISTER_TABLES = ("coil", "discrete", "input", "holding")
AMPLITUDE_UNITS = ("Vpp", "Vpk", "Vrms")
SLOPE_ORDERS = {6: 1, 12: 2, 18: 3, 24: 4}


def shipped_profiles() -> list[str]:
    return sorted(p.stem for p in SHIPPED_PROFILE_DIR.glob("*.toml"))


@dataclass(frozen=True)
class Setting:
    """A command template and how to check it took effect.

    ``query`` reads the value back; a numeric read-back must agree within ``tolerance_rel``
    (relative), a text one must equal ``expect`` (after stripping, case-insensitive). ``reply``
    (a regular expression searched in the answer) picks the value out of a compound answer
    (Siglent's ``C1:BSWV WVTP,SINE,FRQ,100HZ,...``): its group 1 (or the whole match) is the
    number, or the text compared with ``expect``. ``{ch}`` is filled in ``expect`` and ``reply``.
    """

    set: str
    query: str = ""
    expect: str = ""
    tolerance_rel: float = 1e-6
    unit: str = ""
    reply: str = ""
    resolution: float = 0.0  # the instrument's step in the setting's unit: read-backs agree within it


@dataclass(frozen=True)
class ScpiGeneratorProfile:
    name: str
    source: str
    model: str
    identity_query: str
    identity_expect: str  # regular expression searched in the reply
    error_query: str
    no_error: str  # regular expression matching an empty error queue
    init: tuple[str, ...]
    frequency: Setting
    amplitude: Setting
    output_on: Setting
    output_off: Setting
    frequency_limits_hz: tuple[float, float]
    amplitude_limits_v: tuple[float, float]  # peak volts
    channels: tuple[int, ...] = (1,)
    termination: str = "\n"
    timeout_s: float = 2.0
    kind: str = "scpi-generator"
    dead_man: str = ""
    high_z: str = "INF"  # what the instrument calls a high-impedance load ({load} without load_ohms)
    arbitrary: ArbitraryWaveform | None = None  # plays arbitrary waveforms (multisine records)


@dataclass(frozen=True)
class ArbitraryWaveform:
    """A generator's ``[arbitrary]`` table (issue 26): how to upload a waveform and play it.

    Templates take ``{ch}``, ``{name}``, ``{value}`` (a number) and, for the upload, either
    ``{values}`` (``data = "ascii"``: comma-separated floats in [-1, 1]) or, with
    ``data = "binary"``, ``{flag}`` (the package flag), ``{points}`` and ``{bytes}`` (this
    package's size): the points go as 16-bit DAC codes (``codes``: the codes of -1 and +1, in
    ``byte_order``) after the upload text, in an IEEE 488.2 definite-length block
    (``block = "ieee"``) or alone (``"raw"``), at most ``package_points`` to a command (the
    flags of ``package_flags``: more to come, the last).

    ``select`` may hold several commands separated by ``;``; it must leave the generator
    holding each point for one sample period (its interpolation filter off): the played peak is
    then exactly the largest point, which the safety check needs."""

    clear: str  # free the volatile memory ("": nothing to free)
    upload: str  # {name}, {values} | {flag}, {points}, {bytes}
    select: str  # play waveform {name} ({name}; the filter, the function)
    sample_rate: Setting  # {value} Sa/s, read back
    function_query: str  # what the function query answers once the arbitrary waveform plays
    function_expect: str
    sine: str  # back to the generator's own sine
    max_points: int
    sample_rate_limits: tuple[float, float]
    name: str = "SETMEM"
    data: str = "ascii"  # "ascii" | "binary"
    codes: tuple[int, int] = (0, 0)  # binary: the DAC codes of -1 and +1
    byte_order: str = "lsb"  # binary: "lsb" (little-endian) | "msb"
    block: str = "ieee"  # binary: "ieee" (a definite-length block) | "raw" (the bytes alone)
    package_points: int = 0  # binary: the most points one upload command carries
    package_flags: tuple[str, str] = ("", "")  # binary: {flag} of a package with more to come, of the last
    byte_order_command: str = ""  # binary: sent before an upload, so the instrument reads the codes in byte_order
    # asked after an upload (``*OPC?``) with a timeout from its size: the instrument answers once
    # it has taken the upload in, so no later query meets a reply that is still on its way
    complete_query: str = ""
    upload_bytes_per_s: float = 1e5  # the slowest rate an instrument takes an upload in (the wait's timeout)
    # what the generator's sync output does while an arbitrary waveform plays: "period" (one
    # pulse per waveform period, rising at its first point: the 33500B, its guide's SYNC and
    # MARKer pages) or "record" (a pulse a record may start on). With "period" a record cannot
    # wait for the sync (the waveform is the record plus its levelling, tens of seconds): the
    # oscilloscope triggers multisine records on the force channel (issue 63 item 7)
    sync: str = "period"


@dataclass(frozen=True)
class LockInProfile:
    name: str
    source: str
    model: str
    identity_query: str
    identity_expect: str
    error_query: str
    no_error: str
    init: tuple[str, ...]
    reference: Setting  # select / verify the external reference
    reference_frequency_query: str
    time_constant: Setting  # template with {index}
    time_constants_s: tuple[float, ...]
    filter_order: int  # cascade order of the output filter the init sequence selects
    read_xy: str  # query answering "X,Y" in volts RMS
    status_query: str
    overload_mask: int
    unlock_mask: int
    full_scale_v: float
    termination: str = "\n"
    timeout_s: float = 2.0
    kind: str = "scpi-lockin"
    sensitivity: Setting | None = None  # template with {index}: the full scale, for auto-ranging
    sensitivities_v: tuple[float, ...] = ()  # full scale of each index


@dataclass(frozen=True)
class RegisterSpec:
    table: str
    address: int
    type: str = "uint16"
    scale: float = 1.0
    word_order: str = "big"
    expect: float | None = None

    @property
    def n_registers(self) -> int:
        return 0 if self.table in ("coil", "discrete") else (2 if self.type in ("uint32", "int32", "float32") else 1)


@dataclass(frozen=True)
class ModbusProfile:
    name: str
    source: str
    model: str
    device_id: int
    identity: RegisterSpec
    frequency_hz: RegisterSpec
    amplitude_v: RegisterSpec
    output: RegisterSpec
    watchdog_s: RegisterSpec | None
    watchdog_timeout_s: float
    frequency_limits_hz: tuple[float, float]
    amplitude_limits_v: tuple[float, float]
    timeout_s: float = 1.0
    kind: str = "modbus"
    channels: tuple[int, ...] = (1,)


@dataclass(frozen=True)
class CanopenIdentity:
    """Object 0x1018 (identity) of a CANopen node, read by SDO before any output."""

    node: int
    vendor_id: int
    product_code: int


@dataclass(frozen=True)
class DbcProfile:
    """A CAN device described by a DBC file: command, status (read-back) and identity messages."""

    name: str
    source: str
    model: str
    dbc_path: str
    command_message: str
    command_signals: dict  # role -> signal name (frequency_hz, amplitude_v, output)
    period_s: float
    status_message: str
    status_signals: dict
    status_timeout_s: float
    identity_message: str
    identity_signal: str
    identity_expect: float
    identity_request: str
    canopen_identity: CanopenIdentity | None
    frequency_limits_hz: tuple[float, float]
    amplitude_limits_v: tuple[float, float]
    kind: str = "dbc"
    channels: tuple[int, ...] = (1,)


@dataclass(frozen=True)
class DaqProfile:
    """An NI DAQ analog input (NI-DAQmx); the instrument table's ``resource`` is the physical
    channel (``Dev1/ai0``)."""

    name: str
    source: str
    model: str
    range_v: float
    terminal: str
    max_sample_rate_hz: float
    ac_coupling_corner_hz: float = 0.5  # the -3 dB corner of the input's AC coupling (first order)
    kind: str = "nidaqmx"
    channels: tuple[int, ...] = (1,)


@dataclass(frozen=True)
class ScopeProfile:
    """An oscilloscope reading force and responses as sampled records (issue 26).

    The command templates take ``{ch}`` (a channel number), ``{value}`` (a number) and
    ``{source}`` (the trigger source: ``trigger_sources`` maps ``"ext"`` or a channel to the
    instrument's name for it); the record's transfer templates take ``{start}``/``{stop}``
    (1-based points). Volts from codes follow ``y_origin``: ``"codes"`` (Rigol:
    ``(code - yorigin - yreference) * yincrement``) or ``"volts"`` (Keysight:
    ``(code - yreference) * yincrement + yorigin``).
    """

    name: str
    source: str
    model: str
    identity_query: str
    identity_expect: str
    error_query: str
    no_error: str
    init: tuple[str, ...]
    channels: tuple[int, ...]
    has_ext_trigger: bool
    adc_bits: int
    divisions: float  # vertical divisions of the screen (full scale = divisions x V/div)
    time_divisions: float  # horizontal divisions (record length = time_divisions x s/div)
    vertical_scales_v: tuple[float, ...]  # V/div the scope offers, ascending (with vertical_fine: the range's ends and coarse steps)
    time_scales_s: tuple[float, ...]  # s/div, ascending
    record_points: Mapping[int, tuple[int, ...]]  # memory depths offered (points per channel, ascending), by the number of channels on
    max_transfer_points: int  # points per :WAV:DATA? transfer; longer records are read in pieces
    gain_accuracy: float  # DC vertical gain accuracy, fraction of full scale (datasheet)
    timebase_ppm: float  # sample-clock accuracy
    trigger_jitter_s: float  # rms trigger jitter
    commands: Mapping[str, str]  # role -> template (see SCOPE_COMMANDS)
    done_expect: str  # regex the done query answers once the record is complete ("" with done_clear_mask)
    data_format: str  # "byte" or "word"
    word_msb_first: bool
    y_origin: str  # "codes" or "volts"
    clip_codes: tuple[int, ...]  # codes that mean clipped (or a hole): refused
    trigger_sources: Mapping[str, str]
    termination: str = "\n"
    timeout_s: float = 5.0
    kind: str = "scpi-scope"
    done_clear_mask: int = 0  # or: done when these bits of the done query's integer answer are clear
    vertical_fine: bool = False  # any V/div between the smallest and largest (fine adjustment): the signal fills the screen


# the scope command roles a profile gives in [commands]; the driver sends them in this sense
SCOPE_COMMANDS = {
    "channel_on": "switch channel {ch} on, DC coupled, no offset (a list of commands joined by ';')",
    "channel_off": "switch channel {ch} off",
    "vertical_scale": "set channel {ch} to {value} V/div",
    "vertical_scale_query": "read channel {ch}'s V/div back",
    "time_scale": "set {value} s/div with the trigger at the left edge of the record",
    "record_points": "ask for {value} points per channel",
    "trigger": "edge trigger on {source}, rising, level {value} V",
    "arm": "start one single acquisition",
    "done_query": "answers done_expect once the record is complete",
    "waveform_source": "select channel {ch} for the transfer",
    "waveform_setup": "the transfer format (raw record, byte or word)",
    "waveform_range": "the points {start}..{stop} of the next transfer (absent: the whole record at once)",
    "preamble": "the preamble query (format,type,points,count,xincrement,xorigin,xreference,yincrement,yorigin,yreference)",
    "data": "the data query (an IEEE 488.2 definite-length block)",
    "force_trigger": "complete an armed acquisition without a trigger (the noise records, output off)",
}
_SCOPE_REQUIRED = ("channel_on", "vertical_scale", "time_scale", "trigger", "arm", "done_query", "waveform_source", "preamble", "data")


Profile = ScpiGeneratorProfile | LockInProfile | ModbusProfile | DbcProfile | DaqProfile | ScopeProfile

_COMMON = {"kind", "model", "description", "extends"}
PROFILE_KEYS: dict[str, set[str]] = {
    "scpi-generator": _COMMON | {"termination", "timeout_s", "identity", "errors", "init", "commands", "limits", "dead_man", "high_z",
                                 "arbitrary"},
    "scpi-lockin": _COMMON | {"termination", "timeout_s", "identity", "errors", "init", "reference", "time_constant", "read", "status", "filter_slope_db_per_octave", "full_scale_v", "sensitivity"},
    "modbus": _COMMON | {"device_id", "identity", "frequency_hz", "amplitude_v", "output", "watchdog_s", "watchdog_timeout_s", "limits", "timeout_s"},
    "dbc": _COMMON | {"dbc", "command", "status", "identity", "canopen_identity", "limits"},
    "nidaqmx": _COMMON | {"range_v", "terminal", "max_sample_rate_hz", "ac_coupling_corner_hz"},
    "scpi-scope": _COMMON | {"termination", "timeout_s", "identity", "errors", "init", "channels", "ext_trigger", "vertical_fine", "adc_bits",
                             "divisions", "time_divisions", "vertical_scales_v", "time_scales_s", "record_points",
                             "max_transfer_points", "gain_accuracy", "timebase_ppm", "trigger_jitter_s", "commands", "done",
                             "waveform", "trigger_sources"},
}
_TABLE_KEYS = {
    "identity": {"query", "expect"},
    "errors": {"query", "no_error", "error_mask"},
    "commands": {"frequency_hz", "amplitude", "output_on", "output_off"},
    "setting": {"set", "query", "expect", "tolerance_rel", "resolution", "unit", "reply"},
    "limits": {"frequency_hz", "amplitude_v", "channels"},
    "reference": {"set", "query", "expect", "reply", "frequency_query"},
    "time_constant": {"set", "query", "reply", "values_s"},
    "sensitivity": {"set", "query", "reply", "values_v"},
    "read": {"xy"},
    "status": {"query", "overload_mask", "unlock_mask"},
    "register": {"table", "address", "type", "scale", "word_order", "expect"},
    "dbc-command": {"message", "frequency_hz", "amplitude_v", "output", "period_s"},
    "dbc-status": {"message", "frequency_hz", "amplitude_v", "output", "timeout_s"},
    "dbc-identity": {"message", "signal", "expect", "request"},
    "canopen-identity": {"node", "vendor_id", "product_code"},
    "scope-commands": set(SCOPE_COMMANDS),
    "scope-done": {"expect", "clear_mask"},
    "scope-waveform": {"format", "byte_order", "y_origin", "clip_codes"},
    "scope-trigger-sources": {"ext", "channel"},
    "arbitrary": {"clear", "upload", "select", "sample_rate", "function_query", "function_expect", "sine", "max_points",
                  "sample_rate_limits", "name", "data", "codes", "byte_order", "block", "package_points", "package_flags",
                  "byte_order_command", "complete_query", "upload_bytes_per_s", "sync"},
}


class _Reader:
    """Typed access to one table of a profile, with errors naming file, table and key."""

    def __init__(self, source: str, location: str, mapping: Any, allowed: set[str]):
        self.source, self.location = source, location
        if not isinstance(mapping, Mapping):
            raise self.error(f"expected a table, found {mapping!r}")
        self.mapping = mapping
        problem = unknown_key(mapping, sorted(allowed))
        if problem:
            raise self.error(problem)

    def error(self, problem: str) -> ProcedureError:
        return ProcedureError(self.source, self.location, problem)

    def sub(self, key: str, allowed_kind: str) -> "_Reader":
        if key not in self.mapping:
            raise self.error(f"missing table {key!r}")
        where = f"{self.location}.{key}" if self.location != "top level" else f"[{key}]"
        return _Reader(self.source, where, self.mapping[key], _TABLE_KEYS[allowed_kind])

    def string(self, key: str, default: str | None = None) -> str:
        if key not in self.mapping:
            if default is None:
                raise self.error(f"missing key {key!r}")
            return default
        v = self.mapping[key]
        if not isinstance(v, str):
            raise self.error(f"{key}: expected a string, found {v!r}")
        return v

    def regex(self, key: str, default: str | None = None) -> str:
        v = self.string(key, default)
        try:
            re.compile(fill_fields(v, ch=1, load="INF"))
        except re.error as exc:
            raise self.error(f"{key}: not a valid regular expression ({exc})") from None
        return v

    def number(self, key: str, default: float | None = None, *, positive: bool = False) -> float:
        if key not in self.mapping:
            if default is None:
                raise self.error(f"missing key {key!r}")
            return default
        v = self.mapping[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
            raise self.error(f"{key}: expected a {'positive ' if positive else ''}finite number, found {v!r}")
        return float(v)

    def integer(self, key: str, default: int | None = None, lo: int = 0, hi: int = 2**31) -> int:
        if key not in self.mapping:
            if default is None:
                raise self.error(f"missing key {key!r}")
            return default
        v = self.mapping[key]
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise self.error(f"{key}: expected an integer in [{lo}, {hi}], found {v!r}")
        return v

    def strings(self, key: str) -> tuple[str, ...]:
        v = self.mapping.get(key, [])
        if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
            raise self.error(f"{key}: expected an array of strings, found {v!r}")
        return tuple(v)

    def pair(self, key: str, default: tuple[float, float]) -> tuple[float, float]:
        v = self.mapping.get(key, list(default))
        if (not isinstance(v, list) or len(v) != 2 or any(isinstance(x, bool) or not isinstance(x, (int, float)) for x in v)
                or not 0 <= v[0] <= v[1]):
            raise self.error(f"{key}: expected [low, high] with 0 <= low <= high, found {v!r}")
        return float(v[0]), float(v[1])

    def template(self, key: str, fields: set[str], default: str | None = None) -> str:
        text = self.string(key, default)
        unknown = template_fields(text) - fields
        if unknown:
            raise self.error(f"{key}: unknown field {{{sorted(unknown)[0]}}} in {text!r} (fields: {', '.join('{' + f + '}' for f in sorted(fields))})")
        return text


_GENERATOR_FIELDS = {"ch", "value", "load"}


def _setting(parent: _Reader, key: str, fields: set[str], *, units: bool = False) -> Setting:
    r = parent.sub(key, "setting")
    unit = r.string("unit", "") if units else ""
    if units and unit not in AMPLITUDE_UNITS:
        raise r.error(f"unit: expected one of {', '.join(AMPLITUDE_UNITS)}, found {unit!r}")
    if not units and "unit" in r.mapping:
        raise r.error("unit: only the amplitude setting has a unit")
    return Setting(
        set=r.template("set", fields),
        query=r.template("query", fields - {"value"}, ""),
        expect=r.string("expect", ""),
        tolerance_rel=r.number("tolerance_rel", 1e-6, positive=True),
        unit=unit,
        reply=_reply(r),
        resolution=r.number("resolution", 0.0),
    )


def _reply(r: _Reader) -> str:
    """The ``reply`` regular expression (at most one group: the value), or ""."""
    text = r.regex("reply", "")
    if text and re.compile(fill_fields(text, ch=1, load="INF")).groups > 1:
        raise r.error(f"reply: at most one group (the value) in {text!r}; make the others non-capturing: (?:...)")
    return text


def _identity_and_errors(top: _Reader) -> tuple[str, str, str, str]:
    """Identity query and pattern; the error query and what an empty queue answers: a regular
    expression (``no_error``) or, for a status register, ``error_mask`` (bits that mean an error)."""
    ident = top.sub("identity", "identity")
    errors = top.sub("errors", "errors")
    if ("no_error" in errors.mapping) == ("error_mask" in errors.mapping):
        raise errors.error("give exactly one of no_error (a regular expression) and error_mask (an integer)")
    no_error = errors.regex("no_error") if "no_error" in errors.mapping else f"mask:{errors.integer('error_mask', None, 1, 2**16)}"
    return ident.string("query"), ident.regex("expect"), errors.string("query"), no_error


def _generator(name: str, source: str, top: _Reader) -> ScpiGeneratorProfile:
    identity_query, identity_expect, error_query, no_error = _identity_and_errors(top)
    commands = top.sub("commands", "commands")
    limits = top.sub("limits", "limits")
    channels = limits.mapping.get("channels", [1])
    if not isinstance(channels, list) or not channels or not all(isinstance(c, int) and not isinstance(c, bool) and c > 0 for c in channels):
        raise limits.error(f"channels: expected an array of positive integers, found {channels!r}")
    init = top.strings("init")
    for i, command in enumerate(init):
        bad = template_fields(command) - {"ch", "load"}
        if bad:
            raise top.error(f"init[{i}]: unknown field {{{sorted(bad)[0]}}} in {command!r} (fields: {{ch}}, {{load}})")
    return ScpiGeneratorProfile(
        name=name, source=source, model=top.string("model", name),
        identity_query=identity_query, identity_expect=identity_expect, error_query=error_query, no_error=no_error,
        init=init,
        frequency=_setting(commands, "frequency_hz", _GENERATOR_FIELDS),
        amplitude=_setting(commands, "amplitude", _GENERATOR_FIELDS, units=True),
        output_on=_setting(commands, "output_on", _GENERATOR_FIELDS),
        output_off=_setting(commands, "output_off", _GENERATOR_FIELDS),
        frequency_limits_hz=limits.pair("frequency_hz", (0.0, math.inf)),
        amplitude_limits_v=limits.pair("amplitude_v", (0.0, math.inf)),
        channels=tuple(channels),
        termination=top.string("termination", "\n"),
        timeout_s=top.number("timeout_s", 2.0, positive=True),
        dead_man=top.string("dead_man", ""),
        high_z=_high_z(top),
        arbitrary=_arbitrary(top) if "arbitrary" in top.mapping else None,
    )


def _arbitrary(top: _Reader) -> ArbitraryWaveform:
    a = top.sub("arbitrary", "arbitrary")
    data = a.string("data", "ascii")
    if data not in ("ascii", "binary"):
        raise a.error(f"data: \"ascii\" (floats in the upload text) or \"binary\" (16-bit DAC codes), found {data!r}")
    fields = {"ch", "name", "value"} | ({"values"} if data == "ascii" else {"flag", "points", "bytes"})
    rate = a.pair("sample_rate_limits", (0.0, math.inf))
    max_points = a.integer("max_points", None, 8, 2**31)
    sync = a.string("sync", "period")
    if sync not in ("period", "record"):
        raise a.error(f"sync: \"period\" (one sync pulse per waveform period) or \"record\" (a pulse a record may start on), found {sync!r}")
    binary = _binary_upload(a, max_points) if data == "binary" else {}
    return ArbitraryWaveform(
        clear=a.template("clear", fields, ""), upload=a.template("upload", fields), select=a.template("select", fields),
        sample_rate=_setting(a, "sample_rate", fields), function_query=a.template("function_query", fields),
        function_expect=a.regex("function_expect"), sine=a.template("sine", fields),
        max_points=max_points, sample_rate_limits=rate, name=a.string("name", "SETMEM"), data=data,
        complete_query=a.template("complete_query", fields, ""), upload_bytes_per_s=a.number("upload_bytes_per_s", 1e5, positive=True),
        sync=sync, **binary)


def _binary_upload(a: _Reader, max_points: int) -> dict:
    """The binary upload's keys: the codes of -1 and +1 (16-bit, signed or not), byte order,
    block framing, the package size and its flags."""
    codes = a.mapping.get("codes")
    if (not isinstance(codes, list) or len(codes) != 2 or any(isinstance(c, bool) or not isinstance(c, int) for c in codes)
            or not codes[0] < codes[1] or not (0 <= codes[0] and codes[1] <= 0xFFFF or -0x8000 <= codes[0] and codes[1] <= 0x7FFF)):
        raise a.error(f"codes: expected [code of -1, code of +1], 16-bit integers (0..65535 or -32768..32767), found {codes!r}")
    order, block = a.string("byte_order", "lsb"), a.string("block", "ieee")
    if order not in ("lsb", "msb") or block not in ("ieee", "raw"):
        raise a.error(f"byte_order: \"lsb\" or \"msb\"; block: \"ieee\" or \"raw\"; found {order!r}, {block!r}")
    flags = a.strings("package_flags") or ("", "")
    if len(flags) != 2:
        raise a.error(f"package_flags: expected [flag of a package with more to come, flag of the last], found {list(flags)!r}")
    return {"codes": (codes[0], codes[1]), "byte_order": order, "block": block,
            "byte_order_command": a.template("byte_order_command", {"ch"}, ""),
            "package_points": a.integer("package_points", max_points, 8, max_points), "package_flags": tuple(flags)}


def _high_z(top: _Reader) -> str:
    token = top.string("high_z", "INF")
    if not re.fullmatch(r"[A-Za-z0-9_.+-]+", token):
        raise top.error(f"high_z: expected the instrument's word for a high-impedance load (INF, HZ, ...), found {token!r}")
    return token


def _lockin(name: str, source: str, top: _Reader) -> LockInProfile:
    identity_query, identity_expect, error_query, no_error = _identity_and_errors(top)
    ref = top.sub("reference", "reference")
    tc = top.sub("time_constant", "time_constant")
    values = tc.mapping.get("values_s")
    if not isinstance(values, list) or not values or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0 for v in values) \
            or list(values) != sorted(values):
        raise tc.error(f"values_s: expected the instrument's time constants in seconds, ascending, found {values!r}")
    status = top.sub("status", "status")
    sensitivity, sensitivities = None, ()
    if "sensitivity" in top.mapping:
        sens = top.sub("sensitivity", "sensitivity")
        values_v = sens.mapping.get("values_v")
        if not isinstance(values_v, list) or not values_v or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0 for v in values_v):
            raise sens.error(f"values_v: expected the full scale of each index in volts, found {values_v!r}")
        sensitivity = Setting(set=sens.template("set", {"index"}), query=sens.string("query", ""), reply=_reply(sens))
        sensitivities = tuple(float(v) for v in values_v)
    slope = top.integer("filter_slope_db_per_octave", 24, 6, 24)
    if slope not in SLOPE_ORDERS:
        raise top.error(f"filter_slope_db_per_octave: expected 6, 12, 18 or 24, found {slope}")
    return LockInProfile(
        name=name, source=source, model=top.string("model", name),
        identity_query=identity_query, identity_expect=identity_expect, error_query=error_query, no_error=no_error,
        init=top.strings("init"),
        reference=Setting(set=ref.string("set"), query=ref.string("query", ""), expect=ref.string("expect", ""), reply=_reply(ref)),
        reference_frequency_query=ref.string("frequency_query"),
        time_constant=Setting(set=tc.template("set", {"index"}), query=tc.string("query", ""), reply=_reply(tc)),
        time_constants_s=tuple(float(v) for v in values),
        filter_order=SLOPE_ORDERS[slope],
        read_xy=top.sub("read", "read").string("xy"),
        status_query=status.string("query", ""),
        overload_mask=status.integer("overload_mask", 0, 0, 2**16),
        unlock_mask=status.integer("unlock_mask", 0, 0, 2**16),
        full_scale_v=top.number("full_scale_v", 1.0, positive=True),
        termination=top.string("termination", "\n"),
        timeout_s=top.number("timeout_s", 2.0, positive=True),
        sensitivity=sensitivity,
        sensitivities_v=sensitivities,
    )


def register_spec(parent: _Reader, key: str, *, with_expect: bool = False) -> RegisterSpec:
    """One ``{ table, address, type, scale, word_order }`` role of a Modbus profile."""
    if key not in parent.mapping:
        raise parent.error(f"missing key {key!r} (an inline table {{ table = ..., address = ..., type = ... }})")
    allowed = _TABLE_KEYS["register"] if with_expect else _TABLE_KEYS["register"] - {"expect"}
    r = _Reader(parent.source, f"key '{key}'", parent.mapping[key], allowed)
    table = r.string("table")
    if table not in REGISTER_TABLES:
        raise r.error(f"table: expected one of {', '.join(REGISTER_TABLES)}, found {table!r}")
    bit = table in ("coil", "discrete")
    if bit and "type" in r.mapping:
        raise r.error(f"type: a {table} is one bit and takes no type")
    kind = "bool" if bit else r.string("type", "uint16")
    if not bit and kind not in REGISTER_TYPES:
        raise r.error(f"type: expected one of {', '.join(REGISTER_TYPES)}, found {kind!r}")
    order = r.string("word_order", "big")
    if order not in ("big", "little"):
        raise r.error(f"word_order: expected 'big' or 'little', found {order!r}")
    scale = r.number("scale", 1.0)
    if scale == 0:
        raise r.error("scale: must not be 0")
    expect = r.number("expect") if with_expect else None
    return RegisterSpec(table=table, address=r.integer("address", None, 0, 65535), type=kind, scale=scale, word_order=order, expect=expect)


def _modbus(name: str, source: str, top: _Reader) -> ModbusProfile:
    limits = top.sub("limits", "limits") if "limits" in top.mapping else _Reader(source, "[limits]", {}, _TABLE_KEYS["limits"])
    output = register_spec(top, "output")
    if output.table not in ("coil", "holding"):
        raise top.error(f"output: expected a coil or a holding register, found table {output.table!r}")
    for role in ("frequency_hz", "amplitude_v"):
        if top.mapping.get(role, {}).get("table") not in ("holding", None):
            raise top.error(f"{role}: expected a holding register (it is written), found table {top.mapping[role].get('table')!r}")
    watchdog = register_spec(top, "watchdog_s") if "watchdog_s" in top.mapping else None
    return ModbusProfile(
        name=name, source=source, model=top.string("model", name),
        device_id=top.integer("device_id", None, 0, 247),
        identity=register_spec(top, "identity", with_expect=True),
        frequency_hz=register_spec(top, "frequency_hz"),
        amplitude_v=register_spec(top, "amplitude_v"),
        output=output,
        watchdog_s=watchdog,
        watchdog_timeout_s=top.number("watchdog_timeout_s", 2.0, positive=True),
        frequency_limits_hz=limits.pair("frequency_hz", (0.0, math.inf)),
        amplitude_limits_v=limits.pair("amplitude_v", (0.0, math.inf)),
        timeout_s=top.number("timeout_s", 1.0, positive=True),
    )


def _dbc(name: str, source: str, top: _Reader) -> DbcProfile:
    """A DBC profile; the DBC file is loaded with cantools now, so a missing message or signal
    is reported with the profile, before any bus is opened."""
    try:
        import cantools
    except ImportError:  # pragma: no cover - the [can] extra is in [test]
        raise top.error("dbc profiles need cantools: pip install 'setmem-hil[can]'") from None
    dbc_path = Path(top.string("dbc"))
    if not dbc_path.is_absolute():
        dbc_path = Path(source).parent / dbc_path
    try:
        db = cantools.database.load_file(str(dbc_path))
    except Exception as exc:  # noqa: BLE001 - cantools raises several parse errors
        raise top.error(f"dbc: cannot load {str(dbc_path)!r} ({' '.join(str(exc).split())})") from None

    def message(r: _Reader, key: str = "message") -> str:
        text = r.string(key)
        try:
            db.get_message_by_name(text)
        except KeyError:
            names = [m.name for m in db.messages]
            close = difflib.get_close_matches(text, names, n=1)
            raise r.error(f"{key}: no message {text!r} in {dbc_path.name}" + (f"; did you mean {close[0]!r}?" if close else "")
                          + f" (messages: {', '.join(names)})") from None
        return text

    def signals(r: _Reader, msg: str) -> dict:
        found = {}
        names = [sig.name for sig in db.get_message_by_name(msg).signals]
        for role in ("frequency_hz", "amplitude_v", "output"):
            sig = r.string(role)
            if sig not in names:
                raise r.error(f"{role}: no signal {sig!r} in message {msg!r} (signals: {', '.join(names)})")
            found[role] = sig
        return found

    cmd = top.sub("command", "dbc-command")
    command = message(cmd)
    st = top.sub("status", "dbc-status")
    status = message(st)
    ident = top.sub("identity", "dbc-identity")
    ident_msg = message(ident)
    ident_signal = ident.string("signal")
    if ident_signal not in [sig.name for sig in db.get_message_by_name(ident_msg).signals]:
        raise ident.error(f"signal: no signal {ident_signal!r} in message {ident_msg!r}")
    request = message(ident, "request") if "request" in ident.mapping else ""
    co = None
    if "canopen_identity" in top.mapping:
        c = top.sub("canopen_identity", "canopen-identity")
        co = CanopenIdentity(c.integer("node", None, 1, 127), c.integer("vendor_id", None, 0, 2**32 - 1), c.integer("product_code", None, 0, 2**32 - 1))
    limits = top.sub("limits", "limits") if "limits" in top.mapping else _Reader(source, "[limits]", {}, _TABLE_KEYS["limits"])
    return DbcProfile(
        name=name, source=source, model=top.string("model", name), dbc_path=str(dbc_path),
        command_message=command, command_signals=signals(cmd, command), period_s=cmd.number("period_s", 0.1, positive=True),
        status_message=status, status_signals=signals(st, status), status_timeout_s=st.number("timeout_s", 0.5, positive=True),
        identity_message=ident_msg, identity_signal=ident_signal, identity_expect=ident.number("expect"), identity_request=request,
        canopen_identity=co,
        frequency_limits_hz=limits.pair("frequency_hz", (0.0, math.inf)),
        amplitude_limits_v=limits.pair("amplitude_v", (0.0, math.inf)),
    )


def _daq(name: str, source: str, top: _Reader) -> DaqProfile:
    terminal = top.string("terminal", "DIFF")
    if terminal not in ("DIFF", "RSE", "NRSE", "PSEUDO_DIFF", "DEFAULT"):
        raise top.error(f"terminal: expected DIFF, RSE, NRSE, PSEUDO_DIFF or DEFAULT, found {terminal!r}")
    return DaqProfile(name=name, source=source, model=top.string("model", name), range_v=top.number("range_v", 10.0, positive=True),
                      terminal=terminal, max_sample_rate_hz=top.number("max_sample_rate_hz", 100e3, positive=True),
                      ac_coupling_corner_hz=top.number("ac_coupling_corner_hz", 0.5, positive=True))


def _ascending(top: _Reader, key: str) -> tuple[float, ...]:
    values = top.mapping.get(key)
    if not isinstance(values, list) or not values or any(isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0 for v in values) \
            or list(values) != sorted(values):
        raise top.error(f"{key}: expected positive numbers, ascending, found {values!r}")
    return tuple(float(v) for v in values)


def _record_points(top: _Reader, n_channels: int) -> dict[int, tuple[int, ...]]:
    """``record_points``: the memory depths (points per channel) the scope offers, one number or
    an ascending array, or a table of those by the number of channels on (``{ "1" = [12000,
    120000], "4" = [3000, 30000] }``: a count not listed uses the next larger one listed)."""
    v = top.mapping.get("record_points", 10000)
    table = v if isinstance(v, Mapping) else {str(n): v for n in range(1, n_channels + 1)}

    def depths(p) -> tuple[int, ...] | None:
        items = p if isinstance(p, list) else [p]
        if not items or any(isinstance(x, bool) or not isinstance(x, int) or x < 100 for x in items) or items != sorted(set(items)):
            return None
        return tuple(int(x) for x in items)

    if not table or any(not str(k).isdigit() or depths(p) is None for k, p in table.items()):
        raise top.error(f"record_points: expected points (>= 100, one number or an ascending array) or a table of those by "
                        f"channel count, found {v!r}")
    listed = sorted((int(k), depths(p)) for k, p in table.items())
    out = {}
    for n in range(1, n_channels + 1):
        larger = [p for k, p in listed if k >= n]
        if not larger:
            raise top.error(f"record_points: no entry for {n} channels or more")
        out[n] = larger[0]
    return out


def _scope(name: str, source: str, top: _Reader) -> ScopeProfile:
    identity_query, identity_expect, error_query, no_error = _identity_and_errors(top)
    cmds = top.sub("commands", "scope-commands")
    commands = {}
    for role in SCOPE_COMMANDS:
        if role in cmds.mapping:
            commands[role] = cmds.template(role, {"ch", "value", "source", "start", "stop", "offset"})
        elif role in _SCOPE_REQUIRED:
            raise cmds.error(f"missing key {role!r} ({SCOPE_COMMANDS[role]})")
    wave = top.sub("waveform", "scope-waveform")
    data_format = wave.string("format", "byte")
    if data_format not in ("byte", "word"):
        raise wave.error(f"format: expected \"byte\" or \"word\", found {data_format!r}")
    order = wave.string("byte_order", "msb")
    y_origin = wave.string("y_origin", "volts")
    if order not in ("msb", "lsb") or y_origin not in ("codes", "volts"):
        raise wave.error(f"byte_order: \"msb\" or \"lsb\"; y_origin: \"codes\" or \"volts\"; found {order!r}, {y_origin!r}")
    clip = wave.mapping.get("clip_codes", [0, 255] if data_format == "byte" else [0, 65535])
    if not isinstance(clip, list) or any(isinstance(c, bool) or not isinstance(c, int) for c in clip):
        raise wave.error(f"clip_codes: expected an array of integers, found {clip!r}")
    done = top.sub("done", "scope-done")
    if ("expect" in done.mapping) == ("clear_mask" in done.mapping):
        raise done.error("give exactly one of expect (a regular expression) and clear_mask (bits clear when done)")
    n_channels = top.integer("channels", 4, 1, 16)
    ext = bool(top.mapping.get("ext_trigger", False))
    fine = top.mapping.get("vertical_fine", False)
    if not isinstance(fine, bool):
        raise top.error(f"vertical_fine: expected true or false, found {fine!r}")
    sources = top.sub("trigger_sources", "scope-trigger-sources") if "trigger_sources" in top.mapping else None
    trigger_sources = {"channel": sources.string("channel", "CHAN{ch}") if sources else "CHAN{ch}",
                       "ext": sources.string("ext", "EXT") if sources else "EXT"}
    return ScopeProfile(
        name=name, source=source, model=top.string("model", name),
        identity_query=identity_query, identity_expect=identity_expect, error_query=error_query, no_error=no_error,
        init=top.strings("init"), channels=tuple(range(1, n_channels + 1)), has_ext_trigger=ext, vertical_fine=fine,
        adc_bits=top.integer("adc_bits", 8, 4, 16), divisions=top.number("divisions", 8.0, positive=True),
        time_divisions=top.number("time_divisions", 10.0, positive=True),
        vertical_scales_v=_ascending(top, "vertical_scales_v"), time_scales_s=_ascending(top, "time_scales_s"),
        record_points=_record_points(top, n_channels),
        max_transfer_points=top.integer("max_transfer_points", 250000, 100, 10**8),
        gain_accuracy=top.number("gain_accuracy"), timebase_ppm=top.number("timebase_ppm", 50.0),
        trigger_jitter_s=top.number("trigger_jitter_s", 1e-9),
        commands=commands, done_expect=done.regex("expect", ""), done_clear_mask=done.integer("clear_mask", 0, 0, 2**31),
        data_format=data_format, word_msb_first=order == "msb", y_origin=y_origin, clip_codes=tuple(int(c) for c in clip),
        trigger_sources=trigger_sources, termination=top.string("termination", "\n"), timeout_s=top.number("timeout_s", 5.0, positive=True),
    )


_BUILDERS = {"scpi-generator": _generator, "scpi-lockin": _lockin, "modbus": _modbus, "dbc": _dbc, "nidaqmx": _daq, "scpi-scope": _scope}


def parse_profile(text: str, source: str, name: str = "") -> Profile:
    """Validate profile TOML text (``source`` names the file in messages; ``extends`` is
    resolved relative to its folder)."""
    doc = _with_base(parse_toml_text(text, source), source, (source,))
    kind = doc.get("kind") if isinstance(doc, Mapping) else None
    if kind not in PROFILE_KEYS:
        raise ProcedureError(source, "top level", f"kind: expected one of {', '.join(repr(k) for k in PROFILE_KEYS)}, found {kind!r}")
    top = _Reader(source, "top level", doc, PROFILE_KEYS[kind])
    return _BUILDERS[kind](name or Path(source).stem, source, top)


def _with_base(doc: dict, source: str, chain: tuple[str, ...]) -> dict:
    """``extends = "<shipped profile or path>"``: the base profile's tables with this file's keys
    laid over them (tables merge key by key; any other value, arrays included, replaces)."""
    if "extends" not in doc:
        return doc
    spec = doc["extends"]
    if not isinstance(spec, str) or not spec:
        raise ProcedureError(source, "top level", f"extends: expected a shipped profile name or a path, found {spec!r}")
    path, _ = _profile_path(spec, relative_to=source, asked_in=source)
    if str(path) in chain:
        raise ProcedureError(source, "top level", f"extends: {spec!r} extends this profile again ({' -> '.join(chain)} -> {path})")
    base = _with_base(parse_toml_text(_read_profile_text(path), str(path)), str(path), (*chain, str(path)))
    return _merged(base, {k: v for k, v in doc.items() if k != "extends"})


def _merged(base: Mapping, over: Mapping) -> dict:
    out = dict(base)
    for key, value in over.items():
        out[key] = _merged(out[key], value) if isinstance(value, Mapping) and isinstance(out.get(key), Mapping) else value
    return out


def _profile_path(spec: str, relative_to: str | Path | None, asked_in: str = "") -> tuple[Path, str]:
    """A shipped profile's file, or a path (relative to ``relative_to``'s folder); and its name."""
    looks_like_path = "/" in spec or "\\" in spec or spec.endswith(".toml")
    if not looks_like_path:
        shipped = SHIPPED_PROFILE_DIR / f"{spec}.toml"
        if not shipped.is_file():
            close = difflib.get_close_matches(spec, shipped_profiles(), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ProcedureError(asked_in or spec, "" if not asked_in else "key 'extends'",
                                 f"unknown instrument profile {spec!r}{hint} (shipped: {', '.join(shipped_profiles())}; "
                                 "or give the path of a profile .toml file)")
        return shipped, spec
    path = Path(spec)
    if not path.is_absolute() and relative_to:
        path = Path(relative_to).parent / path
    return path, path.stem


def _read_profile_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ProcedureError(str(path), "", f"cannot read the instrument profile: {exc}") from None


def load_profile(spec: str, relative_to: str | Path | None = None) -> Profile:
    """A shipped profile by name, or a profile file by path (relative to ``relative_to``'s folder).

    Raises
    ------
    ProcedureError
        Unknown name, unreadable file, or a profile that does not validate.
    """
    path, name = _profile_path(spec, relative_to)
    return parse_profile(_read_profile_text(path), str(path), name=name)


def profile_warnings(profile: Profile) -> list[str]:
    """What ``run --check`` warns about: a command that sets a value without a read-back (the
    driver cannot tell that the instrument did what it was told)."""
    settings: dict[str, Setting | None] = {}
    if isinstance(profile, ScpiGeneratorProfile):
        settings = {"[commands] frequency_hz": profile.frequency, "[commands] amplitude": profile.amplitude,
                    "[commands] output_on": profile.output_on, "[commands] output_off": profile.output_off}
    elif isinstance(profile, LockInProfile):
        settings = {"[reference]": profile.reference, "[time_constant]": profile.time_constant, "[sensitivity]": profile.sensitivity}
    return [f"{profile.source}: {where}: {s.set!r} has no read-back (no 'query'): the instrument's state is not checked "
            "after it is set" for where, s in settings.items() if s is not None and not s.query]
