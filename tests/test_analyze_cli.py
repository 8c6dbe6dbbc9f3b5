"""``setmem-hil analyze`` command (public contract)."""

import dataclasses
import json

import pytest

from setmem_hil.cli.main import main
from setmem_hil.io.analysis_inputs import read_weights_table as _weights_from_table
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.io.result_file import result_document, write_json
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.model.weights import THESIS_WEIGHTS

TABLE_B1_LOWER = [[2.0911e-9, 8.8827e-1, 0.0, 2.7028], [4.5511e-9, 3.3851e1, 0.0, -1.4572], [1.6299e-9, 2.6725e2, 0.0, -7.8492]]
TABLE_B1_UPPER = [[1.2140e-1, 1.2333, 0.0, 7.6251], [5.3030e-1, 4.3162e1, 0.0, 7.6061], [2.5572, 3.5747e2, 0.0, 1.5549e1]]


def write_model(path, model):
    write_json(result_document(model, [1.0] * model.n_modes, [1.0] * model.n_modes, 1), path)


def test_analyze_writes_the_contract(tmp_path):
    model_path, out = tmp_path / "RESULT.json", tmp_path / "ANALYSIS.json"
    write_model(model_path, IntervalModel(TABLE_B1_LOWER, TABLE_B1_UPPER))
    assert main(["analyze", "--model", str(model_path), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    for key in ("mu_peak", "mu_peak_omega", "mu_lower_peak", "omega", "mu", "sensitivities", "controller_order"):
        assert key in doc
    assert set(doc["sensitivities"]) == {f"{p}_{m}" for p in ("a1", "a0", "b0") for m in (1, 2, 3)}
    assert len(doc["omega"]) == len(doc["mu"]) >= 200
    assert doc["mu_lower_peak"] <= doc["mu_peak"]
    assert max(doc["mu"]) == pytest.approx(doc["mu_peak"])
    assert doc["controller_order"] == 15
    assert doc["mu_peak_certified"] is True and doc["mu_certified_intervals"] >= 1 and doc["mu_peak_grid"] <= doc["mu_peak"]
    top3 = sorted(doc["sensitivities"], key=doc["sensitivities"].get, reverse=True)[:3]
    assert top3 == ["b0_1", "b0_2", "b0_3"]


def test_procedure_weights_are_used(tmp_path):
    from setmem_hil.io.procedure import default_procedure
    from setmem_hil.io.procedure_file import format_procedure

    model_path = tmp_path / "RESULT.json"
    write_model(model_path, IntervalModel.point(beam_parameters().truncated(3)))
    out_default, out_strict = tmp_path / "a.json", tmp_path / "b.json"
    assert main(["analyze", "--model", str(model_path), "--out", str(out_default)]) == 0
    # a performance weight twice as demanding: mu-bar must rise
    strict = dataclasses.replace(THESIS_WEIGHTS, w2_num=tuple(2.0 * c for c in THESIS_WEIGHTS.w2_num))
    proc = dataclasses.replace(default_procedure(), weights=strict)
    proc_path = tmp_path / "proc.toml"
    proc_path.write_text(format_procedure(proc))
    assert main(["analyze", "--model", str(model_path), "--procedure", str(proc_path), "--out", str(out_strict)]) == 0
    a, b = json.loads(out_default.read_text()), json.loads(out_strict.read_text())
    assert a["sensitivities"] == {} and b["sensitivities"] == {}
    assert b["mu_peak"] > 1.2 * a["mu_peak"]


def test_weights_table_fallback_reader(tmp_path):
    p = tmp_path / "w.toml"
    p.write_text("[weights]\nw2_num = [0.66, 1.0]\nw2_den = [1.0, 2.0]\nw2_extra_pole_rad_s = 5000\n")
    w = _weights_from_table(str(p))
    assert w.w2_num == (0.66, 1.0) and w.w2_extra_pole_rad_s == 5000.0
    assert w.w1_num == THESIS_WEIGHTS.w1_num
    p.write_text("[weights]\nw2_num = 'x'\n")
    with pytest.raises(Exception, match="w2_num"):
        _weights_from_table(str(p))


def test_malformed_model_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"modes": [{"a1": [1, 0]}]}')
    assert main(["analyze", "--model", str(bad), "--out", str(tmp_path / "o.json")]) == 2
    assert "bad.json" in capsys.readouterr().err
    assert not (tmp_path / "o.json").exists()
