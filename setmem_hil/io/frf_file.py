"""Measured FRF files to the model's receptance with error bounds: CSV and UFF 58.

* CSV (``omega,re,im,bound``, rad/s; :mod:`setmem_hil.io.data_file`): the default.
* UFF 58 (``.uff``/``.unv``, read with pyuff): the FRF record (function type 4) with its
  abscissa in Hz and its ordinate quantity (data-type 8 displacement, 11 velocity, 12
  acceleration, over 13 force); a coherence record (function type 6) of the same response and
  reference nodes is used by ``averages``. A UFF file carries no error bound: give
  ``bound_rel``/``bound_abs`` (``bound = rel |H| + abs`` in the file's own units) or, with a
  coherence record, ``averages`` (the H1 random error of Bendat & Piersol, *Random Data*, eq.
  9.90: ``eps = sqrt(1 - gamma^2) / (|gamma| sqrt(2 n_d))``, taken at ``COVERAGE`` = 3 standard
  deviations: a bound, not a guarantee, because the estimate is statistical).

Quantities: the model is a receptance (displacement per force, ``b1 = 0`` models a displacement
sensor). Mobility ``Y = j omega H`` and accelerance ``A = -omega^2 H`` are converted, with their
bounds, by dividing by ``j omega`` and ``-omega^2`` (the bound by ``omega`` and ``omega^2``).
Lines at 0 Hz cannot be converted and are dropped (said in ``notes``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.io.data_file import read_data_csv
from setmem_hil.model.frequency_data import FrequencyData

__all__ = ["QUANTITIES", "FrfLoad", "load_frf", "to_receptance", "COVERAGE"]

QUANTITIES = ("displacement", "velocity", "acceleration")
UFF_QUANTITY = {8: "displacement", 11: "velocity", 12: "acceleration"}
UFF_FRF, UFF_COHERENCE = 4, 6
COVERAGE = 3.0


@dataclass(frozen=True)
class FrfLoad:
    """A loaded FRF: receptance data with bounds, and what the reader did (``notes``)."""

    data: FrequencyData
    quantity: str
    notes: tuple[str, ...] = ()


def to_receptance(omega_rad_s, response, bound, quantity: str):
    """Convert ``response`` and ``bound`` of ``quantity`` per force to receptance (m/N)."""
    w = np.asarray(omega_rad_s, dtype=float)
    g = np.asarray(response, dtype=complex)
    r = np.asarray(bound, dtype=float)
    if quantity == "displacement":
        return g, r
    if quantity == "velocity":
        return g / (1j * w), r / w
    if quantity == "acceleration":
        return g / (-(w**2)), r / w**2
    raise ValueError(f"quantity: expected one of {', '.join(QUANTITIES)}, found {quantity!r}")


def load_frf(path: str | os.PathLike, *, quantity: str | None = None, bound_rel: float | None = None,
             bound_abs: float | None = None, averages: int | None = None) -> FrfLoad:
    """Read a CSV or UFF FRF file and return receptance data with bounds (see the module docs).

    Raises
    ------
    InputFormatError
        Unreadable file, no FRF record, a quantity that contradicts the file, or a UFF file
        without a way to bound its errors.
    """
    p = Path(path)
    try:
        return _load(p, quantity, bound_rel, bound_abs, averages)
    except ValueError as exc:  # FrequencyData's own checks (non-finite, out of range)
        if isinstance(exc, InputFormatError):
            raise
        raise InputFormatError(str(p), "", str(exc)) from None


def _load(p: Path, quantity, bound_rel, bound_abs, averages) -> FrfLoad:
    if quantity is not None and quantity not in QUANTITIES:
        raise InputFormatError(str(p), "--quantity", f"expected one of {', '.join(QUANTITIES)}, found {quantity!r}")
    if p.suffix.lower() in (".uff", ".unv"):
        return _load_uff(p, quantity, bound_rel, bound_abs, averages)
    if averages is not None or bound_rel is not None or bound_abs is not None:
        raise InputFormatError(str(p), "--bound-rel/--bound-abs/--averages", "a CSV file carries its own bound column; these options are for UFF files")
    data = read_data_csv(p)
    q = quantity or "displacement"
    if q == "displacement":
        return FrfLoad(data, q)
    keep = data.omega_rad_s > 0
    g, r = to_receptance(data.omega_rad_s[keep], data.response[keep], data.bound[keep], q)
    notes = () if keep.all() else (f"{int((~keep).sum())} line(s) at 0 rad/s dropped (cannot convert {q} to receptance)",)
    return FrfLoad(FrequencyData(data.omega_rad_s[keep], g, r), q, notes)


def load_frf_outputs(path: str | os.PathLike, *, quantity: str | None = None, bound_rel: float | None = None,
                     bound_abs: float | None = None, averages: int | None = None) -> list[tuple[str, FrfLoad]]:
    """Every output a file holds, in file order (issue 25): a CSV is one; a UFF file holding
    several FRF records with one reference (one shaker, several response points) is one output
    per record, named ``<stem> node <n> dir <d>``. Several references are refused."""
    p = Path(path)
    if p.suffix.lower() not in (".uff", ".unv"):
        return [(p.stem, load_frf(p, quantity=quantity, bound_rel=bound_rel, bound_abs=bound_abs, averages=averages))]
    records, frfs = _uff_frf_records(p)
    references = {(r.get("ref_node"), r.get("ref_dir")) for r in frfs}
    if len(references) > 1:
        raise InputFormatError(str(p), "", f"FRF records of {len(references)} references {sorted(references, key=str)}: "
                                           "several outputs must share one input (split the file by reference)")
    out = []
    for frf in frfs:
        name = p.stem if len(frfs) == 1 else f"{p.stem} node {frf.get('rsp_node')} dir {frf.get('rsp_dir')}"
        try:
            out.append((name, _uff_frf(p, frf, records, quantity, bound_rel, bound_abs, averages)))
        except ValueError as exc:
            if isinstance(exc, InputFormatError):
                raise
            raise InputFormatError(str(p), name, str(exc)) from None
    return out


def _uff_frf_records(p: Path) -> tuple[list, list]:
    """All data sets of a UFF file and its FRF records (UFF 58, function type 4)."""
    try:
        import pyuff
    except ImportError:  # pragma: no cover - pyuff is a core dependency
        raise InputFormatError(str(p), "", "reading UFF files needs pyuff (pip install pyuff)") from None
    try:
        records = pyuff.UFF(str(p)).read_sets()
    except Exception as exc:  # pyuff raises bare Exceptions on malformed files
        raise InputFormatError(str(p), "", f"not a readable UFF file ({exc})") from None
    records = records if isinstance(records, list) else [records]
    frfs = [r for r in records if r.get("type") == 58 and int(r.get("func_type", -1)) == UFF_FRF]
    if not frfs:
        kinds = sorted({(r.get("type"), r.get("func_type")) for r in records}, key=str)
        raise InputFormatError(str(p), "", f"no FRF record (UFF 58 with function type 4) among the data sets {kinds}")
    return records, frfs


def _load_uff(p: Path, quantity, bound_rel, bound_abs, averages) -> FrfLoad:
    records, frfs = _uff_frf_records(p)
    if len(frfs) > 1:
        raise InputFormatError(str(p), "", f"{len(frfs)} FRF records: identify, prior and discrepancy take them as one "
                                           "output each; elsewhere give one FRF per file (split the file)")
    return _uff_frf(p, frfs[0], records, quantity, bound_rel, bound_abs, averages)


def _uff_frf(p: Path, frf: dict, records: list, quantity, bound_rel, bound_abs, averages) -> FrfLoad:
    """One FRF record as receptance with its bound (module doc)."""
    f_hz = np.asarray(frf["x"], dtype=float)
    h = np.asarray(frf["data"], dtype=complex)
    declared = UFF_QUANTITY.get(int(frf.get("ordinate_spec_data_type", 0) or 0))
    if quantity and declared and quantity != declared:
        raise InputFormatError(str(p), "--quantity", f"the file's FRF is {declared} per force, not {quantity}")
    q = quantity or declared or "displacement"
    notes = [] if declared or quantity else ["the file does not declare its ordinate quantity; taken as displacement (give --quantity)"]
    if averages is not None:
        coh = [r for r in records if r.get("type") == 58 and int(r.get("func_type", -1)) == UFF_COHERENCE
               and r.get("rsp_node") == frf.get("rsp_node") and r.get("ref_node") == frf.get("ref_node")]
        if not coh:
            raise InputFormatError(str(p), "--averages", "the file holds no coherence record (function type 6) of this FRF; give --bound-rel/--bound-abs")
        if int(averages) < 1:
            raise InputFormatError(str(p), "--averages", f"expected a positive number of averages, found {averages}")
        gamma2 = np.clip(np.real(np.asarray(coh[0]["data"])).astype(float), 1e-12, 1.0)
        if gamma2.size != h.size:
            raise InputFormatError(str(p), "coherence record", f"{gamma2.size} lines, the FRF has {h.size}")
        eps = np.sqrt(1.0 - gamma2) / (np.sqrt(gamma2) * np.sqrt(2.0 * int(averages)))
        bound = COVERAGE * eps * np.abs(h) + (bound_abs or 0.0) + (bound_rel or 0.0) * np.abs(h)
    elif bound_rel is not None or bound_abs is not None:
        bound = (bound_rel or 0.0) * np.abs(h) + (bound_abs or 0.0)
    else:
        raise InputFormatError(str(p), "", "a UFF file carries no error bound: give --bound-rel R and/or --bound-abs A "
                                           "(bound = R |H| + A in the file's units), or --averages N with a coherence record")
    if np.any(bound < 0) or not np.all(np.isfinite(bound)):
        raise InputFormatError(str(p), "--bound-rel/--bound-abs", "the bound must be finite and non-negative")
    w = 2.0 * np.pi * f_hz
    keep = w > 0
    if not keep.all():
        notes.append(f"{int((~keep).sum())} line(s) at 0 Hz dropped (cannot convert {q} to receptance)")
    g, r = to_receptance(w[keep], h[keep], bound[keep], q)
    if g.size == 0:
        raise InputFormatError(str(p), "", "no FRF line above 0 Hz")
    return FrfLoad(FrequencyData(w[keep], g, r), q, tuple(notes))
