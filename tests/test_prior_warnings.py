"""`setmem-hil prior` says when its own proposal will not do (issue 25, user findings 4 and 5).

A proposal whose least-squares estimate misses the data by more than the bound predicts that
`identify` exits 3; a mode with a damping far above the structure's is most likely a
computational mode of the fit. Both used to be written silently with exit 0.
"""

import math
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.estimation.modal_estimate import ModalEstimate, ModeEstimate
from setmem_hil.io.prior_proposal import format_prior_proposal, misfit_advice, suspicious_modes

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
needs_realdata = pytest.mark.skipif(not REALDATA.is_dir(), reason=f"real data sets not present at {REALDATA}")


def estimate(zetas, worst=0.5, low=False):
    modes = tuple(ModeEstimate(2 * math.pi * f, z, 0.1, low and i == 0) for i, (f, z) in enumerate(zip((50, 142, 279, 460, 946), zetas)))
    return ModalEstimate(modes, worst, (2 * math.pi * 100, 2 * math.pi * 1000), (), (), ())


def test_a_high_damping_mode_is_flagged_in_the_file():
    est = estimate([0.1, 3e-4, 2e-4, 4e-4, 0.18], low=True)  # the low pseudo-mode's 0.1 is its assumption, not a flag
    flags = dict(suspicious_modes(est))
    assert set(flags) == {4} and "0.18" in flags[4]
    text = format_prior_proposal(est, "beam.csv")
    assert text.count("# CHECK THIS MODE") == 1
    assert text.index("# CHECK THIS MODE") > text.index("zeta 0.18") - 200  # next to the mode it is about


def test_a_damping_far_above_the_others_is_flagged_even_below_0_1():
    flags = dict(suspicious_modes(estimate([3e-4, 2e-4, 0.036, 4e-4, 2e-4])))
    assert set(flags) == {2} and "median" in flags[2]
    assert suspicious_modes(estimate([3e-4, 2e-4, 1e-3, 4e-4, 2e-4])) == []  # 4x is a real spread, not a flag


def test_a_proposal_that_misses_its_data_says_what_to_do():
    assert misfit_advice(estimate([1e-3] * 5, worst=0.98)) is None
    advice = misfit_advice(estimate([1e-3] * 5, worst=1.8))
    assert "1.8" in advice and "exit 3" in advice and "--modes" in advice
    assert "# WARNING" in format_prior_proposal(estimate([1e-3] * 5, worst=1.8), "x.csv")


def propose(tmp_path, capsys, folder: str, modes: int):
    """``setmem-hil prior`` on a real relaxed FRF: (data file, prior file, stderr)."""
    data = REALDATA / folder / "frf_displacement_relaxed.csv"
    prior = tmp_path / "prior.toml"
    assert main(["prior", "--data", str(data), "--modes", str(modes), "--out", str(prior)]) == 0
    return data, prior, capsys.readouterr().err


@needs_realdata
def test_real_beam_point_2_proposal_warns_and_identify_then_fails(tmp_path, capsys):
    data, prior, err = propose(tmp_path, capsys, "ladisk-pyuff-beam-point2", 6)
    assert "warning" in err and "exit 3" in err  # the user saw exit 0 and no word
    assert main(["identify", "--data", str(data), "--prior", str(prior), "--out", str(tmp_path / "r.json")]) == 3  # as predicted


@needs_realdata
def test_real_beam_seven_modes_flags_the_spurious_one(tmp_path, capsys):
    _, prior, err = propose(tmp_path, capsys, "ladisk-pyuff-beam", 7)
    assert "computational mode" in err
    assert prior.read_text().count("# CHECK THIS MODE") == 1
