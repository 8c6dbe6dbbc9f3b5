"""Property-based fuzzing of the data CSV, prior TOML and result JSON parsers (issue 8):
arbitrary input yields a parsed value or a typed InputFormatError, never another exception."""

import json

from hypothesis import given, settings
from hypothesis import strategies as st

from setmem_hil.io.data_file import parse_data_csv
from setmem_hil.errors import InputFormatError
from setmem_hil.model.prior import parse_prior_mapping, parse_toml_text
from setmem_hil.io.result_file import parse_result_mapping

CELL = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=6), st.integers().map(str))
ROW = st.lists(CELL, min_size=0, max_size=6).map(",".join)


@settings(max_examples=400, deadline=None)
@given(st.lists(ROW, max_size=8), st.booleans())
def test_data_csv_parser_only_raises_typed_errors(rows, with_header):
    text = "\n".join((["omega,re,im,bound"] if with_header else []) + rows)
    try:
        data = parse_data_csv(text, "fuzz.csv")
    except InputFormatError as exc:
        assert str(exc).startswith("fuzz.csv")
    else:
        assert len(data) >= 1


@settings(max_examples=400, deadline=None)
@given(st.text(max_size=300))
def test_data_csv_parser_on_raw_text(text):
    try:
        parse_data_csv(text, "fuzz.csv")
    except InputFormatError:
        pass


VALUE = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-10, 10**6), st.floats(allow_nan=False), st.text(max_size=5)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=12,
)
MODE_KEYS = st.sampled_from(["omega_min", "omega_max", "zeta_max", "b1", "b1_min", "b1_max", "b0_min", "b0_max", "x"])


@settings(max_examples=400, deadline=None)
@given(st.lists(st.dictionaries(MODE_KEYS, st.one_of(st.floats(-5, 50), VALUE), max_size=8), max_size=4),
       st.dictionaries(st.sampled_from(["gamma", "max_partitions", "other"]), VALUE, max_size=2))
def test_prior_parser_only_raises_typed_errors(modes, top):
    doc = dict(top)
    doc["mode"] = modes
    try:
        prior = parse_prior_mapping(doc, "fuzz.toml")
    except InputFormatError as exc:
        assert str(exc).startswith("fuzz.toml")
    else:
        assert all(m.omega_min <= m.omega_max for m in prior.modes)


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200))
def test_toml_text_parser_only_raises_typed_errors(text):
    try:
        doc = parse_toml_text(text, "fuzz.toml")
        parse_prior_mapping(doc, "fuzz.toml")
    except InputFormatError:
        pass


@settings(max_examples=400, deadline=None)
@given(VALUE)
def test_result_json_parser_only_raises_typed_errors(doc):
    try:
        parse_result_mapping(json.loads(json.dumps(doc)), "fuzz.json")
    except InputFormatError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.lists(st.dictionaries(st.sampled_from(["a1", "a0", "b1", "b0"]),
                                st.lists(st.one_of(st.floats(), st.integers(), st.text(max_size=2)), max_size=3), max_size=4), max_size=3))
def test_result_modes_parser_only_raises_typed_errors(modes):
    try:
        model = parse_result_mapping({"modes": modes}, "fuzz.json")
    except InputFormatError:
        pass
    else:
        assert (model.lower <= model.upper).all()
