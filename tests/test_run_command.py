"""``setmem-hil run``: checking, running, refusing, interrupting, device faults, resuming."""

from __future__ import annotations

import importlib.util
import json
import os
from datetime import datetime, timezone
from pathlib import Path

import pytest

from setmem_hil import __version__
from setmem_hil.cli.main import main
from setmem_hil.errors import DeviceError
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import default_procedure

_spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def cheap(tmp_path, monkeypatch):
    H.install_fast_analysis(monkeypatch)
    path = tmp_path / "cheap.toml"
    path.write_text(H.cheap_procedure_text(2))
    return path


@pytest.mark.parametrize("path", sorted((REPO / "procedures").glob("*.toml")), ids=lambda p: p.name)
def test_check_accepts_every_shipped_procedure(path, capsys):
    assert main(["run", "--check", str(path)]) == 0
    assert capsys.readouterr().out.strip().endswith(f"{path}: OK")


def test_check_names_file_table_and_key(tmp_path, capsys):
    bad = tmp_path / "x.toml"
    bad.write_text((REPO / "procedures" / "beam_6_3_2.toml").read_text().replace("max_amplitude_n = 1.0", "max_amplitude_n = -1"))
    assert main(["run", "--check", str(bad)]) == 2
    assert f"{bad}: [safety]: max_amplitude_n -1 must be > 0" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["run"], "give a procedure file, or --resume DIR"),
    (["run", "p.toml", "--resume", "d"], "--resume DIR takes no procedure"),
    (["run", "--resume", "d", "--seed", "3"], "--resume DIR takes no procedure"),
])
def test_argument_errors(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_a_run_stores_everything_and_writes_the_summary(tmp_path, cheap, capsys):
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out), "--seed", "11", "--strategy", "log-sweep"]) == 0
    printed = capsys.readouterr().out
    assert f"run directory: {out}" in printed and "iteration 1:" in printed and "finished:" in printed
    j = Journal.open(out)
    info = j.run_info()
    assert info["procedure_text"] == cheap.read_text() == (out / "procedure.toml").read_text()
    assert (info["seed"], info["strategy"], info["software_version"], info["backend"]) == (11, "log-sweep", __version__, "sim")
    assert info["finished"] and len(j.measurements()) == 17
    summary = json.loads((out / "summary.json").read_text())
    assert summary == json.loads(json.dumps(info["summary"]))
    assert summary["seed"] == 11 and summary["strategy"] == "log-sweep" and summary["experiments_added"] == 2
    j.close()
    # the same --out again is refused, nothing is overwritten
    assert main(["run", str(cheap), "--out", str(out)]) == 2
    assert "already holds a run" in capsys.readouterr().err
    # resuming a finished run does nothing
    assert main(["run", "--resume", str(out)]) == 0
    assert "already finished" in capsys.readouterr().out


def test_resume_uses_the_stored_procedure_not_the_edited_file(tmp_path, cheap, monkeypatch):
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []
    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: made.append(H.InterruptingExperiment(real_open(p, s), 16 if not made else None)) or made[-1])
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out), "--quiet"]) == 130
    cheap.write_text(cheap.read_text().replace("max_experiments = 2", "max_experiments = 9"))
    (out / "procedure.toml").write_text("garbage = [")
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    j = Journal.open(out)
    assert len(j.measurements()) == 15 + 2  # the stored budget of 2, not the edited 9
    j.close()


@pytest.mark.slow
def test_device_fault_zeroes_the_exciter_and_can_be_resumed(tmp_path, cheap, monkeypatch, capsys):
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []

    def opener(p, s):
        made.append(H.InterruptingExperiment(real_open(p, s), 4 if not made else None, error=DeviceError))
        return made[-1]

    monkeypatch.setattr(run_cmd, "open_backend", opener)
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out), "--quiet"]) == 4
    assert made[0].closed
    err = capsys.readouterr().err
    assert "device fault" in err and f"setmem-hil run --resume {out}" in err
    j = Journal.open(out)
    assert len(j.measurements()) == 3 and j.events()[-1]["kind"] == "device-fault"
    j.close()
    assert main(["run", "--resume", str(out), "--quiet", "--report"]) == 0
    assert made[1].closed
    assert (out / "report.html").stat().st_size > 0 and (out / "fig_mu_peak.png").exists()


