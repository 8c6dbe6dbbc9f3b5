"""The campaign journal: round trips, append-only, refusal to overwrite, typed errors."""

from __future__ import annotations

import math
import sqlite3

import numpy as np
import pytest

from setmem_hil.errors import InputFormatError
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import IterationRecord, Journal, JournalError


def _create(tmp_path, **overrides):
    kw = dict(procedure_text="name = 'x'\n", procedure_name="x", seed=7, software_version="9.9", backend="sim", strategy="mu")
    kw.update(overrides)
    return Journal.create(tmp_path / "run" / "journal.sqlite", **kw)


def _record(k: int, rng: np.random.Generator, next_omega=2.5) -> IterationRecord:
    lo = rng.uniform(0, 1, (3, 4))
    return IterationRecord(
        k=k, n_points=14 + k, lower=lo, upper=lo + rng.uniform(0, 1, (3, 4)),
        mu_peak=float(rng.uniform(1, 3)), mu_peak_omega=1.01, mu_lower_peak=0.9,
        omega=np.geomspace(0.1, 100, 50), mu=rng.uniform(0, 2, 50),
        sensitivities={"a0_1": 0.3, "a1_2": 0.01}, next_omega=next_omega,
        candidate_omega=np.geomspace(0.1, 100, 7), estimated_improvement=rng.uniform(0, 0.1, 7),
        controller_order=6, safeguard="new-design", wall_s=1.5,
        embedding_gamma=np.array([1.05, 1.1, 1.02]), mismatch_ratio=np.array([0.1, 0.2, 0.3]),
    )


def test_run_info_round_trip(tmp_path):
    j = _create(tmp_path)
    info = j.run_info()
    assert info["procedure_text"] == "name = 'x'\n"
    assert (info["procedure_name"], info["seed"], info["software_version"], info["backend"], info["strategy"]) == ("x", 7, "9.9", "sim", "mu")
    assert info["finished"] is False and info["summary"] is None
    assert "T" in info["created_utc"]
    j.finish({"mu_peak": 0.98, "n_measurements": 3})
    info = j.run_info()
    assert info["finished"] is True and info["summary"] == {"mu_peak": 0.98, "n_measurements": 3}
    with pytest.raises(JournalError, match="already finished"):
        j.finish({})
    j.close()


def test_measurements_round_trip_in_order(tmp_path):
    rng = np.random.default_rng(1)
    ms = [Measurement(float(w), complex(*rng.normal(size=2)), float(rng.uniform(0.01, 0.1))) for w in rng.uniform(0.1, 50, 20)]
    j = _create(tmp_path)
    seqs = [j.add_measurement(m, iteration=0 if i < 15 else i - 14, role="initial" if i < 15 else "added") for i, m in enumerate(ms)]
    assert seqs == list(range(1, 21))
    j.close()
    j = Journal.open(tmp_path / "run")  # a directory opens its journal.sqlite
    assert j.measurements() == ms  # exact floats survive
    rows = j.measurement_rows()
    assert [r["seq"] for r in rows] == list(range(1, 21))
    assert [r["role"] for r in rows] == ["initial"] * 15 + ["added"] * 5
    assert rows[16]["iteration"] == 2
    assert set(rows[0]) == {"seq", "iteration", "role", "omega_rad_s", "re", "im", "bound", "utc", "rig_s", "others"}
    assert j.integrity_problems() == []
    j.close()


