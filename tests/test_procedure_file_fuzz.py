"""Property-based fuzzing of the procedure parser (issue 8): whatever the input, only a typed
:class:`ProcedureError` (an :class:`InputFormatError`) escapes, and its message names the file.

Three generators: arbitrary text; the shipped demo file with random character edits (mostly
near-valid TOML); and the parsed demo document with one key replaced by an arbitrary value,
removed, or joined by an unknown key (valid TOML, invalid content). The number of cases run is
printed (``pytest -s``) and counted in ``FUZZ_CASES``.
"""

from __future__ import annotations

import copy
import datetime as dt
import math
import os
import tomllib
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from setmem_hil.errors import InputFormatError, ProcedureError
from setmem_hil.io.procedure import Procedure
from setmem_hil.io.procedure_file import parse_procedure_mapping, parse_procedure_text

DEMO = (Path(__file__).resolve().parents[1] / "procedures" / "beam_6_3_2.toml").read_text()
DEMO_DOC = tomllib.loads(DEMO)
SRC = "procedures/fuzz.toml"
FUZZ_CASES = {"text": 0, "edits": 0, "documents": 0, "rejected": 0}
# SETMEM_FUZZ_EXAMPLES=5000 runs a longer, randomised campaign; the default is fixed and quick.
_N = int(os.environ.get("SETMEM_FUZZ_EXAMPLES", "400"))
FUZZ = settings(max_examples=_N, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize="SETMEM_FUZZ_EXAMPLES" not in os.environ, database=None)


def _check(call) -> None:
    try:
        result = call()
    except ProcedureError as exc:
        FUZZ_CASES["rejected"] += 1
        assert isinstance(exc, InputFormatError)
        assert exc.source == SRC
        assert str(exc).startswith(SRC + ": ") and len(exc.problem) > 5
        assert "Traceback" not in str(exc)
        return
    assert isinstance(result, Procedure)


@FUZZ
@given(st.text(max_size=300))
def test_arbitrary_text(text):
    FUZZ_CASES["text"] += 1
    _check(lambda: parse_procedure_text(text, SRC))


_EDIT = st.tuples(st.integers(0, len(DEMO)), st.integers(0, 8), st.text(alphabet=st.sampled_from(list("=[]{}\"'.,#\n -01e9x_abinf")), max_size=6))


@FUZZ
@given(st.lists(_EDIT, min_size=1, max_size=4))
def test_random_edits_of_the_demo_file(edits):
    FUZZ_CASES["edits"] += 1
    text = DEMO
    for pos, n_delete, insert in edits:
        pos = min(pos, len(text))
        text = text[:pos] + insert + text[pos + n_delete:]
    _check(lambda: parse_procedure_text(text, SRC))


_SCALAR = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**63), 2**63 - 1), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12), st.sampled_from(["sim", "mu", "snr10", "timeout", "serial-loopback"]),
    st.datetimes(), st.dates(), st.times(),
)
_VALUE = st.recursive(_SCALAR, lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)), max_leaves=8)


def _paths(doc, prefix=()):
    """Every (path to a key) in the document, descending into tables and arrays of tables."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            if isinstance(v, dict):
                yield from _paths(v, prefix + (i,))


PATHS = list(_paths(DEMO_DOC)) + [("backend", "transport"), ("backend", "faults"), ("initial", "log_spaced"), ("weights", "w1_num")]


@FUZZ
@given(st.sampled_from(PATHS), st.sampled_from(["replace", "delete", "unknown"]), _VALUE, st.text(min_size=1, max_size=8))
def test_documents_with_one_bad_value(path, action, value, new_key):
    FUZZ_CASES["documents"] += 1
    doc = copy.deepcopy(DEMO_DOC)
    parent = doc
    for step in path[:-1]:
        if isinstance(parent, dict):
            parent = parent.setdefault(step, {})
        else:
            parent = parent[step]
    if not isinstance(parent, dict):
        return
    if action == "replace":
        parent[path[-1]] = value
    elif action == "delete":
        parent.pop(path[-1], None)
    else:
        parent[new_key] = value
    _check(lambda: parse_procedure_mapping(doc, SRC, ""))


def test_zz_report_fuzz_case_count():
    total = FUZZ_CASES["text"] + FUZZ_CASES["edits"] + FUZZ_CASES["documents"]
    print(f"\nprocedure parser fuzz: {total} cases ({FUZZ_CASES}); only ProcedureError escaped")
    for kind in ("text", "edits", "documents"):  # each fuzz test that ran, ran its examples
        assert FUZZ_CASES[kind] == 0 or FUZZ_CASES[kind] >= _N // 2, FUZZ_CASES


def test_fuzz_generators_reach_the_validator():
    """Sanity check of the document generator: a deep replacement is caught with its location."""
    doc = copy.deepcopy(DEMO_DOC)
    doc["mode"][1]["omega_max"] = dt.date(2020, 1, 1)
    try:
        parse_procedure_mapping(doc, SRC, "")
    except ProcedureError as exc:
        assert str(exc) == f"{SRC}: [[mode]] 2: omega_max: expected a number, found datetime.date(2020, 1, 1)"
    else:  # pragma: no cover
        raise AssertionError("a date as omega_max was accepted")
    assert not math.isnan(parse_procedure_mapping(DEMO_DOC, SRC, "").prior.gamma)
