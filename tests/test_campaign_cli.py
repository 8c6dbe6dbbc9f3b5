"""``setmem-hil campaign`` and ``setmem-hil demo``: contract of the outputs and of --out."""

import dataclasses
import json

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import Goal, default_procedure
from setmem_hil.io.procedure_file import format_procedure


@pytest.fixture
def quick_procedure(tmp_path):
    """The 6.3.2 procedure with a goal met at once (one identification + analysis) and kind 'sim'."""
    proc = dataclasses.replace(default_procedure(), goal=Goal(mu_target=50.0, max_experiments=2))
    path = tmp_path / "quick.toml"
    path.write_text(format_procedure(proc), encoding="utf-8")
    return path


def test_campaign_command_writes_summary_and_journal_and_refuses_to_overwrite(quick_procedure, tmp_path, capsys):
    out = tmp_path / "run"
    # the thesis's H2 design: the contract is the design's own business, and the tuned design's
    # analysis costs a minute (the robust design's run: tests/test_robust_design.py)
    argv = ["campaign", "--procedure", str(quick_procedure), "--backend", "sim", "--out", str(out), "--seed", "3", "--quiet",
            "--design", "h2"]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reached_goal"] is True and summary["experiments_added"] == 0
    assert summary["final_mu_peak"] < 50.0 and summary["wall_s"] > 0
    assert summary["iterations"][0]["k"] == 1 and summary["iterations"][0]["n_points"] == 15
    assert summary["iterations"][0]["next_omega"] is None
    assert summary["iterations"][0]["mu_peak_certified"] is True and summary["iterations"][0]["mu_certified_intervals"] >= 1
    journal = Journal.open(out)
    try:
        assert journal.n_measurements() == 15
        assert journal.run_info()["seed"] == 3 and journal.run_info()["finished"]
        (it,) = journal.iterations()
        assert it.mu_peak == pytest.approx(summary["final_mu_peak"]) and np.all(it.lower <= it.upper)
        assert it.mu_peak_certified is True and it.mu_certified_intervals == summary["iterations"][0]["mu_certified_intervals"]
    finally:
        journal.close()
    capsys.readouterr()
    assert main(argv) == 2  # a directory holding a journal is refused
    assert "already holds a journal" in capsys.readouterr().err


def test_campaign_command_rejects_an_unknown_strategy(quick_procedure, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["campaign", "--procedure", str(quick_procedure), "--out", str(tmp_path / "x"), "--strategy", "greedy"])
    assert exc.value.code == 2