def test_iteration_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    recs = [_record(1, rng), _record(2, rng, next_omega=None)]
    j = _create(tmp_path)
    for r in recs:
        j.add_iteration(r)
    with pytest.raises(JournalError, match="iteration 2 is already stored"):
        j.add_iteration(recs[1])
    got = j.iterations()
    assert [g.k for g in got] == [1, 2]
    for a, b in zip(recs, got):
        for name in ("lower", "upper", "omega", "mu", "candidate_omega", "estimated_improvement", "embedding_gamma", "mismatch_ratio"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert b.lower.shape == (3, 4)
        assert (a.mu_peak, a.sensitivities, a.next_omega, a.safeguard, a.controller_order) == (b.mu_peak, b.sensitivities, b.next_omega, b.safeguard, b.controller_order)
    assert got[1].next_omega is None
    j.close()


def test_infinite_bounds_survive(tmp_path):
    """The prior's box has +-inf residue bounds before the first identification."""
    rng = np.random.default_rng(3)
    r = _record(1, rng)
    lo = r.lower.copy()
    lo[:, 3] = -np.inf
    r = IterationRecord(**{**r.__dict__, "lower": lo, "mu_peak": math.nan})
    j = _create(tmp_path)
    j.add_iteration(r)
    got = j.iterations()[0]
    assert np.all(np.isneginf(got.lower[:, 3])) and math.isnan(got.mu_peak)
    j.close()


def test_discrepancies_and_events(tmp_path):
    j = _create(tmp_path)
    j.add_discrepancy(3, {"consistent": False, "omegas_rad_s": [1.0, 2.0]})
    j.add_event("fault", "timeout on dwell 4; retried")
    j.add_event("interrupted", "Ctrl-C")
    assert j.discrepancies() == [(3, {"consistent": False, "omegas_rad_s": [1.0, 2.0]})]
    assert [(e["kind"], e["message"]) for e in j.events()] == [("fault", "timeout on dwell 4; retried"), ("interrupted", "Ctrl-C")]
    j.close()


def test_refuses_to_overwrite(tmp_path):
    _create(tmp_path).close()
    with pytest.raises(InputFormatError, match="already exists"):
        _create(tmp_path)


def test_open_rejects_missing_and_foreign_files(tmp_path):
    with pytest.raises(InputFormatError, match="no journal"):
        Journal.open(tmp_path / "nowhere")
    text = tmp_path / "text.sqlite"
    text.write_text("hello")
    with pytest.raises(InputFormatError, match="not an SQLite database"):
        Journal.open(text)
    other = tmp_path / "other.sqlite"
    sqlite3.connect(other).execute("CREATE TABLE t (x)").connection.close()
    with pytest.raises(InputFormatError, match="not a setmem-hil journal"):
        Journal.open(other)


def test_append_only(tmp_path):
    j = _create(tmp_path)
    j.add_measurement(Measurement(1.0, 1 + 1j, 0.1), iteration=0, role="initial")
    j.close()
    conn = sqlite3.connect(tmp_path / "run" / "journal.sqlite")
    for sql in ("UPDATE measurement SET re = 0", "DELETE FROM measurement", "UPDATE run SET seed = 3"):
        with pytest.raises(sqlite3.DatabaseError, match="append-only"):
            conn.execute(sql)
    conn.close()
    j = Journal.open(tmp_path / "run")
    assert j.measurements() == [Measurement(1.0, 1 + 1j, 0.1)]
    j.close()


def test_rejects_bad_role_and_non_finite(tmp_path):
    j = _create(tmp_path)
    with pytest.raises(JournalError, match="role"):
        j.add_measurement(Measurement(1.0, 1j, 0.1), iteration=0, role="extra")
    with pytest.raises(JournalError, match="non-finite"):
        j.add_measurement(Measurement(1.0, complex(math.nan, 0), 0.1), iteration=0, role="initial")
    assert j.measurements() == []
    j.close()
    with pytest.raises(JournalError, match="closed"):
        j.add_event("x", "y")


def test_wal_mode_and_reader_during_writes(tmp_path):
    j = _create(tmp_path)
    assert j._db().execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    reader = Journal.open(tmp_path / "run")
    j.add_measurement(Measurement(2.0, 1j, 0.1), iteration=0, role="initial")
    assert reader.measurements() == [Measurement(2.0, 1j, 0.1)]  # committed, visible to another connection
    reader.close()
    j.close()


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra.numpy import arrays  # noqa: E402

_FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=30, deadline=None)
@given(
    n_modes=st.integers(1, 4),
    data=st.data(),
)
def test_iteration_records_round_trip_any_floats(tmp_path_factory, n_modes, data):
    lo = data.draw(arrays(float, (n_modes, 4), elements=_FLOATS))
    grid = data.draw(arrays(float, data.draw(st.integers(0, 30)), elements=_FLOATS))
    sens = data.draw(st.dictionaries(st.text(min_size=1, max_size=6), st.floats(allow_nan=False), max_size=5))
    nxt = data.draw(st.one_of(st.none(), st.floats(allow_nan=False, allow_infinity=False)))
    rec = IterationRecord(1, 3, lo, lo, data.draw(_FLOATS), 1.0, 0.5, grid, grid, sens, nxt, grid, grid, 4, "expanded", 0.1,
                          np.ones(n_modes), np.zeros(n_modes))
    d = tmp_path_factory.mktemp("j")
    j = Journal.create(d / "journal.sqlite", procedure_text="", procedure_name="h", seed=0, software_version="t", backend="sim", strategy="mu")
    j.add_iteration(rec)
    got = j.iterations()[0]
    j.close()
    for name in ("lower", "omega", "mu", "candidate_omega"):
        np.testing.assert_array_equal(getattr(got, name), getattr(rec, name))  # NaN == NaN here
    assert got.sensitivities == sens and got.next_omega == nxt
    assert (got.mu_peak == rec.mu_peak) or (math.isnan(got.mu_peak) and math.isnan(rec.mu_peak))


