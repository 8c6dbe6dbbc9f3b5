"""A priori knowledge for identification (thesis section 3.2.2, 6.1) and the prior TOML format.

``PRIOR.toml`` (public contract, see README): one ``[[mode]]`` table per mode in ascending
frequency with ``omega_min``, ``omega_max`` (rad/s) and ``zeta_max``; optional ``b1 = <value>``
to fix ``b1`` (``b1 = 0`` for a displacement sensor), or ``b1_min``/``b1_max``; optional
``b0_min``/``b0_max``. Top level: optional ``gamma = 1.1`` (target embedding conservatism ratio)
and ``max_partitions = 200``.

Optional ``[residuals]`` table (issue 14): booleans ``lower`` (mass line ``r_l / s^2``, i.e.
``-r_l / omega^2`` in receptance) and ``upper`` (residual flexibility, a constant ``r_u``) enable
residual terms for modes outside the band; optional ``lower_min``/``lower_max``/``upper_min``/
``upper_max`` bound them (without bounds they are bounded from the data).

The prior gives ``a0 = omega_n^2`` in ``[omega_min^2, omega_max^2]`` and
``a1 = 2 zeta omega_n`` in ``[0, 2 zeta_max omega_max]``.
"""

from __future__ import annotations

import difflib

import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.model.modal_model import IntervalModel

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore[no-redef]

MODE_KEYS = ("omega_min", "omega_max", "zeta_max", "b1", "b1_min", "b1_max", "b0_min", "b0_max")
PRIOR_TOP_KEYS = ("mode", "gamma", "max_partitions", "residuals", "outputs")
PER_OUTPUT_KEYS = ("b1", "b1_min", "b1_max", "b0_min", "b0_max")  # a number, or one entry per output
RESIDUAL_KEYS = ("lower", "upper", "lower_min", "lower_max", "upper_min", "upper_max")


@dataclass(frozen=True)
class ModePrior:
    """A priori bounds for one mode."""

    omega_min: float
    omega_max: float
    zeta_max: float
    b1_min: float = -math.inf
    b1_max: float = math.inf
    b0_min: float = -math.inf
    b0_max: float = math.inf

    @property
    def b1_fixed(self) -> bool:
        return self.b1_min == self.b1_max


@dataclass(frozen=True)
class ResidualPrior:
    """Which residual terms are modelled and their a-priori bounds (``+-inf`` when not given)."""

    lower: bool = False
    upper: bool = False
    lower_min: float = -math.inf
    lower_max: float = math.inf
    upper_min: float = -math.inf
    upper_max: float = math.inf

    @property
    def enabled(self) -> tuple[str, ...]:
        return tuple(name for name, on in (("lower", self.lower), ("upper", self.upper)) if on)

    def bounds(self, name: str) -> tuple[float, float]:
        return (self.lower_min, self.lower_max) if name == "lower" else (self.upper_min, self.upper_max)


@dataclass(frozen=True)
class Prior:
    """Prior for all modes plus the partitioning settings of section 3.2.3."""

    modes: tuple[ModePrior, ...]
    gamma: float = 1.1
    max_partitions: int = 200
    extra: Mapping[str, Any] = field(default_factory=dict)
    residuals: ResidualPrior = field(default_factory=ResidualPrior)

    def time_scaled(self, factor: float) -> "Prior":
        """The prior of the time-scaled structure ``G(s / factor)``: frequencies and ``b1`` times
        ``factor``, ``b0`` times ``factor**2``, damping bounds unchanged."""
        f = float(factor)
        modes = tuple(replace(m, omega_min=m.omega_min * f, omega_max=m.omega_max * f, b1_min=m.b1_min * f,
                              b1_max=m.b1_max * f, b0_min=m.b0_min * f * f, b0_max=m.b0_max * f * f) for m in self.modes)
        return replace(self, modes=modes)

    @property
    def n_modes(self) -> int:
        return len(self.modes)

    def initial_bounds(self) -> IntervalModel:
        """Box of eq. (3.26)'s a priori bounds; unknown residues are +-inf."""
        lo = np.array([[0.0, m.omega_min**2, m.b1_min, m.b0_min] for m in self.modes])
        hi = np.array([[2 * m.zeta_max * m.omega_max, m.omega_max**2, m.b1_max, m.b0_max] for m in self.modes])
        return IntervalModel(lo, hi)