def test_default_run_directory(tmp_path, cheap, monkeypatch, capsys):
    from setmem_hil.run.run_directory import default_run_dir

    when = datetime(2026, 11, 21, 23, 5, 9, tzinfo=timezone.utc)
    assert default_run_dir(default_procedure(), when) == Path("runs") / "beam-6.3.2-20261121T230509Z"
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(cheap), "--quiet"]) == 0
    runs = list((tmp_path / "runs").iterdir())
    assert len(runs) == 1 and runs[0].name.startswith("cheap-") and (runs[0] / "summary.json").exists()


def test_programmatic_procedure_is_stored_as_text_and_resumable(tmp_path, monkeypatch):
    """start_run with default_procedure() (as the demo does) stores TOML that resume can read."""
    import dataclasses

    from setmem_hil.cli.commands.run import resume_run, start_run
    from setmem_hil.io.procedure_file import parse_procedure_text

    H.install_fast_analysis(monkeypatch)
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []
    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: made.append(H.InterruptingExperiment(real_open(p, s), 2 if not made else None)) or made[-1])
    proc = dataclasses.replace(default_procedure(), goal=dataclasses.replace(default_procedure().goal, max_experiments=0))
    with pytest.raises(KeyboardInterrupt):
        start_run(proc, tmp_path / "demo")
    j = Journal.open(tmp_path / "demo")
    stored = parse_procedure_text(j.run_info()["procedure_text"], "<stored>")
    j.close()
    assert dataclasses.replace(stored, source_text="") == proc
    outcome = resume_run(tmp_path / "demo")
    assert outcome.summary["experiments_added"] == 0 and len(outcome.summary["iterations"]) == 1


@pytest.mark.skipif(importlib.util.find_spec("setmem_hil.experiment_factory") is None, reason="transport backends not yet available")
@pytest.mark.parametrize("name", ["serial_loopback.toml", "can_virtual.toml", "modbus_loopback.toml"])
def test_loopback_procedures_run(tmp_path, monkeypatch, name):
    H.install_fast_analysis(monkeypatch)
    text = (REPO / "procedures" / name).read_text().replace("max_experiments = 2", "max_experiments = 1")
    proc = tmp_path / name
    proc.write_text(text)
    try:
        code = main(["run", str(proc), "--out", str(tmp_path / "run"), "--quiet"])
    except ModuleNotFoundError as exc:  # a transport still being written
        if not (exc.name or "").startswith("setmem_hil.drivers"):
            raise
        pytest.skip(f"{name}: {exc}")
    assert code == 0
    j = Journal.open(tmp_path / "run")
    kind = {"serial_loopback.toml": "serial-loopback", "can_virtual.toml": "can-virtual", "modbus_loopback.toml": "modbus-loopback"}[name]
    assert len(j.measurements()) == 16 and j.run_info()["backend"] == kind
    j.close()


