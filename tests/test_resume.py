"""Interrupt a campaign at several points, resume it, and get exactly the uninterrupted run:
the same measurements in the same order, no duplicates, the same iterations (issue 7)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.cli.main import main
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure_file import load_procedure

_spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)


def _procedure_file(tmp_path, max_experiments=3) -> Path:
    path = tmp_path / "cheap.toml"
    path.write_text(H.cheap_procedure_text(max_experiments))
    return path


def _reference(tmp_path, proc_path):
    """The uninterrupted run, straight through run_campaign (not the run command)."""
    p = load_procedure(proc_path)
    j = Journal.create(tmp_path / "ref" / "journal.sqlite", procedure_text=p.source_text, procedure_name=p.name, seed=p.seed,
                       software_version="ref", backend="sim", strategy="mu")
    run_campaign(p, H.simulated(p, p.seed), j)
    out = (j.measurement_rows(), j.iterations())
    j.close()
    return out


def _assert_same_iterations(got, want):
    assert [r.k for r in got] == [r.k for r in want]
    for a, b in zip(got, want):
        assert (a.n_points, a.next_omega, a.mu_peak) == (b.n_points, b.next_omega, b.mu_peak)
        np.testing.assert_array_equal(a.lower, b.lower)
        np.testing.assert_array_equal(a.upper, b.upper)


def _strip(rows):
    return [(r["seq"], r["iteration"], r["role"], r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in rows]


@pytest.mark.parametrize("interrupts", [
    (3, 13, 1, 1),   # during the initial dwells, the first added dwell, right after each replay
    pytest.param((15, 2), marks=pytest.mark.slow),  # the last initial dwell, then the second added one (17 s)
    (16,),           # the first added dwell only
], ids=["four-stops", "two-stops", "one-stop"])
def test_interrupted_and_resumed_equals_uninterrupted(tmp_path, monkeypatch, capsys, interrupts):
    H.install_fast_analysis(monkeypatch)
    proc = _procedure_file(tmp_path)
    ref_rows, ref_iterations = _reference(tmp_path, proc)
    assert len(ref_rows) == 18 and len({r["omega_rad_s"] for r in ref_rows[15:]}) >= 2  # the design moves around

    import setmem_hil.cli.commands.run as run_cmd

    experiments = []
    real_open = run_cmd.open_backend

    def open_interrupting(procedure, seed):
        at = interrupts[len(experiments)] if len(experiments) < len(interrupts) else None
        e = H.InterruptingExperiment(real_open(procedure, seed), at)
        experiments.append(e)
        return e

    monkeypatch.setattr(run_cmd, "open_backend", open_interrupting)
    run_dir = tmp_path / "run"
    code = main(["run", str(proc), "--out", str(run_dir), "--quiet"])
    for n in range(len(interrupts)):
        assert code == 130
        assert experiments[-1].closed  # exciter commanded to zero
        err = capsys.readouterr().err
        assert f"setmem-hil run --resume {run_dir}" in err
        j = Journal.open(run_dir)
        rows = j.measurement_rows()
        assert j.integrity_problems() == []
        assert _strip(rows) == _strip(ref_rows[: len(rows)])  # a prefix of the uninterrupted run
        assert j.events()[-1]["kind"] == "interrupted"
        j.close()
        code = main(["run", "--resume", str(run_dir), "--quiet"])
    assert code == 0
    j = Journal.open(run_dir)
    assert _strip(j.measurement_rows()) == _strip(ref_rows)
    _assert_same_iterations(j.iterations(), ref_iterations)
    info = j.run_info()
    assert info["finished"]
    kinds = [e["kind"] for e in j.events()]
    assert kinds.count("interrupted") == len(interrupts) and kinds.count("resumed") == len(interrupts)
    j.close()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["experiments_added"] == 3
    # no dwell was repeated: the experiments together measured each stored point exactly once
    measured = sum(e.calls - (1 if e.interrupt_at is not None and e.calls >= e.interrupt_at else 0) for e in experiments)
    assert measured == len(ref_rows)


@pytest.mark.slow
def test_real_analysis_interrupted_after_the_first_iteration(tmp_path, monkeypatch):
    """End to end with the real H2 design and mixed-mu analysis (one stop, after iteration 1)."""
    proc = _procedure_file(tmp_path, max_experiments=1)
    ref_rows, ref_iterations = _reference(tmp_path, proc)
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []
    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: made.append(H.InterruptingExperiment(real_open(p, s), 16 if not made else None)) or made[-1])
    run_dir = tmp_path / "run"
    assert main(["run", str(proc), "--out", str(run_dir), "--quiet"]) == 130
    j = Journal.open(run_dir)
    assert len(j.measurements()) == 15 and len(j.iterations()) == 1
    j.close()
    assert main(["run", "--resume", str(run_dir), "--quiet"]) == 0
    j = Journal.open(run_dir)
    assert _strip(j.measurement_rows()) == _strip(ref_rows)
    _assert_same_iterations(j.iterations(), ref_iterations)
    j.close()
