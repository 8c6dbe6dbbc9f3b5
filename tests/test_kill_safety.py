"""Kill safety of the journal (issue 8): SIGKILL at random moments never loses, duplicates
or half-writes a record, and a restarted writer continues from what is stored.

A child process replays a fixed sequence of actions (measurement n, and after every fifth
measurement an iteration record), skipping what the journal already holds, exactly as the
campaign's REPLAY resume does. The parent kills it at random instants and checks the journal
after every kill against the sequence the child was meant to write (independent truth: the
closed-form value of record n).
"""

from __future__ import annotations

import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.errors import InputFormatError
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import Journal

N_TOTAL = 120
PER_ITERATION = 5

CHILD = r"""
import sys
import time
from pathlib import Path
import numpy as np
from pathlib import Path
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import IterationRecord, Journal

path, n_total, per = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
if path.exists():
    j = Journal.open(path)
else:
    j = Journal.create(path, procedure_text="x", procedure_name="kill", seed=3, software_version="t", backend="sim", strategy="mu")
stored, stored_k = j.n_measurements(), len(j.iterations())
print("ready", stored, stored_k, flush=True)
for n in range(1, n_total + 1):
    if n > stored:
        time.sleep(0.002)  # a dwell stand-in, so that kills land mid-campaign
        seq = j.add_measurement(Measurement(0.1 * n, complex(n, -0.5 * n), 1.0 / n), iteration=n // per, role="initial" if n <= 15 else "added")
        if seq != n:
            raise SystemExit(f"sequence {seq} != {n}")
    k = n // per
    if n % per == 0 and k > stored_k:
        j.add_iteration(IterationRecord(
            k=k, n_points=n, lower=np.full((3, 4), float(k)), upper=np.full((3, 4), k + 1.0),
            mu_peak=1.0 / k, mu_peak_omega=float(k), mu_lower_peak=0.5 / k, omega=np.arange(1.0, 201.0),
            mu=np.full(200, 1.0 / k), sensitivities={"a0_1": float(k)}, next_omega=0.1 * (n + 1),
            candidate_omega=np.arange(1.0, 51.0), estimated_improvement=np.full(50, float(k)), controller_order=6,
            safeguard="new-design", wall_s=0.0, embedding_gamma=np.ones(3), mismatch_ratio=np.zeros(3)))
if not j.run_info()["finished"]:
    j.finish({"n": n_total})
j.close()
print("done", flush=True)
"""


def expected_measurement(n: int) -> Measurement:
    return Measurement(0.1 * n, complex(n, -0.5 * n), 1.0 / n)


def check_journal(path) -> tuple[int, int]:
    j = Journal.open(path)
    try:
        assert j.integrity_problems() == []
        ms = j.measurements()
        assert ms == [expected_measurement(n) for n in range(1, len(ms) + 1)]  # no gap, duplicate or torn row
        its = j.iterations()
        for rec in its:
            assert rec.n_points == PER_ITERATION * rec.k
            np.testing.assert_array_equal(rec.mu, np.full(200, 1.0 / rec.k))  # whole JSON arrays, never truncated
            assert rec.upper.shape == (3, 4) and rec.upper[0, 0] == rec.k + 1.0
        # iterations lag measurements by at most one record
        assert len(ms) // PER_ITERATION - len(its) in (0, 1)
        return len(ms), len(its)
    finally:
        j.close()