def test_certificate_round_trips_and_version_3_journals_are_upgraded(tmp_path):
    import dataclasses
    import sqlite3

    rng = np.random.default_rng(5)
    j = _create(tmp_path)
    j.add_iteration(dataclasses.replace(_record(1, rng), mu_peak_certified=True, mu_certified_intervals=17))
    j.add_iteration(dataclasses.replace(_record(2, rng), mu_peak_certified=False, mu_certified_intervals=3))
    got = j.iterations()
    assert [(g.mu_peak_certified, g.mu_certified_intervals) for g in got] == [(True, 17), (False, 3)]
    j.close()
    conn = sqlite3.connect(tmp_path / "run" / "journal.sqlite")  # as written before the certificate existed
    conn.execute("ALTER TABLE iteration DROP COLUMN mu_peak_certified")
    conn.execute("ALTER TABLE iteration DROP COLUMN mu_certified_intervals")
    conn.execute("ALTER TABLE iteration DROP COLUMN outputs")
    conn.execute("ALTER TABLE iteration DROP COLUMN common_gain")
    conn.execute("ALTER TABLE measurement DROP COLUMN others")
    conn.execute("ALTER TABLE iteration DROP COLUMN groups")  # version 8 (issue 47)
    conn.execute("ALTER TABLE iteration DROP COLUMN design")  # version 7 (issue 38)
    conn.execute("ALTER TABLE iteration DROP COLUMN floor_modes")
    conn.execute("ALTER TABLE run DROP COLUMN design")
    conn.execute("PRAGMA user_version=3")
    conn.commit()
    conn.close()
    with Journal.open(tmp_path / "run") as old:
        got = old.iterations()
    assert [g.k for g in got] == [1, 2] and all(g.mu_peak_certified is None and g.mu_certified_intervals is None for g in got)
    # every compensator of a journal from before issue 38 was an H2 design; the floor is a
    # function of the stored box
    assert all(g.design == "h2" for g in got)
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.model.mu_floor import floor_modes

    assert [g.floor_modes for g in got] == [floor_modes(IntervalModel(g.lower, g.upper)) for g in got]
    assert all(g.groups is None for g in got)  # not recorded before issue 47: the report says "-"