def _number(value: Any, source: str, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputFormatError(source, where, f"{key}: expected a number, found {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputFormatError(source, where, f"{key}: expected a finite number, found {value!r}")
    return v


def parse_mode_table(table: Any, source: str, index: int) -> ModePrior:
    """Validate one ``[[mode]]`` table (1-based ``index`` for messages)."""
    where = f"[[mode]] {index}"
    if not isinstance(table, Mapping):
        raise InputFormatError(source, where, f"expected a table, found {type(table).__name__}")
    unknown = sorted(set(table) - set(MODE_KEYS))
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), list(MODE_KEYS), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise InputFormatError(source, where, f"unknown key {unknown[0]!r}{hint} (allowed: {', '.join(MODE_KEYS)})")
    for key in ("omega_min", "omega_max", "zeta_max"):
        if key not in table:
            raise InputFormatError(source, where, f"missing key {key!r}")
    w_lo = _number(table["omega_min"], source, where, "omega_min")
    w_hi = _number(table["omega_max"], source, where, "omega_max")
    z_hi = _number(table["zeta_max"], source, where, "zeta_max")
    if w_lo <= 0:
        raise InputFormatError(source, where, f"omega_min {w_lo:g} must be > 0")
    if w_lo > w_hi:
        raise InputFormatError(source, where, f"omega_min {w_lo:g} > omega_max {w_hi:g}")
    if not 0 < z_hi <= 10:
        raise InputFormatError(source, where, f"zeta_max {z_hi:g} must be in (0, 10]")
    kwargs: dict[str, float] = {}
    if "b1" in table:
        if "b1_min" in table or "b1_max" in table:
            raise InputFormatError(source, where, "give either b1 (fixed) or b1_min/b1_max, not both")
        b1 = _number(table["b1"], source, where, "b1")
        kwargs.update(b1_min=b1, b1_max=b1)
    for lo_key, hi_key in (("b1_min", "b1_max"), ("b0_min", "b0_max")):
        for key in (lo_key, hi_key):
            if key in table:
                kwargs[key] = _number(table[key], source, where, key)
        if lo_key in kwargs and hi_key in kwargs and kwargs[lo_key] > kwargs[hi_key]:
            raise InputFormatError(source, where, f"{lo_key} {kwargs[lo_key]:g} > {hi_key} {kwargs[hi_key]:g}")
    return ModePrior(w_lo, w_hi, z_hi, **kwargs)


def parse_residuals_table(table: Any, source: str) -> ResidualPrior:
    """Validate the optional ``[residuals]`` table."""
    where = "[residuals]"
    if not isinstance(table, Mapping):
        raise InputFormatError(source, where, f"expected a table, found {type(table).__name__}")
    unknown = sorted(set(table) - set(RESIDUAL_KEYS))
    if unknown:
        raise InputFormatError(source, where, f"unknown key {unknown[0]!r}; allowed: {', '.join(RESIDUAL_KEYS)}")
    kwargs: dict[str, Any] = {}
    for key in ("lower", "upper"):
        if key in table:
            if not isinstance(table[key], bool):
                raise InputFormatError(source, where, f"{key}: expected true or false, found {table[key]!r}")
            kwargs[key] = table[key]
    for name in ("lower", "upper"):
        lo_key, hi_key = f"{name}_min", f"{name}_max"
        for key in (lo_key, hi_key):
            if key in table:
                kwargs[key] = _number(table[key], source, where, key)
        if lo_key in kwargs and hi_key in kwargs and kwargs[lo_key] > kwargs[hi_key]:
            raise InputFormatError(source, where, f"{lo_key} {kwargs[lo_key]:g} > {hi_key} {kwargs[hi_key]:g}")
        if (lo_key in kwargs or hi_key in kwargs) and not kwargs.get(name, False):
            raise InputFormatError(source, where, f"{lo_key}/{hi_key} given but {name} is not true")
    return ResidualPrior(**kwargs)


def parse_prior_mapping(doc: Mapping[str, Any], source: str, allow_extra: bool = False) -> Prior:
    """Validate a parsed prior document (also used for the ``[[mode]]`` part of procedures).

    Frequencies may be given in Hz (``omega_min_hz``...: :mod:`setmem_hil.model.units`)."""
    from setmem_hil.model.units import hz_keys_to_rad_s

    doc = hz_keys_to_rad_s(doc, {"": set(PRIOR_TOP_KEYS), "mode": set(MODE_KEYS)}, source)
    if not allow_extra:
        unknown = sorted(set(doc) - set(PRIOR_TOP_KEYS))
        if unknown:
            raise InputFormatError(source, f"key {unknown[0]!r}", f"unknown top-level key; allowed: {', '.join(PRIOR_TOP_KEYS)}")
    tables = doc.get("mode")
    if not isinstance(tables, list) or not tables:
        raise InputFormatError(source, "[[mode]]", "expected at least one [[mode]] table")
    modes = tuple(parse_mode_table(t, source, i + 1) for i, t in enumerate(tables))
    for i in range(1, len(modes)):
        if modes[i].omega_min < modes[i - 1].omega_min:
            raise InputFormatError(
                source, f"[[mode]] {i + 1}",
                f"modes must be in ascending frequency: omega_min {modes[i].omega_min:g} < {modes[i - 1].omega_min:g} of [[mode]] {i}",
            )
    gamma = _number(doc.get("gamma", 1.1), source, "key 'gamma'", "gamma")
    if gamma <= 1.0:
        raise InputFormatError(source, "key 'gamma'", f"gamma {gamma:g} must be > 1")
    max_partitions = doc.get("max_partitions", 200)
    if isinstance(max_partitions, bool) or not isinstance(max_partitions, int) or max_partitions < 1:
        raise InputFormatError(source, "key 'max_partitions'", f"expected a positive integer, found {max_partitions!r}")
    residuals = parse_residuals_table(doc["residuals"], source) if "residuals" in doc else ResidualPrior()
    return Prior(modes, gamma, max_partitions, residuals=residuals)


def load_toml(path: str | os.PathLike) -> dict[str, Any]:
    """Read a TOML file; syntax errors become :class:`InputFormatError` with the line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(str(path), "", f"cannot read: {exc}") from None
    return parse_toml_text(text, str(path))


def parse_toml_text(text: str, source: str) -> dict[str, Any]:
    text = text.removeprefix("\ufeff")  # a byte-order mark some editors write
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputFormatError(source, "", f"invalid TOML: {exc}") from None


def read_prior(path: str | os.PathLike) -> Prior:
    return parse_prior_mapping(load_toml(path), str(path))


def parse_output_priors(doc: Mapping[str, Any], source: str, n_outputs: int) -> tuple[list[Prior], tuple[str, ...] | None]:
    """One prior per output from a PRIOR.toml mapping (issue 25).

    In a ``[[mode]]`` table each residue key (``b1``, ``b1_min``, ``b1_max``, ``b0_min``,
    ``b0_max``) is a number (the same for every output) or an array with one entry per output.
    The optional top-level ``outputs = ["name", ...]`` names the outputs. Returns the priors and
    the names (None when not given). With one output and only numbers this is
    :func:`parse_prior_mapping` exactly.
    """
    names = doc.get("outputs")
    if names is not None:
        if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
            raise InputFormatError(source, "key 'outputs'", f"expected a list of names, found {names!r}")
        if len(names) != n_outputs:
            raise InputFormatError(source, "key 'outputs'", f"{len(names)} names for {n_outputs} data file(s)")
        if len(set(names)) != len(names):
            raise InputFormatError(source, "key 'outputs'", f"names must differ, found {names!r}")
    tables = doc.get("mode")
    priors = []
    for k in range(n_outputs):
        one = {key: value for key, value in doc.items() if key != "outputs"}
        if isinstance(tables, list):
            one["mode"] = [_output_entry(t, source, i + 1, k, n_outputs) for i, t in enumerate(tables)]
        priors.append(parse_prior_mapping(one, source))
    return priors, None if names is None else tuple(names)


def _output_entry(table: Any, source: str, index: int, k: int, n_outputs: int) -> Any:
    """Mode table ``index`` with every per-output array replaced by its entry ``k``."""
    if not isinstance(table, Mapping):
        return table
    out = dict(table)
    for key in PER_OUTPUT_KEYS:
        value = table.get(key)
        if isinstance(value, list):
            if len(value) != n_outputs:
                raise InputFormatError(source, f"[[mode]] {index}", f"{key}: {len(value)} entries for {n_outputs} output(s) "
                                       "(give a number, or one entry per --data file)")
            out[key] = value[k]
    return out
