"""``setmem-hil discrepancy`` end to end: exit codes, report keys, plot file."""

import json

import numpy as np

from setmem_hil.cli.main import main
from setmem_hil.io.data_file import write_data_csv
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.io.result_file import write_json
from setmem_hil.sim_backends.hidden_effects import draw_hidden_effect_case

PRIOR_TOML = """
[[mode]]
omega_min = 0.884
omega_max = 1.125
zeta_max = 0.5
b1 = 0
[[mode]]
omega_min = 5.41
omega_max = 7.34
zeta_max = 0.5
b1 = 0
[[mode]]
omega_min = 16.35
omega_max = 19.81
zeta_max = 0.5
b1 = 0
"""
CONTRACT_KEYS = {"disagreement_bands", "effects", "before", "after"}


def test_prior_path_names_a_lag_and_writes_report_and_plot(tmp_path, capsys):
    case = draw_hidden_effect_case("first_order_lag", 31)
    write_data_csv(case.data, tmp_path / "d.csv")
    (tmp_path / "p.toml").write_text(PRIOR_TOML)
    rc = main(["discrepancy", "--data", str(tmp_path / "d.csv"), "--prior", str(tmp_path / "p.toml"),
               "--out", str(tmp_path / "r.json"), "--plot", str(tmp_path / "f.png")])
    assert rc == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert CONTRACT_KEYS <= set(doc)
    assert [e["name"] for e in doc["effects"]] == ["first_order_lag"]
    tau = doc["effects"][0]["params"]["tau"]
    assert abs(tau / case.params["tau"] - 1) < 0.1
    assert doc["before"]["feasible"] is False and doc["after"]["feasible"] is True
    assert doc["after"]["max_normalized_residual"] <= 1.05 < doc["before"]["max_normalized_residual"]
    assert all(lo <= hi for lo, hi in doc["disagreement_bands"]) and doc["disagreement_bands"]
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # every long step said on stderr before it starts, with the time since the command began
    steps = [line for line in capsys.readouterr().err.splitlines() if line.startswith("discrepancy: [")]
    assert any("identifying 3 mode(s) from the prior" in line for line in steps)
    assert any("bound inflation: identifying with the bounds x" in line for line in steps)
    assert any("first_order_lag interval" in line for line in steps) and "re-identifying with first_order_lag" in steps[-1]


def test_model_path_with_zero_width_truth_on_clean_data_says_none(tmp_path):
    case = draw_hidden_effect_case("none", 32)
    write_data_csv(case.data, tmp_path / "d.csv")
    write_json({"modes": IntervalModel.point(case.truth).named_intervals()}, tmp_path / "m.json")
    rc = main(["discrepancy", "--data", str(tmp_path / "d.csv"), "--model", str(tmp_path / "m.json"),
               "--out", str(tmp_path / "r.json")])
    assert rc == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["effects"] == [] and doc["disagreement_bands"] == []
    # the truth itself is the model: its residual is the noise over the bound, <= 1
    noise = np.abs(case.data.response - case.truth.frequency_response(case.data.omega_rad_s)) / case.data.bound
    assert abs(doc["before"]["max_normalized_residual"] - noise.max()) < 1e-9
    assert doc["before"]["feasible"] is True


def test_malformed_data_exits_2(tmp_path, capsys):
    (tmp_path / "d.csv").write_text("omega,re,im,bound\n1.0,abc,0,1\n")
    (tmp_path / "p.toml").write_text(PRIOR_TOML)
    rc = main(["discrepancy", "--data", str(tmp_path / "d.csv"), "--prior", str(tmp_path / "p.toml"),
               "--out", str(tmp_path / "r.json")])
    assert rc == 2
    assert "line 2" in capsys.readouterr().err


def test_several_outputs_say_which_output_holds_the_effect(tmp_path, capsys):
    """Issue 25 item 5: the workflow per output; the lag is in the second sensor's data only."""
    clean, lagged = draw_hidden_effect_case("none", 32), draw_hidden_effect_case("first_order_lag", 31)
    write_data_csv(clean.data, tmp_path / "clean.csv")
    write_data_csv(lagged.data, tmp_path / "lagged.csv")
    (tmp_path / "p.toml").write_text(PRIOR_TOML)
    rc = main(["discrepancy", "--data", str(tmp_path / "clean.csv"), "--data", str(tmp_path / "lagged.csv"),
               "--prior", str(tmp_path / "p.toml"), "--out", str(tmp_path / "r.json"), "--plot", str(tmp_path / "f.png")])
    assert rc == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert CONTRACT_KEYS <= set(doc)
    assert [(e["name"], e["output"]) for e in doc["effects"]] == [("first_order_lag", "lagged")]
    assert [o["name"] for o in doc["outputs"]] == ["clean", "lagged"] and doc["outputs"][0]["effects"] == []
    assert doc["before"]["feasible"] is False and doc["after"]["feasible"] is True
    assert all(band[2] == "lagged" for band in doc["disagreement_bands"]) and doc["disagreement_bands"]
    assert (tmp_path / "f.png").is_file() and (tmp_path / "f-lagged.png").is_file()
    assert "output lagged: first_order_lag" in capsys.readouterr().err


def test_several_outputs_with_a_model_file_take_each_outputs_residues(tmp_path):
    clean, other = draw_hidden_effect_case("none", 32), draw_hidden_effect_case("none", 33)
    write_data_csv(clean.data, tmp_path / "a.csv")
    write_data_csv(other.data, tmp_path / "b.csv")
    modes = IntervalModel.point(clean.truth).named_intervals()
    for i, mode in enumerate(modes):
        mode["outputs"] = [{"name": n, "b1": mode["b1"], "b0": mode["b0"]} for n in ("a", "b")]
    write_json({"modes": modes, "outputs": ["a", "b"]}, tmp_path / "m.json")
    rc = main(["discrepancy", "--data", str(tmp_path / "a.csv"), "--data", str(tmp_path / "b.csv"), "--model", str(tmp_path / "m.json"),
               "--out", str(tmp_path / "r.json")])
    assert rc == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["effects"] == [] and [o["name"] for o in doc["outputs"]] == ["a", "b"]
    assert main(["discrepancy", "--data", str(tmp_path / "a.csv"), "--data", str(tmp_path / "b.csv"), "--data", str(tmp_path / "a.csv"),
                 "--model", str(tmp_path / "m.json"), "--out", str(tmp_path / "r2.json")]) == 2  # a file twice