def test_sigkill_at_random_moments_then_resume(tmp_path):
    rng = np.random.default_rng(20261121)
    path = tmp_path / "journal.sqlite"
    cmd = [sys.executable, "-c", CHILD, str(path), str(N_TOTAL), str(PER_ITERATION)]
    kills = 0
    progress = []
    for _ in range(12):
        child = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        line = child.stdout.readline()  # wait until it is writing, then kill after a random delay
        if not line.startswith("ready"):
            child.wait()
            pytest.fail(f"child failed to start: {line!r} {child.stderr.read()}")
        time.sleep(float(rng.uniform(0.0, 0.05)))
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
            kills += 1
        child.wait()
        child.stdout.close()
        child.stderr.close()
        progress.append(check_journal(path))
    # the last run completes
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    n, k = check_journal(path)
    assert (n, k) == (N_TOTAL, N_TOTAL // PER_ITERATION)
    j = Journal.open(path)
    assert j.run_info()["finished"]
    j.close()
    assert kills >= 6, f"only {kills} kills landed mid-write; make the child slower"
    assert progress == sorted(progress)  # stored records only ever grow
    print("kills", kills, "stored after each kill", progress)


# ------------------------------------------------------------------------------------------
# The whole campaign: `setmem-hil run` killed with SIGKILL again and again, then resumed.
# ------------------------------------------------------------------------------------------
HELPERS = Path(__file__).with_name("_campaign_helpers.py")
KILL_ROUNDS = int(os.environ.get("SETMEM_CAMPAIGN_KILLS", "20"))  # issue 8: 20 kills

CAMPAIGN_CHILD = r"""
import runpy, sys
h = runpy.run_path(sys.argv[1])
h["install_fast_analysis"]()
import setmem_hil.campaign.runner, setmem_hil.identification.algorithm, setmem_hil.design.input_design  # noqa: F401  (imports before "ready")
import setmem_hil.cli.commands.run as run_cmd
from setmem_hil.cli.main import main
real_open = run_cmd.open_backend
run_cmd.open_backend = lambda p, s: h["InterruptingExperiment"](real_open(p, s), None, delay_s=0.04)
print("ready", flush=True)
sys.exit(main(sys.argv[2:]))
"""


def _stored_measurements(run_dir) -> int:
    """Measurements committed so far (a read-only look; WAL readers never block the writer)."""
    if not (run_dir / "journal.sqlite").exists():
        return 0
    try:
        j = Journal.open(run_dir)
    except (InputFormatError, sqlite3.Error):  # not yet renamed into place: nothing stored
        return 0
    try:
        return j.n_measurements()
    finally:
        j.close()


def _raw_record_seqs(run_dir) -> set[int]:
    """Every measurement ``raw.h5`` holds a record for, read through its index with h5py alone
    (an empty set before the first record)."""
    import h5py

    if not (run_dir / "raw.h5").exists():
        return set()
    with h5py.File(run_dir / "raw.h5", "r") as f:
        return {int(s) for name in f["measurements"] for s in f["measurements"][name].attrs["seqs"]}


@pytest.mark.slow
def test_campaign_killed_repeatedly_then_resumed_equals_uninterrupted(tmp_path, monkeypatch):
    """SIGKILL ``setmem-hil run`` at random moments KILL_ROUNDS times (SETMEM_CAMPAIGN_KILLS=20
    for the full issue-8 run), resuming each time; the final journal equals an uninterrupted run."""
    import importlib.util

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.io.procedure_file import load_procedure

    spec = importlib.util.spec_from_file_location("_campaign_helpers", HELPERS)
    h = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(h)
    h.install_fast_analysis(monkeypatch)
    proc_path = tmp_path / "cheap.toml"
    proc_path.write_text(h.cheap_procedure_text(3))
    p = load_procedure(proc_path)
    ref = Journal.create(tmp_path / "ref" / "journal.sqlite", procedure_text=p.source_text, procedure_name=p.name, seed=p.seed,
                         software_version="ref", backend="sim", strategy="mu")
    run_campaign(p, h.simulated(p, p.seed), ref)
    ref_ms, ref_its = ref.measurements(), ref.iterations()
    ref.close()

    run_dir = tmp_path / "run"
    rng = np.random.default_rng(8)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    mid_campaign = 0
    for _ in range(KILL_ROUNDS):
        started = (run_dir / "journal.sqlite").exists()
        argv = ["run", "--resume", str(run_dir), "--quiet"] if started else ["run", str(proc_path), "--out", str(run_dir), "--quiet"]
        child = subprocess.Popen([sys.executable, "-c", CAMPAIGN_CHILD, str(HELPERS), *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        line = child.stdout.readline()
        if not line.startswith("ready"):
            child.wait()
            pytest.fail(f"child failed to start: {line!r} {child.stderr.read()}")
        # Kill at a random point of progress, not a random wall-clock time, so the kill lands
        # mid-campaign however loaded the machine is: wait for a random number of stored
        # measurements beyond those already there, then SIGKILL after a random few milliseconds.
        stored = _stored_measurements(run_dir)
        target = int(rng.integers(stored + 1, len(ref_ms))) if stored + 1 < len(ref_ms) else stored
        deadline = time.monotonic() + 120
        while child.poll() is None and _stored_measurements(run_dir) < target and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(float(rng.uniform(0.0, 0.05)))
        if child.poll() is None:
            os.kill(child.pid, signal.SIGKILL)
        child.wait()
        child.stdout.close()
        child.stderr.close()
        if (run_dir / "journal.sqlite").exists():
            j = Journal.open(run_dir)
            try:
                assert j.integrity_problems() == []
                ms, its = j.measurements(), j.iterations()
                assert ms == ref_ms[: len(ms)]  # a prefix: nothing lost in between, duplicated or torn
                assert [(r.k, r.next_omega) for r in its] == [(r.k, r.next_omega) for r in ref_its[: len(its)]]
                if 0 < len(ms) < len(ref_ms):
                    mid_campaign += 1
            finally:
                j.close()
            assert _raw_record_seqs(run_dir) >= set(range(1, len(ms) + 1))  # raw.h5 readable, every committed point's record in it
    done = subprocess.run([sys.executable, "-c", CAMPAIGN_CHILD, str(HELPERS), "run", "--resume", str(run_dir), "--quiet"]
                          if (run_dir / "journal.sqlite").exists() else
                          [sys.executable, "-c", CAMPAIGN_CHILD, str(HELPERS), "run", str(proc_path), "--out", str(run_dir), "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    j = Journal.open(run_dir)
    assert j.measurements() == ref_ms
    assert [(r.k, r.n_points, r.next_omega, r.mu_peak) for r in j.iterations()] == [(r.k, r.n_points, r.next_omega, r.mu_peak) for r in ref_its]
    assert j.run_info()["finished"] and (run_dir / "summary.json").exists()
    j.close()
    from setmem_hil.cli.main import main

    assert main(["reprocess", str(run_dir)]) == 0  # every point recomputed from raw.h5 after the kills
    print(f"campaign killed {KILL_ROUNDS} times ({mid_campaign} mid-campaign), resumed to the uninterrupted result")
    assert mid_campaign >= max(1, KILL_ROUNDS // 4)


def test_sigterm_stops_like_ctrl_c(tmp_path):
    """``kill PID`` (SIGTERM) zeroes the exciter, journals the interruption and exits 130."""
    proc_path = tmp_path / "cheap.toml"
    import importlib.util

    spec = importlib.util.spec_from_file_location("_campaign_helpers", HELPERS)
    h = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(h)
    proc_path.write_text(h.cheap_procedure_text(3))
    run_dir = tmp_path / "run"
    child = subprocess.Popen([sys.executable, "-c", CAMPAIGN_CHILD, str(HELPERS), "run", str(proc_path), "--out", str(run_dir), "--quiet"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    assert child.stdout.readline().startswith("ready")
    deadline = time.monotonic() + 60
    while not (run_dir / "journal.sqlite").exists() and time.monotonic() < deadline:
        time.sleep(0.02)
    time.sleep(0.3)
    child.send_signal(signal.SIGTERM)
    _, err = child.communicate(timeout=60)
    assert child.returncode == 130, err
    assert f"setmem-hil run --resume {run_dir}" in err
    j = Journal.open(run_dir)
    assert j.events()[-1]["kind"] == "interrupted" and "SIGTERM" in j.events()[-1]["message"]
    assert j.integrity_problems() == [] and not j.run_info()["finished"]
    j.close()
