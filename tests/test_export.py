"""CSV export of a journal: every stored number comes back exactly, in the documented layout."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.io.data_file import read_data_csv
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.export import EXPORT_FILES, export_csv
from setmem_hil.io.journal import IterationRecord, Journal


def _journal(tmp_path, n_iterations=3, seed=5):
    rng = np.random.default_rng(seed)
    j = Journal.create(tmp_path / "run" / "journal.sqlite", procedure_text="x", procedure_name="x", seed=seed,
                       software_version="t", backend="sim", strategy="mu")
    ms = [Measurement(float(w), complex(*rng.normal(size=2)), float(rng.uniform(0.01, 0.2))) for w in np.geomspace(0.3, 30, 15)]
    for m in ms:
        j.add_measurement(m, iteration=0, role="initial")
    recs = []
    for k in range(1, n_iterations + 1):
        lo = rng.uniform(0, 1, (3, 4))
        lo[:, 2] = 0.0
        hi = lo + rng.uniform(0.1, 1, (3, 4))
        hi[:, 2] = 0.0
        last = k == n_iterations
        rec = IterationRecord(
            k=k, n_points=14 + k, lower=lo, upper=hi, mu_peak=3.0 / k, mu_peak_omega=4.4, mu_lower_peak=2.0 / k,
            omega=np.geomspace(0.1, 100, 40), mu=rng.uniform(0, 3.0 / k, 40),
            sensitivities={f"{p}_{i}": float(rng.uniform()) for i in (1, 2, 3) for p in ("a1", "a0", "b0")},
            next_omega=None if last else float(rng.uniform(1, 20)),
            candidate_omega=np.zeros(0) if last else np.geomspace(0.1, 1000, 9),
            estimated_improvement=np.zeros(0) if last else rng.uniform(0, 0.5, 9),
            controller_order=6, safeguard="new-design", wall_s=0.25, embedding_gamma=np.ones(3), mismatch_ratio=np.zeros(3),
        )
        recs.append(rec)
        j.add_iteration(rec)
        if not last:
            m = Measurement(rec.next_omega, complex(*rng.normal(size=2)), 0.05)
            ms.append(m)
            j.add_measurement(m, iteration=k, role="added")
    j.add_event("safeguard", "iteration 2: expanded, with a comma")
    j.close()
    return tmp_path / "run", ms, recs


def _read(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_export_round_trips_every_number(tmp_path):
    run, ms, recs = _journal(tmp_path)
    paths = export_csv(run, tmp_path / "csv")
    assert [p.name for p in paths] == list(EXPORT_FILES)
    rows = _read(tmp_path / "csv" / "measurements.csv")
    assert [int(r["seq"]) for r in rows] == list(range(1, len(ms) + 1))
    assert [Measurement(float(r["omega_rad_s"]), complex(float(r["re"]), float(r["im"])), float(r["bound"])) for r in rows] == ms
    assert [r["role"] for r in rows] == ["initial"] * 15 + ["added"] * 2
    assert [int(r["iteration"]) for r in rows[15:]] == [1, 2]
    data = read_data_csv(tmp_path / "csv" / "data.csv")
    # issue 40: data.csv in ascending frequency (the added points sit among the initial ones);
    # measurements.csv above keeps the measurement order
    assert data.measurements() == sorted(ms, key=lambda m: m.omega_rad_s) and data.measurements() != ms

    bounds = _read(tmp_path / "csv" / "bounds.csv")
    assert len(bounds) == 3 * 3 * 4
    for r in bounds:
        rec = recs[int(r["k"]) - 1]
        i, j = int(r["mode"]) - 1, ("a1", "a0", "b1", "b0").index(r["parameter"])
        assert (float(r["lower"]), float(r["upper"])) == (rec.lower[i, j], rec.upper[i, j])
        assert int(r["n_points"]) == rec.n_points

    mu = _read(tmp_path / "csv" / "mu.csv")
    for k, rec in enumerate(recs, start=1):
        mine = [r for r in mu if int(r["k"]) == k]
        np.testing.assert_array_equal([float(r["omega_rad_s"]) for r in mine], rec.omega)
        np.testing.assert_array_equal([float(r["mu"]) for r in mine], rec.mu)

    its = _read(tmp_path / "csv" / "iterations.csv")
    assert [float(r["mu_peak"]) for r in its] == [3.0, 1.5, 1.0]
    assert its[-1]["next_omega"] == "" and float(its[0]["next_omega"]) == recs[0].next_omega

    sens = _read(tmp_path / "csv" / "sensitivities.csv")
    assert [r["parameter"] for r in sens[:3]] == ["a1_1", "a0_1", "b0_1"]  # mode, then a1 a0 b1 b0
    assert {(int(r["k"]), r["parameter"]): float(r["sensitivity"]) for r in sens} == {(rec.k, p): v for rec in recs for p, v in rec.sensitivities.items()}

    cand = _read(tmp_path / "csv" / "candidates.csv")
    assert len(cand) == 18 and {int(r["k"]) for r in cand} == {1, 2}
    assert [float(r["estimated_improvement"]) for r in cand if r["k"] == "2"] == list(recs[1].estimated_improvement)

    events = _read(tmp_path / "csv" / "events.csv")
    assert events[0]["message"] == "iteration 2: expanded, with a comma"


def test_non_finite_values_are_spelled(tmp_path):
    j = Journal.create(tmp_path / "r" / "journal.sqlite", procedure_text="x", procedure_name="x", seed=1, software_version="t", backend="sim", strategy="mu")
    lo = np.full((1, 4), -np.inf)
    j.add_iteration(IterationRecord(1, 1, lo, -lo, math.inf, 1.0, 0.5, np.array([1.0]), np.array([math.inf]), {}, None,
                                    np.zeros(0), np.zeros(0), 2, "new-design", 0.0, np.ones(1), np.zeros(1)))
    j.close()
    export_csv(tmp_path / "r", tmp_path / "out")
    assert _read(tmp_path / "out" / "iterations.csv")[0]["mu_peak"] == "inf"
    assert {r["lower"] for r in _read(tmp_path / "out" / "bounds.csv")} == {"-inf"}
    assert _read(tmp_path / "out" / "measurements.csv") == []


def test_export_command(tmp_path, capsys):
    run, ms, _ = _journal(tmp_path)
    assert main(["export", str(run), "--csv", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "bounds.csv").stat().st_size > 0
    assert main(["export", str(run)]) == 0  # issue 17: --csv defaults to DIR/csv
    assert (run / "csv" / "bounds.csv").stat().st_size > 0
    capsys.readouterr()
    assert main(["export", str(tmp_path / "nothing"), "--csv", str(tmp_path / "o2")]) == 2
    assert "no journal" in capsys.readouterr().err


@pytest.mark.slow
def test_export_uff_writes_one_58_record_per_output_that_identify_reads_back(tmp_path, capsys):
    """Issue 39, item 4: `export RUN --uff FILE.uff` (with or without --csv): UFF dataset 58, one
    FRF record per output, frequency in Hz, displacement over force, double precision (58b);
    pyuff reads the same numbers back (a second reader than ours), and `identify` takes the file."""
    import json

    import pyuff

    from setmem_hil.io.journal import read_snapshot
    from setmem_hil.model.frequency_data import FrequencyData

    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    run = tmp_path / "run"
    procedure = (repo / "procedures" / "beam_6_3_2_fast.toml").read_text().replace(
        "[backend.simulation]", "[backend.simulation]\nsensors = [1.0, 0.7]", 1)
    (tmp_path / "p.toml").write_text(procedure)
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(run), "--quiet", "--design", "h2"]) == 0
    assert main(["export", str(run), "--uff", str(tmp_path / "run.uff")]) == 0
    assert not (run / "csv").exists()  # only what was asked for
    records = pyuff.UFF(str(tmp_path / "run.uff")).read_sets()
    measurements = read_snapshot(run).measurements
    assert len(records) == 2 == 1 + len(measurements[0].others)
    for k, record in enumerate(records):
        truth = FrequencyData.from_measurements(measurements, output=k).sorted_by_frequency()
        assert record["type"] == 58 and record["func_type"] == 4 and record["ord_data_type"] == 6
        assert record["abscissa_spec_data_type"] == 18 and record["ordinate_spec_data_type"] == 8 and record["orddenom_spec_data_type"] == 13
        np.testing.assert_allclose(2 * np.pi * np.asarray(record["x"]), truth.omega_rad_s, rtol=1e-15)
        assert np.array_equal(np.asarray(record["data"]), truth.response)
    assert main(["export", str(run), "--uff", str(tmp_path / "both.uff"), "--csv", str(tmp_path / "csv")]) == 0
    assert (tmp_path / "both.uff").exists() and (tmp_path / "csv" / "data.csv").exists()
    capsys.readouterr()
    bound = float(max(m.bound for m in measurements)) * 3
    assert main(["identify", "--data", str(tmp_path / "run.uff"), "--bound-abs", str(bound), "--prior", str(tmp_path / "p.toml"),
                 "--out", str(tmp_path / "id.json")]) == 0
    assert len(json.loads((tmp_path / "id.json").read_text())["modes"]) == 3
