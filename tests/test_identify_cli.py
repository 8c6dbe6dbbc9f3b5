"""The identify contract: files in, RESULT.json out, exit codes 0 / 2 / 3 with clear messages."""

import json
import subprocess
import sys

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.io.data_file import write_data_csv
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.sim_backends.thesis_cases import section_6_2_data

PRIOR = """gamma = 1.1
max_partitions = 200
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


@pytest.fixture
def files(tmp_path):
    data, beam = section_6_2_data(3)
    write_data_csv(data, tmp_path / "data.csv")
    (tmp_path / "prior.toml").write_text(PRIOR)
    return tmp_path, data, beam


def test_success_writes_contract_json_containing_truth(files):
    tmp, data, beam = files
    assert main(["identify", "--data", str(tmp / "data.csv"), "--prior", str(tmp / "prior.toml"), "--out", str(tmp / "r.json")]) == 0
    doc = json.loads((tmp / "r.json").read_text())
    assert len(doc["modes"]) == 3 and isinstance(doc["iterations"], int)
    lo = np.array([[m[k][0] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    hi = np.array([[m[k][1] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    t = beam.modelled_truth.values
    assert np.all((lo <= t) & (t <= hi))
    assert len(doc["conservatism"]["embedding_gamma"]) == 3 and len(doc["conservatism"]["mismatch_ratio"]) == 3


def test_point_outside_its_bound_exits_3_naming_it(files, capsys):
    tmp, data, _ = files
    g = data.response.copy()
    k = 7  # a point near the second peak
    g[k] += 10.0 * data.bound[k] * np.exp(0.3j)
    write_data_csv(FrequencyData(data.omega_rad_s, g, data.bound), tmp / "bad.csv")
    code = main(["identify", "--data", str(tmp / "bad.csv"), "--prior", str(tmp / "prior.toml"), "--out", str(tmp / "r.json")])
    assert code == 3
    err = capsys.readouterr().err
    assert f"{data.omega_rad_s[k]:.6g}" in err
    assert not (tmp / "r.json").exists()


def test_outlier_rejection_drops_the_bad_point(files, capsys):
    tmp, data, beam = files
    g = data.response.copy()
    g[7] += 10.0 * data.bound[7]
    write_data_csv(FrequencyData(data.omega_rad_s, g, data.bound), tmp / "bad.csv")
    code = main(["identify", "--data", str(tmp / "bad.csv"), "--prior", str(tmp / "prior.toml"), "--out", str(tmp / "r.json"), "--reject-outliers"])
    assert code == 0
    doc = json.loads((tmp / "r.json").read_text())
    assert [p["omega"] for p in doc["rejected_points"]] == [pytest.approx(data.omega_rad_s[7])]
    out = capsys.readouterr().out
    assert f"from {len(data.omega_rad_s) - 1} points (1 rejected)" in out  # the summary counts what was used


@pytest.mark.parametrize(
    "csv_text, fragment",
    [
        ("omega,re,im\n1,2,3\n", "expected header omega,re,im,bound"),
        ("omega,re,im,bound\n1,2,3\n", "line 2: expected 4 columns"),
        ("omega,re,im,bound\n1,2,x,0.1\n", "line 2: column im: expected a number"),
        ("omega,re,im,bound\n-1,2,3,0.1\n", "line 2: column omega: expected a positive frequency"),
        ("omega,re,im,bound\n1,2,3,-0.1\n", "line 2: column bound"),
        ("omega,re,im,bound\n1,nan,3,0.1\n", "line 2: column re: expected a finite number"),
        ("", "empty file"),
    ],
)
def test_malformed_csv_exits_2_naming_line(files, capsys, csv_text, fragment):
    tmp, _, _ = files
    (tmp / "m.csv").write_text(csv_text)
    assert main(["identify", "--data", str(tmp / "m.csv"), "--prior", str(tmp / "prior.toml"), "--out", str(tmp / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "m.csv" in err and fragment in err


@pytest.mark.parametrize(
    "prior_text, fragment",
    [
        ("[[mode]]\nomega_min = 7.3\nomega_max = 5.4\nzeta_max = 0.5\n", "[[mode]] 1: omega_min 7.3 > omega_max 5.4"),
        ("[[mode]]\nomega_min = 1\nzeta_max = 0.5\n", "[[mode]] 1: missing key 'omega_max'"),
        ("[[mode]]\nomega_min = 1\nomega_max = 2\nzeta_max = 0.5\nb1 = 0\nb1_min = 0\n", "either b1 (fixed) or b1_min/b1_max"),
        ("gamma = 0.9\n[[mode]]\nomega_min = 1\nomega_max = 2\nzeta_max = 0.5\n", "gamma 0.9 must be > 1"),
        ("[[mode]]\nomega_min = 1\nomega_max = 2\nzeta_max = 'big'\n", "zeta_max: expected a number"),
        ("[[mode\n", "invalid TOML"),
        ("[[mode]]\nomega_min = 1\nomega_max = 2\nzeta_max = 0.5\ncolour = 3\n", "unknown key 'colour'"),
    ],
)
def test_malformed_prior_exits_2_naming_key(files, capsys, prior_text, fragment):
    tmp, _, _ = files
    (tmp / "p.toml").write_text(prior_text)
    assert main(["identify", "--data", str(tmp / "data.csv"), "--prior", str(tmp / "p.toml"), "--out", str(tmp / "r.json")]) == 2
    err = capsys.readouterr().err
    assert "p.toml" in err and fragment in err


def test_installed_console_script_runs(files):
    tmp, _, _ = files
    proc = subprocess.run([sys.executable, "-m", "setmem_hil.cli.main", "identify", "--data", str(tmp / "data.csv"), "--prior",
                           str(tmp / "prior.toml"), "--out", str(tmp / "r.json")], capture_output=True, text=True, cwd=tmp)
    assert proc.returncode == 0, proc.stderr


def test_reject_outliers_with_a_prior_that_does_not_fit_shows_progress_and_stops(files, capsys):
    """A user's prior proposed from another sensor: --reject-outliers ran for minutes at full CPU
    with no output. Now every trial is reported and the search is bounded (documented maxima),
    then exit 3 says the prior does not fit."""
    tmp, data, _ = files
    wrong = PRIOR.replace("omega_min = 5.41\nomega_max = 7.34", "omega_min = 7.6\nomega_max = 9.0")  # mode 2 is at 6.27
    (tmp / "wrong.toml").write_text(wrong)
    code = main(["identify", "--data", str(tmp / "data.csv"), "--prior", str(tmp / "wrong.toml"), "--out", str(tmp / "r.json"),
                 "--reject-outliers"])
    err = capsys.readouterr().err
    trials = [line for line in err.splitlines() if line.startswith("reject-outliers: trial ")]
    assert code == 3 and not (tmp / "r.json").exists()
    assert 1 <= len(trials) <= 40  # the documented budget
    assert "prior does not fit" in err and "Traceback" not in err


def test_exit_3_says_which_mode_band_each_point_lies_in(files, capsys):
    """A user read "mode 6: ... points at 686 Hz" as mode 6's fault; the points lay next to mode 5.
    Here a point of mode 3's band, corrupted, makes mode 2's problem fail first: the message
    must file mode 3's points under mode 3's band."""
    tmp, data, _ = files
    g = data.response.copy()
    g[14] += 100.0 * data.bound[14]  # 18.0 rad/s, in mode 3's band
    write_data_csv(FrequencyData(data.omega_rad_s, g, data.bound), tmp / "bad.csv")
    code = main(["identify", "--data", str(tmp / "bad.csv"), "--prior", str(tmp / "prior.toml"), "--out", str(tmp / "r.json")])
    err = capsys.readouterr().err
    assert code == 3
    failing = int(err.split("mode ")[1].split(":")[0])
    assert failing != 3 and "(mode 3's band)" in err  # the points of another band are named as such
