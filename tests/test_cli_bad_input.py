"""Every command on bad input: its documented exit code, one line on stderr, no traceback.

Run through the installed entry point (a subprocess, as a technician runs it) for a few cases
and in-process for the rest; ``--debug`` is the only way to see a traceback.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from setmem_hil.cli.main import main

REPO = Path(__file__).resolve().parents[1]
PRIOR = """
[[mode]]
omega_min = 0.89
omega_max = 1.12
zeta_max = 0.5
b1 = 0.0
"""
GOOD_CSV = "omega,re,im,bound\n" + "".join(
    f"{w},{1.0 / (1.0 - w * w):.9g},0.0,0.01\n" for w in (0.5, 0.7, 0.8, 1.2, 1.4, 1.6))


def _files(tmp: Path) -> dict[str, str]:
    files = {
        "good.csv": GOOD_CSV,
        "prior.toml": PRIOR,
        "bad.csv": "omega,re,im\n1,2,3\n",
        "garbled.csv": "\x00\x01 not a csv at all",
        "bad.toml": "[[mode]\nomega_min = ",
        "bad.json": "{not json",
        "model_wrong.json": '{"modes": [{"a1": [1, 0]}]}',
        "conflict.csv": "omega,re,im,bound\n0.5,1.3,0,0.001\n0.5,-5,0,0.001\n",
        "proc_typo.toml": (REPO / "procedures" / "beam_6_3_2.toml").read_text().replace("[goal]", "[goal]\nmu_targt = 1.0", 1),
        "proc_bad_kind.toml": (REPO / "procedures" / "beam_6_3_2.toml").read_text().replace('kind = "sim"', 'kind = "telepathy"', 1),
        "not_a_run/readme.txt": "no journal here",
    }
    for name, text in files.items():
        path = tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return {name: str(tmp / name) for name in files}


CASES = [
    # (name, argv template, expected exit code)
    ("identify: missing data file", ["identify", "--data", "{tmp}/nope.csv", "--prior", "{prior.toml}", "--out", "{tmp}/r.json"], 2),
    ("identify: CSV without bound column", ["identify", "--data", "{bad.csv}", "--prior", "{prior.toml}", "--out", "{tmp}/r.json"], 2),
    ("identify: garbled CSV", ["identify", "--data", "{garbled.csv}", "--prior", "{prior.toml}", "--out", "{tmp}/r.json"], 2),
    ("identify: malformed TOML prior", ["identify", "--data", "{good.csv}", "--prior", "{bad.toml}", "--out", "{tmp}/r.json"], 2),
    ("identify: data inconsistent with the prior", ["identify", "--data", "{conflict.csv}", "--prior", "{prior.toml}", "--out", "{tmp}/r.json"], 3),
    ("analyze: malformed JSON model", ["analyze", "--model", "{bad.json}", "--out", "{tmp}/a.json"], 2),
    ("analyze: model with crossed bounds", ["analyze", "--model", "{model_wrong.json}", "--out", "{tmp}/a.json"], 2),
    ("analyze: missing model", ["analyze", "--model", "{tmp}/none.json", "--out", "{tmp}/a.json"], 2),
    ("discrepancy: missing data", ["discrepancy", "--data", "{tmp}/none.csv", "--prior", "{prior.toml}", "--out", "{tmp}/d.json"], 2),
    ("discrepancy: malformed model", ["discrepancy", "--data", "{good.csv}", "--model", "{bad.json}", "--out", "{tmp}/d.json"], 2),
    ("run: misspelt key", ["run", "--check", "{proc_typo.toml}"], 2),
    ("run: unknown backend", ["run", "--check", "{proc_bad_kind.toml}"], 2),
    ("run: missing procedure", ["run", "{tmp}/none.toml", "--out", "{tmp}/run"], 2),
    ("run: resume of a folder without journal", ["run", "--resume", "{tmp}/not_a_run"], 2),
    ("export: not a run directory", ["export", "{tmp}/not_a_run", "--csv", "{tmp}/csv"], 2),
    ("report: not a run directory", ["report", "{tmp}/not_a_run"], 2),
    ("sweep: bad seed range", ["sweep", "--procedure", "{proc_typo.toml}", "--seeds", "x-y", "--out", "{tmp}/sw"], 2),
]


def _argv(template, files, tmp):
    def fill(arg: str) -> str:
        for name, path in {**files, "tmp": str(tmp)}.items():
            arg = arg.replace("{" + name + "}", path)
        return arg

    return [fill(a) for a in template]


@pytest.mark.parametrize("name, template, code", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gives_exit_code_and_one_line(tmp_path, capsys, name, template, code):
    files = _files(tmp_path)
    assert main(_argv(template, files, tmp_path)) == code
    err = capsys.readouterr().err.strip()
    assert err.startswith("setmem-hil: ") and len(err.splitlines()) == 1, err
    assert "Traceback" not in err


@pytest.mark.parametrize("name, template, code", [CASES[0], CASES[4], CASES[10]], ids=["missing-file", "inconsistent", "typo"])
def test_installed_command_prints_no_traceback_unless_debug(tmp_path, name, template, code):
    files = _files(tmp_path)
    cmd = [sys.executable, "-m", "setmem_hil.cli.main", *_argv(template, files, tmp_path)]
    plain = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert plain.returncode == code and "Traceback" not in plain.stderr
    assert len(plain.stderr.strip().splitlines()) == 1, plain.stderr
    debug = subprocess.run(cmd[:3] + ["--debug"] + cmd[3:], capture_output=True, text=True, timeout=120)
    assert debug.returncode == code and "Traceback" in debug.stderr


def test_every_setmem_error_has_an_exit_code_and_a_message():
    import inspect

    from setmem_hil import errors
    from setmem_hil.cli.main import exit_code_and_message

    expected = {"InputFormatError": 2, "ProcedureError": 2, "SafetyLimitError": 2, "InconsistentDataError": 3,
                "DeviceError": 4, "DeviceTimeoutError": 4, "FrameError": 4, "DeviceDisconnectedError": 4,
                "DeviceRejectedError": 4, "ModbusExceptionError": 4, "DeviceIdentityError": 4, "CampaignAborted": 130,
                "OutputNotConfirmedOffError": 4, "MeasuredLimitError": 4}
    for name, cls in inspect.getmembers(errors, inspect.isclass):
        if not issubclass(cls, errors.SetmemError) or cls is errors.SetmemError:
            continue
        required = [p for p in inspect.signature(cls.__init__).parameters.values()
                    if p.name != "self" and p.default is p.empty and p.kind is p.POSITIONAL_OR_KEYWORD]
        exc = cls(*(["a problem"] * max(1, len(required))))
        code, message = exit_code_and_message(exc)
        assert code == expected.get(name, 1), name
        assert message and "\n" not in message


# --- issue 17: absurd values on otherwise good data; never exit 0 with bounds not derived from data ---
def _beam_rows():
    import numpy as np

    from setmem_hil.io.procedure import thesis_6_3_2_initial_omegas
    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    ms = SimulatedBeamExperiment(seed=1).measure_many(np.array(thesis_6_3_2_initial_omegas()))
    return [[repr(m.omega_rad_s), repr(m.response.real), repr(m.response.imag), repr(m.bound)] for m in ms]


ABSURD = [
    ("re 1e18", 3, 1, "1e18", 3),
    ("re 1e40", 3, 1, "1e40", 3),
    ("re 1e308", 3, 1, "1e308", 2),
    ("omega 1e308", 14, 0, "1e308", 2),
    ("omega negative", 2, 0, "-3.0", 2),
    ("bound NaN", 4, 3, "nan", 2),
    ("re inf", 4, 1, "inf", 2),
    ("re subnormal", 3, 1, "5e-324", 3),
    ("bound huge", 5, 3, "1e200", 2),
]


@pytest.mark.parametrize("name, row, col, value, code", ABSURD, ids=[a[0] for a in ABSURD])
def test_absurd_values_give_their_exit_code_never_a_prior_box(tmp_path, capsys, name, row, col, value, code):
    rows = _beam_rows()
    rows[row][col] = value
    data = tmp_path / "data.csv"
    data.write_text("\ufeffomega,re,im,bound\n" + "\n".join(",".join(r) for r in rows) + "\n")  # with a BOM, as spreadsheets write
    out = tmp_path / "r.json"
    assert main(["identify", "--data", str(data), "--prior", str(REPO / "procedures" / "beam_6_3_2.toml"), "--out", str(out)]) == code
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "Warning" not in err, err
    assert not out.exists()


def test_good_data_with_a_bom_and_a_procedure_as_prior_identifies(tmp_path, capsys):
    rows = _beam_rows()
    data = tmp_path / "data.csv"
    data.write_text("\ufeffomega,re,im,bound\n" + "\n".join(",".join(r) for r in rows) + "\n")
    assert main(["identify", "--data", str(data), "--prior", str(REPO / "procedures" / "beam_6_3_2.toml"), "--out", str(tmp_path / "r.json")]) == 0
    assert "identified 3 mode(s) from 15 points" in capsys.readouterr().out


def test_output_into_a_missing_folder_fails_before_computing(tmp_path, capsys):
    files = _files(tmp_path)
    assert main(["identify", "--data", files["good.csv"], "--prior", files["prior.toml"], "--out", str(tmp_path / "no" / "r.json")]) == 2
    assert "does not exist" in capsys.readouterr().err


def _model_doc(changes=None):
    import json

    from setmem_hil.sim_backends.beam import beam_parameters

    v = beam_parameters().truncated(3).values
    modes = [{k: [float(v[i, j]) * 0.95, float(v[i, j]) * 1.05] for j, k in enumerate(("a1", "a0", "b1", "b0"))} for i in range(3)]
    for (i, key), interval in (changes or {}).items():
        modes[i][key] = interval
    return json.dumps({"modes": modes, "conservatism": {"embedding_gamma": [1, 1, 1], "mismatch_ratio": [1, 1, 1]}, "iterations": 1})


@pytest.mark.parametrize("changes, where", [({(0, "a0"): [-1.0, 1.0]}, "mode 1 a0"), ({(1, "a1"): [0.01, 1e308]}, "mode 2 a1"),
                                            ({(2, "a1"): [-0.5, 0.5]}, "mode 3 a1")])
def test_analyze_refuses_models_it_cannot_mean(tmp_path, capsys, changes, where):
    (tmp_path / "m.json").write_text(_model_doc(changes))
    assert main(["analyze", "--model", str(tmp_path / "m.json"), "--out", str(tmp_path / "a.json")]) == 2
    err = capsys.readouterr().err
    assert where in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "a.json").exists()


def test_analyze_takes_a_weights_only_file_and_prints_a_summary(tmp_path, capsys):
    from setmem_hil.model.weights import THESIS_WEIGHTS

    (tmp_path / "m.json").write_text(_model_doc())
    (tmp_path / "w.toml").write_text("[weights]\n" + "\n".join(f"{k} = {list(getattr(THESIS_WEIGHTS, k))}" for k in ("w1_num", "w1_den", "w2_num", "w2_den")) + "\n")
    assert main(["analyze", "--model", str(tmp_path / "m.json"), "--procedure", str(tmp_path / "w.toml"), "--out", str(tmp_path / "a.json")]) == 0
    assert "mu-bar peak" in capsys.readouterr().out


def test_empty_files_and_wrong_types_are_named(tmp_path, capsys):
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "header_only.csv").write_text("omega,re,im,bound\n")
    (tmp_path / "typed.toml").write_text('[[mode]]\nomega_min = 0.9\nomega_max = 1.1\nzeta_max = "small"\nb1 = 0\n')
    prior = REPO / "procedures" / "beam_6_3_2.toml"
    for data, where in (("empty.csv", "empty file"), ("header_only.csv", "no data rows")):
        assert main(["identify", "--data", str(tmp_path / data), "--prior", str(prior), "--out", str(tmp_path / "r.json")]) == 2
        assert where in capsys.readouterr().err
    rows = _beam_rows()
    (tmp_path / "good.csv").write_text("omega,re,im,bound\n" + "\n".join(",".join(r) for r in rows) + "\n")
    assert main(["identify", "--data", str(tmp_path / "good.csv"), "--prior", str(tmp_path / "typed.toml"), "--out", str(tmp_path / "r.json")]) == 2
    assert "zeta_max" in capsys.readouterr().err


def test_duplicated_and_unsorted_rows_are_data_and_keep_the_guarantee(tmp_path, capsys):
    """Repeated measurements at one frequency and any row order are legitimate: exit 0, truth inside."""
    import json

    import numpy as np

    from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

    rows = _beam_rows()
    shuffled = [rows[i] for i in np.random.default_rng(2).permutation(len(rows))] + rows[:3]
    (tmp_path / "d.csv").write_text("omega,re,im,bound\n" + "\n".join(",".join(r) for r in shuffled) + "\n")
    out = tmp_path / "r.json"
    assert main(["identify", "--data", str(tmp_path / "d.csv"), "--prior", str(REPO / "procedures" / "beam_6_3_2.toml"), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    truth = SimulatedBeamExperiment(seed=1).modelled_truth.values
    lo = np.array([[m[k][0] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    hi = np.array([[m[k][1] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    assert np.all((lo <= truth) & (truth <= hi))
