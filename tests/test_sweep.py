"""Sweep orchestration without Dask: arguments, storage, skip-done, failures, summary, plot, kill.

The campaigns are real (the section 6.3.2 procedure with a budget of 0 added experiments: one
identification + robust analysis each); failures are real too (a prior that excludes the beam's
first mode makes the identification inconsistent). The Dask paths are in ``test_sweep_dask.py``.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from setmem_hil.cli.main import main as cli_main
from setmem_hil.errors import InputFormatError, ProcedureError
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import BackendSettings, Goal
from setmem_hil.io.procedure_file import load_procedure, parse_procedure_text
from setmem_hil.sweep.runner import (
    parse_seeds,
    parse_strategies,
    run_sweep,
    summarize_runs,
    sweep_campaign,
)
from setmem_hil.sweep.plot import plot_experiments_to_goal

REPO = Path(__file__).resolve().parents[1]
PROCEDURE_FILE = REPO / "procedures" / "beam_6_3_2.toml"
# The beam's first natural frequency is 1.0 rad/s (section 6.1); this prior band excludes it.
BAD_PROCEDURE_TEXT = PROCEDURE_FILE.read_text(encoding="utf-8").replace(
    "omega_min = 0.884\nomega_max = 1.125", "omega_min = 2.0\nomega_max = 3.0")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def fast_procedure(max_experiments: int = 0):
    proc = load_procedure(PROCEDURE_FILE)
    return dataclasses.replace(proc, goal=Goal(mu_target=1.0, max_experiments=max_experiments))


def _bad_prior():
    return parse_procedure_text(BAD_PROCEDURE_TEXT, "bad.toml").prior


def task_failing_seed_2(procedure, seed, strategy, out_dir):
    """The real task, with a prior that excludes mode 1 for seed 2 (a genuine campaign failure)."""
    if seed == 2:
        procedure = dataclasses.replace(procedure, prior=_bad_prior())
    return sweep_campaign(procedure, seed, strategy, out_dir)


def task_boom(procedure, seed, strategy, out_dir):
    raise RuntimeError(f"boom at seed {seed}")


# ---------------------------------------------------------------------------- arguments
def test_parse_seeds_ranges_and_errors():
    assert parse_seeds("3-6") == (3, 4, 5, 6)
    assert parse_seeds("7") == (7,)
    assert parse_seeds("1-2, 5") == (1, 2, 5)
    for bad, fragment in [("6-3", "A <= B"), ("a-b", "integers"), ("1-2,2", "twice"), ("", "expected"), ("1,", "expected")]:
        with pytest.raises(InputFormatError, match=fragment) as info:
            parse_seeds(bad)
        assert str(info.value).startswith("--seeds")


def test_parse_strategies_names_the_allowed_values():
    assert parse_strategies("mu,random") == ("mu", "random")
    with pytest.raises(InputFormatError, match=r"--strategies.*mu, log-sweep, random, max-reduction.*'foo'"):
        parse_strategies("mu,foo")
    with pytest.raises(InputFormatError, match="twice"):
        parse_strategies("mu,mu")


def test_sweep_refuses_a_non_sim_backend(tmp_path):
    proc = dataclasses.replace(fast_procedure(), backend=BackendSettings(kind="can-virtual"))
    with pytest.raises(ProcedureError, match=r"\[backend\] kind.*simulated backend"):
        run_sweep(proc, [1], ["mu"], tmp_path, serial=True)


# ---------------------------------------------------------------------------- summary
def test_summary_statistics_by_hand():
    def row(strategy, seed, added, reached, error=None):
        r = {"seed": seed, "strategy": strategy, "reached_goal": reached, "experiments_added": added,
             "final_mu_peak": 0.9 if reached else 1.2, "wall_s": 1.0}
        if error:
            r.update(error=error, experiments_added=None, reached_goal=False)
        return r

    runs = [
        row("mu", 1, 3, True), row("mu", 2, 7, True), row("mu", 3, 5, True), row("mu", 4, 30, False),
        row("random", 1, 30, False), row("random", 2, 4, True), row("random", 3, 30, False),
        row("log-sweep", 1, None, False, error="RuntimeError: x"), row("log-sweep", 2, 9, True),
    ]
    s = summarize_runs(runs, ["mu", "random", "log-sweep", "max-reduction"])
    # mu: 3, 5, 7, inf -> median (5 + 7) / 2 = 6
    assert s["mu"] == {"median_experiments": 6.0, "reached": 3, "runs": 4, "failed": 0, "median_experiments_reached": 5.0}
    # random: 4, inf, inf -> median inf -> None (more than the budget)
    assert s["random"] == {"median_experiments": None, "reached": 1, "runs": 3, "failed": 0, "median_experiments_reached": 4.0}
    # log-sweep: the failed run is not a data point
    assert s["log-sweep"] == {"median_experiments": 9.0, "reached": 1, "runs": 2, "failed": 1, "median_experiments_reached": 9.0}
    assert s["max-reduction"] == {"median_experiments": None, "reached": 0, "runs": 0, "failed": 0, "median_experiments_reached": None}


def test_plot_writes_a_png(tmp_path):
    doc = {
        "runs": [
            {"seed": 1, "strategy": "mu", "reached_goal": True, "experiments_added": 7, "final_mu_peak": 0.98, "wall_s": 3.1},
            {"seed": 2, "strategy": "mu", "reached_goal": True, "experiments_added": 7, "final_mu_peak": 0.97, "wall_s": 3.0},
            {"seed": 1, "strategy": "random", "reached_goal": False, "experiments_added": 30, "final_mu_peak": 1.8, "wall_s": 9.0},
            {"seed": 2, "strategy": "random", "reached_goal": False, "experiments_added": None, "final_mu_peak": None,
             "wall_s": None, "error": "RuntimeError: x"},
        ],
        "strategies": ["mu", "random"], "goal": {"mu_target": 1.0, "max_experiments": 30}, "procedure": "beam-6.3.2",
    }
    out = plot_experiments_to_goal(doc, tmp_path / "sweep.png")
    data = out.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 5000
    assert not list(tmp_path.glob(".*tmp"))


# ---------------------------------------------------------------------------- storage, failures, skip
@pytest.mark.slow
def test_failed_campaign_is_recorded_not_fatal_and_retried(tmp_path):
    proc = fast_procedure(0)
    result = run_sweep(proc, [1, 2], ["mu"], tmp_path, serial=True, task=task_failing_seed_2, plot=False)
    assert result.executed == ("mu-seed1", "mu-seed2")
    assert result.failed == ("mu-seed2",)
    runs = tmp_path / "runs"
    # the good campaign is complete: its summary agrees with the journal's own copy
    good = json.loads((runs / "mu-seed1" / "summary.json").read_text())
    with Journal.open(runs / "mu-seed1") as j:
        info = j.run_info()
        n_meas = len(j.measurements())
    assert info["finished"] and info["summary"]["final_mu_peak"] == good["final_mu_peak"]
    assert info["seed"] == 1 and info["strategy"] == "mu" and info["backend"] == "sim"
    assert n_meas == len(proc.initial_omegas_rad_s)  # budget 0: the initial points only
    assert good["experiments_added"] == 0 and good["sweep"]["seed"] == 1
    # the failed one: error.json with the identification's message, the partial journal kept, no summary
    err = json.loads((runs / "mu-seed2" / "error.json").read_text())
    assert err["error_type"] == "InconsistentDataError" and "rad/s" in err["error"]
    assert not (runs / "mu-seed2" / "summary.json").exists()
    with Journal.open(runs / "mu-seed2") as j:
        assert not j.run_info()["finished"]
        assert any(e["kind"] == "error" for e in j.events())
    doc = json.loads((tmp_path / "sweep.json").read_text())
    assert [r["seed"] for r in doc["runs"]] == [1, 2]
    assert "error" not in doc["runs"][0] and doc["runs"][0]["final_mu_peak"] == good["final_mu_peak"]
    assert doc["runs"][1]["error"].startswith("InconsistentDataError")
    assert doc["summary"]["mu"]["failed"] == 1 and doc["summary"]["mu"]["runs"] == 2 and doc["failures"] == 1
    assert list((runs / ".partial").iterdir()) == []

    # re-run with the real task: only the failed campaign runs again; the finished one is untouched
    before = (runs / "mu-seed1" / "summary.json").stat()
    again = run_sweep(proc, [1, 2], ["mu"], tmp_path, serial=True, plot=False)
    assert again.skipped == ("mu-seed1",) and again.executed == ("mu-seed2",) and again.failed == ()
    after = (runs / "mu-seed1" / "summary.json").stat()
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
    assert not (runs / "mu-seed2" / "error.json").exists()
    assert json.loads((tmp_path / "sweep.json").read_text())["failures"] == 0


def test_task_exceptions_outside_the_campaign_are_recorded(tmp_path):
    result = run_sweep(fast_procedure(0), [1, 2], ["mu", "random"], tmp_path, serial=True, task=task_boom)
    assert len(result.failed) == 4
    err = json.loads((tmp_path / "runs" / "random-seed2" / "error.json").read_text())
    assert err["error"] == "RuntimeError: boom at seed 2" and "task_boom" in err["traceback"]
    doc = json.loads((tmp_path / "sweep.json").read_text())
    assert doc["failures"] == 4 and all(r["error"].startswith("RuntimeError") for r in doc["runs"])
    assert (tmp_path / "sweep.png").read_bytes()[:8] == PNG_MAGIC


def test_cli_exit_1_when_a_campaign_fails(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(BAD_PROCEDURE_TEXT, encoding="utf-8")
    out = tmp_path / "sweep"
    code = cli_main(["sweep", "--procedure", str(bad), "--seeds", "4-4", "--strategies", "log-sweep",
                     "--out", str(out), "--serial", "--quiet"])
    captured = capsys.readouterr()
    assert code == 1
    assert "campaign log-sweep-seed4 failed: InconsistentDataError" in captured.err
    assert json.loads((out / "sweep.json").read_text())["runs"][0]["error"].startswith("InconsistentDataError")


def test_cli_bad_arguments_exit_2(tmp_path, capsys):
    args = ["sweep", "--procedure", str(PROCEDURE_FILE), "--out", str(tmp_path), "--serial"]
    assert cli_main(args + ["--seeds", "5-1"]) == 2
    assert "--seeds" in capsys.readouterr().err
    assert cli_main(args + ["--seeds", "1", "--strategies", "mu,best"]) == 2
    assert "'best'" in capsys.readouterr().err
    assert cli_main(args + ["--seeds", "1", "--scheduler", "tcp://127.0.0.1:1"]) == 2
    assert not (tmp_path / "runs").exists()


def test_refuses_runs_of_a_different_procedure(tmp_path, capsys):
    calls = []

    def recording_task(procedure, seed, strategy, out_dir):  # must never be called
        calls.append(seed)
        raise AssertionError("ran")

    run_dir = tmp_path / "runs" / "mu-seed1"
    run_dir.mkdir(parents=True)
    (run_dir / "summary.json").write_text(json.dumps({
        "reached_goal": True, "experiments_added": 3, "final_mu_peak": 0.9, "wall_s": 1.0,
        "sweep": {"procedure_fingerprint": "0" * 64}}))
    with pytest.raises(InputFormatError, match="different procedure"):
        run_sweep(fast_procedure(0), [1, 2], ["mu"], tmp_path, serial=True, task=recording_task)
    assert calls == []
    code = cli_main(["sweep", "--procedure", str(PROCEDURE_FILE), "--seeds", "1-2", "--strategies", "mu",
                     "--out", str(tmp_path), "--serial", "--quiet"])
    assert code == 2 and "mu-seed1/summary.json" in capsys.readouterr().err


def test_one_sweep_per_directory(tmp_path):
    import fcntl

    with open(tmp_path / ".sweep.lock", "a+") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(InputFormatError, match="another sweep"):
            run_sweep(fast_procedure(0), [1], ["mu"], tmp_path, serial=True, task=task_boom)
    assert not (tmp_path / "runs").exists()


# ---------------------------------------------------------------------------- killed sweep
def _sweep_process(args: list[str], cwd: Path) -> subprocess.Popen:
    """``setmem-hil`` in a new session, with Ctrl-C handled even if this process ignores SIGINT."""
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from setmem_hil.cli.main import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=cwd, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _wait_for(predicate, timeout_s: float, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if proc is not None and proc.poll() is not None:
            out, err = proc.communicate()
            raise AssertionError(f"process ended early ({proc.returncode}): {out.decode()} {err.decode()}")
        if time.monotonic() > deadline:
            raise AssertionError("timed out")
        time.sleep(0.05)


@pytest.mark.slow
def test_killed_serial_sweep_leaves_no_half_run_and_resumes(tmp_path, capsys):
    out = tmp_path / "sweep"
    args = ["sweep", "--procedure", str(PROCEDURE_FILE), "--seeds", "1-2", "--strategies", "log-sweep",
            "--max-experiments", "0", "--out", str(out), "--serial", "--quiet"]
    first = out / "runs" / "log-sweep-seed1" / "summary.json"
    proc = _sweep_process(args, tmp_path)
    try:
        _wait_for(first.exists, 120, proc)
        os.killpg(proc.pid, signal.SIGKILL)  # mid-way through seed 2, no chance to clean up
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stdout.close()
        proc.stderr.close()
    runs = out / "runs"
    done_at_kill = sorted(p.name for p in runs.iterdir() if (p / "summary.json").exists())
    for p in runs.iterdir():  # nothing that looks like a run is half made
        if p.name != ".partial":
            assert (p / "summary.json").exists() and (p / "journal.sqlite").exists(), p
    assert done_at_kill == ["log-sweep-seed1"]  # seed 2 takes over a second; we kill within 50 ms
    stat1 = first.stat()
    capsys.readouterr()

    assert cli_main(args) == 0  # the same command again
    printed = capsys.readouterr().out
    assert f"({len(done_at_kill)} already done, {2 - len(done_at_kill)} run now, 0 failed now)" in printed
    assert (first.stat().st_ino, first.stat().st_mtime_ns) == (stat1.st_ino, stat1.st_mtime_ns)
    assert list((runs / ".partial").iterdir()) == []
    doc = json.loads((out / "sweep.json").read_text())
    assert [r["seed"] for r in doc["runs"]] == [1, 2] and doc["failures"] == 0
    for r in doc["runs"]:
        with Journal.open(runs / f"log-sweep-seed{r['seed']}") as j:
            info = j.run_info()
            assert info["finished"] and info["summary"]["final_mu_peak"] == r["final_mu_peak"]
            assert len(j.measurements()) == 15  # no duplicates from the interrupted attempt


def test_unreachable_scheduler_exit_1_and_nothing_run(tmp_path, capsys, monkeypatch):
    import socket

    import setmem_hil.sweep.runner as sweep_module

    monkeypatch.setattr(sweep_module, "CONNECT_TIMEOUT_S", 1.0)
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = cli_main(["sweep", "--procedure", str(PROCEDURE_FILE), "--seeds", "1", "--strategies", "mu",
                     "--out", str(tmp_path), "--scheduler", f"tcp://127.0.0.1:{port}", "--quiet"])
    assert code == 1
    assert f"--scheduler tcp://127.0.0.1:{port}: cannot reach the scheduler" in capsys.readouterr().err
    assert not any((tmp_path / "runs").glob("mu-*"))


def test_summary_table_text():
    from setmem_hil.sweep.runner import format_summary_table

    doc = {"goal": {"max_experiments": 30}, "summary": {
        "mu": {"median_experiments": 7.0, "reached": 10, "runs": 10, "failed": 0},
        "random": {"median_experiments": None, "reached": 2, "runs": 10, "failed": 1},
        "log-sweep": {"median_experiments": None, "reached": 0, "runs": 2, "failed": 2}}}
    lines = format_summary_table(doc).splitlines()
    assert lines[2].split() == ["mu", "|", "10", "|", "10", "|", "0", "|", "7"]
    assert lines[3].split() == ["random", "|", "10", "|", "2", "|", "1", "|", ">30"]
    assert lines[4].split() == ["log-sweep", "|", "2", "|", "0", "|", "2", "|", "-"]


def test_progress_counts_done_total_and_failures(tmp_path):
    def half_boom(procedure, seed, strategy, out_dir):
        if seed == 2:
            raise RuntimeError("boom")
        rec = {"seed": seed, "strategy": strategy, "status": "done"}
        # a stand-in finished run, stored like a real one so the next sweep skips it
        from setmem_hil.sweep.storage import procedure_fingerprint, write_json_atomic

        run = Path(out_dir) / "runs" / f"{strategy}-seed{seed}"
        run.mkdir(parents=True)
        write_json_atomic({"reached_goal": True, "experiments_added": seed, "final_mu_peak": 0.5, "wall_s": 0.0,
                           "sweep": {"procedure_fingerprint": procedure_fingerprint(procedure)}}, run / "summary.json")
        return rec

    calls = []
    run_sweep(fast_procedure(0), [1, 2, 3], ["mu"], tmp_path, serial=True, task=half_boom, plot=False,
              progress=lambda done, total, failures, rec: calls.append((done, total, failures, rec["seed"])))
    assert calls == [(1, 3, 0, 1), (2, 3, 1, 2), (3, 3, 1, 3)]
    calls.clear()
    again = run_sweep(fast_procedure(0), [1, 2, 3], ["mu"], tmp_path, serial=True, task=half_boom, plot=False,
                      progress=lambda done, total, failures, rec: calls.append((done, total, failures, rec["seed"])))
    assert calls == [(3, 3, 1, 2)]  # seeds 1 and 3 were done: counted from the start, only seed 2 runs
    assert again.skipped == ("mu-seed1", "mu-seed3") and again.failed == ("mu-seed2",)
    assert again.summary["mu"] == {"median_experiments": 2.0, "reached": 2, "runs": 3, "failed": 1,  # (1 + 3) / 2
                                   "median_experiments_reached": 2.0}


@pytest.mark.slow
def test_sweep_stores_the_discrepancy_check_of_every_iteration_as_run_does(tmp_path, monkeypatch):
    """[discrepancy] check_each_iteration means the same in a sweep as in `setmem-hil run` (one runner)."""
    from setmem_hil.campaign.session import start_run
    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.journal import Journal

    proc = dataclasses.replace(fast_procedure(1), discrepancy_check=True)
    result = run_sweep(proc, [3], ["mu"], tmp_path / "sweep", serial=True, plot=False)
    assert result.failed == ()
    swept = Journal.open(tmp_path / "sweep" / "runs" / "mu-seed3")
    try:
        checked = dict(swept.discrepancies())
        iterations = [rec.k for rec in swept.iterations()]
    finally:
        swept.close()
    assert iterations and sorted(checked) == iterations
    # the same procedure and seed through `run`'s path stores the same checks
    run = start_run(dataclasses.replace(proc, seed=3), tmp_path / "run", opener=open_experiment)
    ran = Journal.open(run.run_dir)
    try:
        # equal up to BLAS rounding (a sweep task pins BLAS to one thread for the whole campaign)
        assert _rounded(dict(ran.discrepancies())) == _rounded(checked)
    finally:
        ran.close()


def _rounded(obj, digits: int = 9):
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}")
    if isinstance(obj, dict):
        return {k: _rounded(v, digits) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_rounded(v, digits) for v in obj]
    return obj


@pytest.mark.slow  # a Dask sweep of whole campaigns (22 s)
def test_a_sweep_over_designs_runs_each_design_and_reports_it(tmp_path, monkeypatch):
    """Issue 46: ``--designs h2,robust`` is an axis like ``--strategies``. Each run is the
    campaign of that design (its journal and summary say so, the truth: the design each
    iteration's row records), named with it, and the document holds each design's summary.
    The contract of sweep.json, not the designs' numerics: the cheap analysis stands in."""
    import importlib.util

    from setmem_hil.sweep.runner import format_summary_table, parse_designs

    spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
    helpers = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(helpers)
    helpers.install_fast_analysis(monkeypatch)

    assert parse_designs("h2,robust") == ("h2", "robust")
    with pytest.raises(InputFormatError, match="--designs.*expected one of robust, h2.*lqg"):
        parse_designs("h2,lqg")
    result = run_sweep(fast_procedure(0), [1], ["mu"], tmp_path, serial=True, plot=True, designs=["h2", "robust"])
    assert sorted(p.name for p in (tmp_path / "runs").iterdir() if not p.name.startswith(".")) == ["mu-h2-seed1", "mu-robust-seed1"]
    doc = json.loads((tmp_path / "sweep.json").read_text())
    assert doc["designs"] == ["h2", "robust"] and set(doc["summary"]) == {"mu-h2", "mu-robust"}
    assert set(doc["by_design"]) == {"h2", "robust"} and set(doc["by_design"]["h2"]) == {"mu"}
    assert sorted((r["design"], r["strategy"]) for r in doc["runs"]) == [("h2", "mu"), ("robust", "mu")]
    for design in ("h2", "robust"):
        summary = json.loads((tmp_path / "runs" / f"mu-{design}-seed1" / "summary.json").read_text())
        assert {it["design"] for it in summary["iterations"]} == {design}
        journal = Journal.open(tmp_path / "runs" / f"mu-{design}-seed1")
        assert journal.run_info()["design"] == design
        journal.close()
    assert (tmp_path / "sweep.png").exists() and "mu-h2" in format_summary_table(result.document)
    # the default axis: the procedure's design, runs named as before
    again = run_sweep(fast_procedure(0), [1], ["mu"], tmp_path / "default", serial=True, plot=False)
    assert [r["design"] for r in again.runs] == [fast_procedure(0).design_method]
    assert (tmp_path / "default" / "runs" / "mu-seed1" / "summary.json").exists() and set(again.summary) == {"mu"}