def test_no_stray_files_left(tmp_path, cheap):
    assert main(["run", str(cheap), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    names = sorted(os.listdir(tmp_path / "r"))
    assert names == [".run.lock", "journal.sqlite", "procedure.toml", "raw", "raw.h5", "summary.json"]  # issue 39: raw records
    assert all(name.endswith(".h5") and not name.startswith(".") for name in os.listdir(tmp_path / "r" / "raw"))  # no partial file


def test_a_second_process_cannot_run_the_same_campaign(tmp_path, cheap, monkeypatch, capsys):
    import fcntl

    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []
    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: made.append(H.InterruptingExperiment(real_open(p, s), 3 if not made else None)) or made[-1])
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out), "--quiet"]) == 130
    with open(out / ".run.lock", "a+") as other:  # another process holding the run
        fcntl.flock(other.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert main(["run", "--resume", str(out), "--quiet"]) == 2
        assert "another setmem-hil process is running this campaign" in capsys.readouterr().err
    j = Journal.open(out)
    assert len(j.measurements()) == 2 and j.events()[-1]["kind"] == "interrupted"  # untouched
    j.close()
    assert main(["run", "--resume", str(out), "--quiet"]) == 0


def test_live_progress_on_a_terminal():
    import io

    from rich.console import Console

    from setmem_hil.cli.progress import CampaignProgress

    buf = io.StringIO()
    console = Console(file=buf, force_terminal=True, width=160)
    seen = []
    with CampaignProgress(console, planned_dwell_s=lambda w: 10.0 / w, on_event=lambda e, **i: seen.append(e)) as show:
        assert show.live
        show("measure", index=1, total=3, omega_rad_s=2.0, replayed=True)
        show("measure", index=2, total=3, omega_rad_s=4.0, replayed=False)
        show("iteration", k=1, n_points=2, mu_peak=float("inf"), mu_peak_omega=4.4, safeguard="expanded")
        show("chosen", k=1, next_omega=6.48)
        show("measure", index=3, total=3, omega_rad_s=6.48, replayed=False)
        task, dwell = show._progress.tasks
        assert task.description == "measurements" and (task.completed, task.total) == (2, 3)
        # frequencies in rad/s and Hz, compact enough for an 80-column terminal (issues 17, 18)
        assert dwell.description == "dwell 3 at 6.48 rad/s (1.031 Hz), 1.54 s" and dwell.total == pytest.approx(10.0 / 6.48)
        import time

        time.sleep(0.6)  # the dwell bar follows the wall clock while the dwell runs
        assert 0.3 < dwell.completed < dwell.total
        show("finished", summary=type("S", (), {"reached_goal": True, "final_mu_peak": 0.9, "experiments_added": 1})())
    text = buf.getvalue()
    assert "iteration 1: 2 points, mu-bar peak inf (nominal loop unstable) at 4.4 rad/s (0.7003 Hz) [expanded]" in text
    assert "next frequency 6.48 rad/s" in text and "finished: goal reached; mu-bar 0.9000" in text
    assert (show.replayed, show.measured) == (1, 2)
    assert seen == ["measure", "measure", "iteration", "chosen", "measure", "finished"]


def test_device_counters_are_journaled(tmp_path, cheap, monkeypatch):
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend

    class Counting(H.InterruptingExperiment):
        def __init__(self, inner):
            super().__init__(inner, None)
            self.counters = {}

        def measure(self, omega_rad_s):
            if self.calls in (2, 5):  # pretend the dwell driver discarded a dwell and retried
                self.counters["discarded_dwell"] = self.counters.get("discarded_dwell", 0) + 1
            return super().measure(omega_rad_s)

    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: Counting(real_open(p, s)))
    assert main(["run", str(cheap), "--out", str(tmp_path / "r"), "--quiet"]) == 0
    j = Journal.open(tmp_path / "r")
    events = [e for e in j.events() if e["kind"] == "discarded_dwell"]
    j.close()
    assert len(events) == 2 and "(total 2)" in events[1]["message"]


def test_the_retries_before_a_device_fault_are_journaled_before_the_fault(tmp_path, cheap, monkeypatch):
    """A dwell that retries twice and then fails: its retries are journaled (named with the dwell's
    frequency) before the fault, and the measurements before it are all kept."""
    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend

    class RetryingThenFailing(H.InterruptingExperiment):
        def __init__(self, inner):
            super().__init__(inner, 3, error=DeviceError)
            self.counters = {"retries": 0}

        def measure(self, omega_rad_s):
            if self.calls + 1 == 3:
                self.counters["retries"] += 2
            return super().measure(omega_rad_s)

    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: RetryingThenFailing(real_open(p, s)))
    assert main(["run", str(cheap), "--out", str(tmp_path / "r"), "--quiet"]) == 4
    j = Journal.open(tmp_path / "r")
    kinds = [e["kind"] for e in j.events()]
    retries = [e["message"] for e in j.events() if e["kind"] == "retries"]
    assert len(j.measurements()) == 2
    j.close()
    assert retries == [retries[0]] and "2 x retries (total 2) during the dwell at" in retries[0] and "(measurement 3)" in retries[0]
    assert kinds.index("retries") < kinds.index("device-fault")