def test_the_groups_of_closely_spaced_modes_round_trip(tmp_path):
    import dataclasses

    rng = np.random.default_rng(6)
    j = _create(tmp_path)
    j.add_iteration(dataclasses.replace(_record(1, rng), groups=((1, 2),)))
    j.add_iteration(dataclasses.replace(_record(2, rng), groups=()))
    assert [g.groups for g in j.iterations()] == [((1, 2),), ()]
    j.close()


def test_other_sensors_round_trip(tmp_path):
    """Issue 25: a dwell's other sensors and an iteration's per-output bounds are stored."""
    import dataclasses

    j = _create(tmp_path)
    m = Measurement(1.5, 0.2 - 0.1j, 0.01, 3.0, ((0.05 + 0.3j, 0.002), (-1.0 + 0j, 0.02)))
    j.add_measurement(m, iteration=0, role="initial")
    j.add_measurement(Measurement(2.0, 1j, 0.1), iteration=0, role="initial")
    outputs = {"names": ["tip", "middle"], "lower": [[[0.0, 1.0, 0.0, 3.0]], [[0.0, 1.0, 0.0, -2.0]]],
               "upper": [[[0.1, 1.1, 0.0, 5.0]], [[0.1, 1.1, 0.0, -1.0]]]}
    j.add_iteration(dataclasses.replace(_record(1, np.random.default_rng(1)), outputs=outputs))
    got = j.measurements()
    assert got[0] == m and got[0].others == m.others and got[1].others == ()
    assert j.iterations()[0].outputs == outputs
    j.close()


def test_every_json_text_of_a_journal_is_valid_and_non_finite_values_read_back(tmp_path):
    """Issue 39, item 4: the journal held `Infinity` (embedding_gamma: 6 of 88 texts of the demo's
    journal failed SQLite's json_valid). Now every JSON text passes json_valid (SQLite's own
    parser: an independent reader), non-finite values are null, and they read back as they were
    written: an unbounded gamma or mu-bar as +inf, other values as NaN."""
    import math
    import sqlite3

    import numpy as np

    from setmem_hil.io.journal import IterationRecord, Journal

    j = Journal.create(tmp_path / "run" / "journal.sqlite", procedure_text="x", procedure_name="x", seed=1,
                       software_version="t", backend="sim", strategy="mu")
    lo = np.ones((2, 4))
    rec = IterationRecord(k=1, n_points=3, lower=lo, upper=lo + 1, mu_peak=math.inf, mu_peak_omega=1.0, mu_lower_peak=math.nan,
                          omega=np.array([1.0, 2.0]), mu=np.array([0.5, math.inf]), sensitivities={"a0_1": math.nan, "b0_1": 0.25},
                          next_omega=None, candidate_omega=np.zeros(0), estimated_improvement=np.zeros(0), controller_order=4,
                          safeguard="new-design", wall_s=0.1, embedding_gamma=np.array([math.inf, 1.5]),
                          mismatch_ratio=np.array([math.nan, 0.2]))
    j.add_iteration(rec)
    j.finish({"final_mu_peak": math.inf, "reached_goal": False})
    j.close()
    db = sqlite3.connect(tmp_path / "run" / "journal.sqlite")
    texts = []
    for (table,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'"):
        columns = [c[1] for c in db.execute(f"PRAGMA table_info({table})")]
        for column in columns:
            texts += db.execute(f"SELECT {column}, json_valid({column}) FROM {table} WHERE typeof({column}) = 'text' "
                                f"AND substr({column}, 1, 1) IN ('[', '{{')").fetchall()
    db.close()
    assert texts and all(valid for _, valid in texts), [t for t, valid in texts if not valid]
    with Journal.open(tmp_path / "run") as j:
        back = j.iterations()[0]
    assert back.mu[1] == math.inf and back.embedding_gamma[0] == math.inf and back.embedding_gamma[1] == 1.5
    assert math.isnan(back.mismatch_ratio[0]) and math.isnan(back.sensitivities["a0_1"]) and back.sensitivities["b0_1"] == 0.25
