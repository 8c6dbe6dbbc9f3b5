"""SCPI text: canonical headers, command templates and numeric replies.

SCPI mnemonics have a long and a short form (``FREQuency`` / ``FREQ``), any case, and numeric
suffixes (``SOURce2``). :func:`canonical_header` reduces a header to its short forms by the
SCPI-1999 mnemonic rule (section 6.2.1 of volume 1: the first four characters, or three when the
fourth is a vowel; a mnemonic of four or fewer characters is its own short form), so that
``:SOURce1:FREQuency``, ``SOUR1:FREQ`` and ``sour1:freq`` compare equal. Tests use it to compare
the commands our profiles send with PyMeasure's drivers (header and value).

Templates are Python format strings over named fields (``{ch}``, ``{value}``, ``{index}``,
``{load}``); :func:`render` fills them and names the missing field in its error.
"""

from __future__ import annotations

import math
import re
import string

__all__ = ["canonical_header", "split_command", "render", "template_fields", "fill_fields", "pick_reply", "parse_number", "parse_numbers"]

_VOWELS = set("AEIOU")


def _short_form(mnemonic: str) -> str:
    m = re.fullmatch(r"(\*?[A-Za-z_]+)(\d*)", mnemonic)
    if not m:
        return mnemonic.upper()
    word, suffix = m.group(1).upper(), m.group(2)
    if word.startswith("*") or len(word) <= 4:
        short = word
    else:
        short = word[:3] if word[3] in _VOWELS else word[:4]
    return short + suffix


def canonical_header(header: str) -> tuple[str, ...]:
    """``":SOURce1:FREQuency?"`` -> ``("SOUR1", "FREQ")`` (query mark and leading colon dropped)."""
    text = header.strip().rstrip("?").lstrip(":")
    return tuple(_short_form(node) for node in text.split(":") if node)


def split_command(command: str) -> tuple[tuple[str, ...], bool, str]:
    """A command line to (canonical header, is_query, argument text)."""
    head, _, args = command.strip().partition(" ")
    return canonical_header(head), head.endswith("?"), args.strip()


def template_fields(template: str) -> set[str]:
    """The named fields a template uses."""
    return {name for _, name, _, _ in string.Formatter().parse(template) if name}


def render(template: str, **fields) -> str:
    """Fill a template; ``KeyError`` names the field the template needs and was not given."""
    try:
        return template.format(**fields)
    except KeyError as exc:
        raise KeyError(f"template {template!r} needs field {exc.args[0]!r}") from None


def fill_fields(text: str, **fields) -> str:
    """Fill ``{name}`` for the given names only, leaving every other brace alone: for regular
    expressions and expected replies (``C{ch}:OUTP (ON|OFF)``, ``\\d{2}``)."""
    for name, value in fields.items():
        text = text.replace("{" + name + "}", str(value))
    return text


def pick_reply(reply: str, pattern: str) -> str | None:
    """The value in an instrument's answer: group 1 of ``pattern`` searched in it (or the whole
    match); the stripped answer when there is no pattern; None when the pattern is not found."""
    if not pattern:
        return reply.strip()
    m = re.search(pattern, reply)
    if m is None:
        return None
    return (m.group(1) if m.re.groups else m.group(0)).strip()


def parse_number(text: str) -> float:
    """A finite number from an instrument reply (``"+1.000000000000000E+03"``, ``"9.9E+37"``...).

    Raises ``ValueError`` naming the text for anything else.
    """
    try:
        x = float(text.strip().split(",")[0])
    except ValueError:
        raise ValueError(f"expected a number, the instrument answered {text.strip()!r}") from None
    if math.isnan(x):
        raise ValueError(f"expected a number, the instrument answered {text.strip()!r}")
    return x


def parse_numbers(text: str, count: int) -> list[float]:
    """``count`` comma-separated finite numbers (a ``SNAP?`` reply)."""
    parts = [p for p in text.strip().split(",") if p.strip()]
    if len(parts) != count:
        raise ValueError(f"expected {count} comma-separated numbers, the instrument answered {text.strip()!r}")
    values = []
    for p in parts:
        try:
            x = float(p)
        except ValueError:
            raise ValueError(f"expected numbers, the instrument answered {text.strip()!r}") from None
        if not math.isfinite(x):
            raise ValueError(f"expected finite numbers, the instrument answered {text.strip()!r}")
        values.append(x)
    return values
