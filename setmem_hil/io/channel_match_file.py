"""The channel-match file (``setmem-hil calibrate-channels``, issue 26): JSON, one object.

Public contract (docs/procedures.md, "Channel match")::

    {"kind": "setmem-hil channel match", "version": 1,
     "scope": "<*IDN? reply>", "frequency_hz": 1000.0, "utc": "2026-11-25T20:00:00+00:00",
     "reference": {"channel": 1, "scale_v": 0.005},
     "gains": [{"channel": 1, "scale_v": 0.001, "gain": 1.0021, "bound": 0.0009}, ...]}

``gain`` is the channel's gain at that V/div over the reference's; the true ratio is within
``gain x (1 +- bound)``.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from setmem_hil.errors import InputFormatError
from setmem_hil.model.channel_match import ChannelGain, ChannelMatch
from setmem_hil.io.atomic_file import write_json_atomic

__all__ = ["write_channel_match", "read_channel_match", "KIND"]

KIND = "setmem-hil channel match"


def write_channel_match(match: ChannelMatch, path: str | Path) -> Path:
    doc = {"kind": KIND, "version": 1, "scope": match.identity, "frequency_hz": match.frequency_hz, "utc": match.utc,
           "reference": {"channel": match.reference[0], "scale_v": match.reference[1]},
           "gains": [{"channel": g.channel, "scale_v": g.scale_v, "gain": g.gain, "bound": g.bound} for g in match.gains]}
    return write_json_atomic(doc, path)


def _number(source: str, where: str, value, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or (value <= 0 if positive else value < 0):
        raise InputFormatError(source, where, f"expected a {'positive' if positive else 'non-negative'} number, found {value!r}")
    return float(value)


def read_channel_match(path: str | Path) -> ChannelMatch:
    """The file's calibration; InputFormatError naming the file and key when it is not one."""
    source = str(path)
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise InputFormatError(source, "", f"cannot read it ({exc.strerror or exc}); run setmem-hil calibrate-channels first") from None
    except ValueError as exc:
        raise InputFormatError(source, "", f"not JSON ({exc})") from None
    if not isinstance(doc, dict) or doc.get("kind") != KIND:
        raise InputFormatError(source, "key 'kind'", f"expected {KIND!r}: not a channel-match file")
    if doc.get("version") != 1:
        raise InputFormatError(source, "key 'version'", f"version {doc.get('version')!r}; this software reads version 1")
    for key, kind in (("scope", str), ("utc", str), ("reference", dict), ("gains", list)):
        if not isinstance(doc.get(key), kind):
            raise InputFormatError(source, f"key '{key}'", f"missing or not a {kind.__name__}")
    gains = []
    for i, g in enumerate(doc["gains"]):
        where = f"gains[{i}]"
        if not isinstance(g, dict) or not isinstance(g.get("channel"), int):
            raise InputFormatError(source, where, "expected {channel, scale_v, gain, bound}")
        gains.append(ChannelGain(g["channel"], _number(source, f"{where} key 'scale_v'", g.get("scale_v")),
                                 _number(source, f"{where} key 'gain'", g.get("gain")),
                                 _number(source, f"{where} key 'bound'", g.get("bound"), positive=False)))
    ref = doc["reference"]
    if not isinstance(ref.get("channel"), int):
        raise InputFormatError(source, "key 'reference'", "expected {channel, scale_v}")
    return ChannelMatch(doc["scope"], _number(source, "key 'frequency_hz'", doc.get("frequency_hz")), doc["utc"],
                        (ref["channel"], _number(source, "key 'reference' scale_v", ref.get("scale_v"))), tuple(gains))
