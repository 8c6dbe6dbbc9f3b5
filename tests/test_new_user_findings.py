"""Issue 40, item 9: what a new user found, each with a test that failed before its fix.

(The live view's rig and elapsed time: tests/test_live_view.py; `prior` and rows in another
order: tests/test_prior_warnings.py; `export`'s data.csv order: tests/test_export.py.)
"""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("findings") / "run"
    assert main(["run", str(REPO / "procedures" / "beam_6_3_2_fast.toml"), "--out", str(out), "--quiet", "--design", "h2"]) == 0
    return out


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> Path:
    """A one-iteration run made in a second (tests/_synthetic_run.py): for the tests that need a
    journal with a compensator, not a campaign's history."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_synthetic_run", Path(__file__).with_name("_synthetic_run.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.one_iteration_run(tmp_path_factory.mktemp("findings-quick") / "run")[0]


@pytest.mark.slow
def test_a_journal_damaged_in_the_middle_is_exit_2_naming_the_file(finished_run, tmp_path, capsys):
    """Before: exit 1 "internal error (DatabaseError: database disk image is malformed)"."""
    damaged = tmp_path / "damaged"
    shutil.copytree(finished_run, damaged)
    journal = damaged / "journal.sqlite"
    size = journal.stat().st_size
    with open(journal, "r+b") as fh:  # past the header page: the file opens, its tables do not read
        fh.seek(size // 2)
        fh.write(b"\xde\xad\xbe\xef" * 1024)
    for argv in (["report", str(damaged)], ["export", str(damaged), "--csv", str(tmp_path / "csv")], ["run", "--resume", str(damaged)]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and str(journal) in err and "damaged" in err, err


@pytest.mark.slow  # its fixture is a whole fast campaign (26 s); the slow tests of this file share it
def test_report_of_a_missing_directory_names_it_not_the_parents_journal(finished_run, capsys):
    """Before: `report RUN/typo` wrote the report of RUN's journal (exit 0)."""
    missing = finished_run / "typo"
    assert main(["report", str(missing)]) == 2
    err = capsys.readouterr().err
    assert str(missing) in err and "no journal here" in err
    assert not (finished_run / "report.html").exists()


def _hz_procedure(tmp_path: Path, what: str) -> Path:
    text = (REPO / "procedures" / "beam_6_3_2.toml").read_text()
    if what == "modes":
        text = re.sub(r"(omega_min|omega_max) = ([0-9.]+)", lambda m: f"{m.group(1)} = {float(m.group(2)) / (2 * math.pi):.5g}", text)
    else:
        text = re.sub(r"omega_rad_s = \[([^\]]*)\]",
                      lambda m: "omega_rad_s = [" + ", ".join(f"{float(x) / (2 * math.pi):.5g}" for x in re.findall(r"[0-9.]+", m.group(1))) + "]",
                      text, flags=re.S)
    path = tmp_path / f"{what}_hz.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("what, words", [("modes", "the [[mode]] bands look like Hz"), ("initial", "the [initial] frequencies look like Hz")])
def test_a_prior_or_initial_list_in_hz_is_named_as_hz(tmp_path, capsys, what, words):
    """Before: caught, but explained as "mode coupling 1.79 >= 1" only."""
    assert main(["run", "--check", str(_hz_procedure(tmp_path, what))]) == 2
    err = capsys.readouterr().err
    assert words in err and "2 pi" in err, err


def test_shipped_procedures_are_not_taken_for_hz(capsys):
    for path in sorted((REPO / "procedures").glob("*.toml")):
        assert main(["run", "--check", str(path)]) == 0, path
    assert "look like Hz" not in capsys.readouterr().err


