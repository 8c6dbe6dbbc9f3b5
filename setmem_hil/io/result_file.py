"""The identify result JSON (public contract, see README).

``{"modes": [{"a1": [lo, hi], "a0": [lo, hi], "b1": [lo, hi], "b0": [lo, hi]}, ...],
"conservatism": {"embedding_gamma": [...], "mismatch_ratio": [...]}, "iterations": N}``,
modes in the prior's order. Readers need only ``modes`` (a simulation model may give
zero-width intervals and omit the rest); extra keys are allowed and ignored.

``identify`` also writes, per mode, ``"verified": true|false`` (every bound of the mode carries a
checked dual certificate of the conic program, see
:mod:`setmem_hil.identification.one_mode_solver`) and, where false, ``"unverified_reason"``;
``"conservatism": {"notes": [...]}`` says, per mode whose gamma exceeds the target, why
(no finite partition, or the partition budget); and, when ``[residuals]`` are enabled in the prior, ``"residuals": {"lower": [lo, hi],
"upper": [lo, hi]}`` (only the enabled terms).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import InputFormatError
from setmem_hil.io.atomic_file import json_safe, write_json_atomic
from setmem_hil.model.modal_model import PARAM_NAMES, IntervalModel


def parse_result_mapping(doc: Any, source: str) -> IntervalModel:
    """Validate a parsed result document and return its interval model."""
    if not isinstance(doc, Mapping):
        raise InputFormatError(source, "", f"expected a JSON object, found {type(doc).__name__}")
    modes = doc.get("modes")
    if not isinstance(modes, list) or not modes:
        raise InputFormatError(source, "key 'modes'", "expected a non-empty list of modes")
    lo = np.empty((len(modes), 4))
    hi = np.empty((len(modes), 4))
    for i, mode in enumerate(modes):
        where = f"modes[{i}]"
        if not isinstance(mode, Mapping):
            raise InputFormatError(source, where, f"expected an object, found {type(mode).__name__}")
        for j, name in enumerate(PARAM_NAMES):
            pair = mode.get(name)
            if not isinstance(pair, list) or len(pair) != 2:
                raise InputFormatError(source, f"{where}.{name}", f"expected [lo, hi], found {pair!r}")
            for k, v in enumerate(pair):
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
                    raise InputFormatError(source, f"{where}.{name}", f"expected finite numbers, found {pair!r}")
            if pair[0] > pair[1]:
                raise InputFormatError(source, f"{where}.{name}", f"lower bound {pair[0]} > upper bound {pair[1]}")
            lo[i, j], hi[i, j] = float(pair[0]), float(pair[1])
    return IntervalModel(lo, hi)


def read_result_outputs(path: str | os.PathLike, n_outputs: int) -> list[IntervalModel]:
    """One model per output from a RESULT.json written with several outputs (issue 25): the
    shared ``a1, a0`` with each output's ``b1, b0`` from ``modes[i]["outputs"]``. A one-output
    file serves every output alike only when ``n_outputs`` is 1."""
    path = Path(path)
    base = read_result(path)
    doc = json.loads(path.read_text(encoding="utf-8"))
    modes = doc["modes"]
    lists = [m.get("outputs") for m in modes]
    if n_outputs == 1 and all(entry is None for entry in lists):
        return [base]
    if any(not isinstance(entry, list) or len(entry) != n_outputs for entry in lists):
        found = "none" if all(entry is None for entry in lists) else "another number"
        raise InputFormatError(str(path), "modes[].outputs", f"expected residues of {n_outputs} outputs (one per --data), found {found}")
    models = []
    for k in range(n_outputs):
        lo, hi = base.lower.copy(), base.upper.copy()
        for i, entry in enumerate(lists):
            for j, name in ((2, "b1"), (3, "b0")):
                pair = entry[k].get(name) if isinstance(entry[k], Mapping) else None
                if not isinstance(pair, list) or len(pair) != 2 or pair[0] > pair[1]:
                    raise InputFormatError(str(path), f"modes[{i}].outputs[{k}].{name}", f"expected [lo, hi], found {pair!r}")
                lo[i, j], hi[i, j] = float(pair[0]), float(pair[1])
        models.append(IntervalModel(lo, hi))
    return models


def read_result(path: str | os.PathLike) -> IntervalModel:
    path = Path(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(str(path), "", f"cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputFormatError(str(path), f"line {exc.lineno}", f"invalid JSON: {exc.msg}") from None
    return parse_result_mapping(doc, str(path))


def result_document(model: IntervalModel, embedding_gamma, mismatch_ratio, iterations: int,
                    verified=None, unverified_reason=None, residuals: Mapping[str, Any] | None = None,
                    conservatism_notes=None, **extra) -> dict[str, Any]:
    # JSON has no infinity: an unbounded ratio is written as null (json_safe)
    modes = model.named_intervals()
    if verified is not None and len(verified) == len(modes):
        reasons = list(unverified_reason or [""] * len(modes))
        for mode, ok, reason in zip(modes, verified, reasons):
            mode["verified"] = bool(ok)
            if not ok:
                mode["unverified_reason"] = str(reason) or "no certificate obtained"
    doc: dict[str, Any] = {
        "modes": modes,
        "conservatism": {
            "embedding_gamma": json_safe([float(v) for v in embedding_gamma]),
            "mismatch_ratio": json_safe([float(v) for v in mismatch_ratio]),
        },
        "iterations": int(iterations),
    }
    if conservatism_notes:
        doc["conservatism"]["notes"] = [str(n) for n in conservatism_notes]
    if residuals:
        doc["residuals"] = {name: [float(v) for v in pair] for name, pair in residuals.items()}
    doc.update(extra)
    return doc


def write_json(doc: Mapping[str, Any], path: str | os.PathLike) -> None:
    """Write JSON atomically (:func:`setmem_hil.io.atomic_file.write_json_atomic`)."""
    write_json_atomic(doc, path)