def test_discrepancy_check_each_iteration_is_journaled_once_per_iteration(tmp_path, cheap, monkeypatch):
    import setmem_hil.cli.commands.run as run_cmd

    cheap.write_text(cheap.read_text() + "\n[discrepancy]\ncheck_each_iteration = true\n")
    real_open = run_cmd.open_backend
    made = []
    monkeypatch.setattr(run_cmd, "open_backend", lambda p, s: made.append(H.InterruptingExperiment(real_open(p, s), 17 if not made else None)) or made[-1])
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out), "--quiet"]) == 130
    j = Journal.open(out)
    assert [k for k, _ in j.discrepancies()] == [1, 2]
    j.close()
    assert main(["run", "--resume", str(out), "--quiet"]) == 0
    j = Journal.open(out)
    found = j.discrepancies()
    assert [k for k, _ in found] == [1, 2, 3] == [r.k for r in j.iterations()]
    assert all("decision" in report and "before" in report for _, report in found)
    j.close()


def test_a_rig_that_does_not_open_leaves_no_run_behind(tmp_path, cheap, monkeypatch, capsys):
    import setmem_hil.cli.commands.run as run_cmd
    from setmem_hil.errors import ProcedureError

    def refuse(p, s):
        raise ProcedureError(str(cheap), "[backend.transport] key 'reply_timeout_s'", "expected a positive float, found -1")

    monkeypatch.setattr(run_cmd, "open_backend", refuse)
    out = tmp_path / "run"
    assert main(["run", str(cheap), "--out", str(out)]) == 2
    assert "reply_timeout_s" in capsys.readouterr().err
    assert not (out / "journal.sqlite").exists()  # fix the file and run again into the same --out


def test_run_check_runs_the_residue_bootstrap_before_any_dwell(tmp_path, capsys):
    """Issue 17: a prior whose residues cannot be bounded at the initial frequencies fails --check
    (exit 2, naming the file and the overlapping bands), not after measuring every initial point."""
    text = (REPO / "procedures" / "beam_6_3_2.toml").read_text().replace("omega_min = 5.41", "omega_min = 0.9", 1)
    bad = tmp_path / "overlap.toml"
    bad.write_text(text)
    assert main(["run", "--check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "mode coupling" in err and "[[mode]] 1 and 2" in err and "overlap" in err
    assert main(["run", "--check", str(REPO / "procedures" / "beam_6_3_2.toml")]) == 0


def test_resume_with_a_corrected_procedure_reuses_every_stored_measurement(tmp_path, cheap, capsys):
    """Issue 17: a run stopped by a prior that excludes the first mode (exit 3 after measuring the
    initial points) continues with the corrected prior; nothing is measured twice; the change is
    journaled; a later plain resume keeps the corrected procedure. (The cheap procedure and the
    cheap analysis: the contract is the journal's, not the loop's numerics.)"""
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import load_procedure

    good_text = cheap.read_text()
    n_initial = len(load_procedure(cheap).initial_omegas_rad_s)
    bad_text = good_text.replace("omega_min = 0.884\nomega_max = 1.125", "omega_min = 1.3\nomega_max = 1.5", 1)
    assert bad_text != good_text
    (tmp_path / "bad.toml").write_text(bad_text)
    (tmp_path / "good.toml").write_text(good_text)
    run_dir = tmp_path / "run"
    assert main(["run", str(tmp_path / "bad.toml"), "--out", str(run_dir), "--quiet"]) == 3
    j = Journal.open(run_dir)
    stored = j.measurements()
    j.close()
    assert len(stored) == n_initial
    assert main(["run", "--resume", str(run_dir), "--procedure", str(tmp_path / "good.toml"), "--quiet"]) == 0
    j = Journal.open(run_dir)
    try:
        after = j.measurements()
        rows = j.measurement_rows()
        kinds = [e["kind"] for e in j.events()]
        assert after[:n_initial] == stored  # reused, not re-measured
        assert all(r["role"] == "added" for r in rows[n_initial:]) and len(rows) - n_initial <= 2
        assert "procedure-changed" in kinds and j.run_info()["finished"]
        assert j.iterations()[0].n_points == n_initial
    finally:
        j.close()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["iterations"] and summary["experiments_added"] == len(rows) - n_initial