def test_controller_c_without_fs_prints_its_prefix_once(quick_run, tmp_path, capsys):
    """Before: "setmem-hil: setmem-hil controller: --format c needs --fs HZ"."""
    assert main(["controller", str(quick_run), "--format", "c", "--out", str(tmp_path / "k.h")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "setmem-hil: controller: --format c needs --fs HZ (the sections are discrete)", err


def test_iteration_axes_have_whole_number_ticks(quick_run, tmp_path, monkeypatch):
    """Before: the interval figure's iteration axis read 1.00, 1.25, 1.50, ... (matplotlib's
    default locator on a handful of iterations)."""
    from setmem_hil.io.journal import read_snapshot
    from setmem_hil.report import figures

    saved = []
    monkeypatch.setattr(figures, "_save", lambda fig, path, **adjust: saved.append(fig) or path)
    import dataclasses

    first = read_snapshot(quick_run).iterations[0]
    iterations = [first, dataclasses.replace(first, k=2, mu_peak=0.9 * first.mu_peak)]  # two: matplotlib's default ticks 1.00, 1.25, ...
    figures.interval_figure(iterations, tmp_path / "intervals.png")
    figures.mu_peak_figure(iterations, 1.0, tmp_path / "peak.png")
    for fig in saved:
        for ax in fig.axes:
            if ax.get_xlabel().startswith("iteration") or ax.get_xlabel() == "":
                lo, hi = ax.get_xlim()
                shown = [t for t in ax.get_xticks() if lo - 1e-9 <= t <= hi + 1e-9]
                assert shown and all(float(t).is_integer() for t in shown), shown


@pytest.mark.slow
@pytest.mark.parametrize("command", ["demo", "campaign"])
def test_progress_written_to_a_file_keeps_its_lines_whole(tmp_path, command):
    """Before: rich wrapped `demo`'s (and `campaign`'s) lines at 80 columns when stdout was a file:
    "procedure 'beam-6.3.2': ... strategy" then "mu, goal mu-bar < 1 ..." on the next line."""
    import os

    argv = {"demo": ["demo", "--out", str(tmp_path / "run"), "--design", "h2"],
            "campaign": ["campaign", "--procedure", str(REPO / "procedures" / "beam_6_3_2_fast.toml"), "--out", str(tmp_path / "run"), "--design", "h2"]}[command]
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    out = subprocess.run([sys.executable, "-m", "setmem_hil.cli.main", *argv], capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    summary = [line for line in lines if line.startswith("procedure ")]
    assert summary and summary[0].rstrip().endswith(", seed 1"), lines[:4]
    assert any(len(line) > 80 for line in lines)
    iteration_lines = [line for line in lines if re.match(r"iteration \d+: \d+ points", line)]
    assert iteration_lines and all("rig time" in line for line in iteration_lines), iteration_lines[:2]


def test_pyproject_refers_to_no_file_the_repository_lacks():
    """Before: `pymodbus~=3.16  # ... see ECOSYSTEM-NOTES`, a file that is not in the repository."""
    text = (REPO / "pyproject.toml").read_text()
    named = re.findall(r"\bsee ([A-Za-z0-9_./-]+)", text) + re.findall(r"\b([A-Z][A-Z0-9]+(?:-[A-Z0-9]+)+(?:\.md)?)\b", text)
    for name in named:
        candidates = [REPO / name, REPO / f"{name}.md", REPO / "docs" / name, REPO / "docs" / f"{name}.md"]
        assert any(c.exists() for c in candidates), f"pyproject.toml refers to {name!r}, not in the repository"


def test_readme_says_what_a_resumed_instrument_run_holds():
    """Before: "run --resume DIR completes the run with the measurements of an uninterrupted run",
    true on the simulated and loopback backends (bit for bit, tests/test_resume.py), not with
    instruments, whose measurements are taken anew on the wall clock."""
    text = " ".join((REPO / "README.md").read_text().split())
    at = text.index("`run --resume DIR` completes the run")
    paragraph = text[at: at + 700]
    assert "bit for bit" in paragraph and "simulated and loopback" in paragraph and "with instruments" in paragraph
