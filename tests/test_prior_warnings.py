"""`setmem-hil prior` says when its own proposal will not do (issue 25, user findings 4 and 5).

A proposal whose least-squares estimate misses the data by more than the bound predicts that
`identify` exits 3; a mode with a damping far above the structure's is most likely a
computational mode of the fit. Both used to be written silently with exit 0.
"""

import json
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


def propose(tmp_path, capsys, folder: str, modes: int, *options: str):
    """``setmem-hil prior`` on a real relaxed FRF: (data file, prior file, stderr)."""
    data = REALDATA / folder / "frf_displacement_relaxed.csv"
    prior = tmp_path / "prior.toml"
    assert main(["prior", "--data", str(data), "--modes", str(modes), "--out", str(prior), *options]) == 0
    return data, prior, capsys.readouterr().err


@needs_realdata
def test_real_beam_point_2_real_residue_proposal_warns_and_identify_then_fails(tmp_path, capsys):
    data, prior, err = propose(tmp_path, capsys, "ladisk-pyuff-beam-point2", 6, "--residues", "real")
    assert "warning" in err and "exit 3" in err  # the user saw exit 0 and no word
    assert "b1_min" not in prior.read_text()
    assert main(["identify", "--data", str(data), "--prior", str(prior), "--out", str(tmp_path / "r.json")]) == 3  # as predicted


@needs_realdata
def test_real_beam_point_2_proposal_turns_to_complex_residues_and_identify_finds_intervals(tmp_path, capsys):
    """The default (``--residues auto``): the real-residue estimate misses by 1.77 x the bound, so
    b1 is bracketed too, and the resonances' frequency intervals then hold the data set's own
    estimates (its README: the peak lines and fits, within half a 1 Hz line)."""
    data, prior, err = propose(tmp_path, capsys, "ladisk-pyuff-beam-point2", 6)
    text = prior.read_text()
    assert "COMPLEX RESIDUES" in text and text.count("b1_min = ") == 5  # not on the low pseudo-mode
    assert "warning" in err and "may still hold" in err
    out = tmp_path / "r.json"
    assert main(["identify", "--data", str(data), "--prior", str(prior), "--out", str(out)]) == 0
    modes = json.loads(out.read_text())["modes"]
    for m, f_hz in zip(modes[1:], (142.18, 278.68, 460.39, 687.18, 958.54)):  # "f, fits" of the data set's README
        f_lo, f_hi = (math.sqrt(a) / (2 * math.pi) for a in m["a0"])
        assert f_lo <= f_hz + 0.5 and f_hz - 0.5 <= f_hi and f_hi - f_lo < 1.0


def test_complex_residues_are_recovered_at_known_poles():
    """A second formulation: residues ``(b1 s + b0)`` of known modes, noise-free; the refit at
    the true poles returns them (and a real-residue FRF gives b1 = 0 to rounding)."""
    from setmem_hil.estimation.modal_estimate import with_complex_residues
    from setmem_hil.model.frequency_data import FrequencyData

    wn, zeta = np.array([3.0, 11.0]), np.array([0.01, 0.02])
    b1, b0 = np.array([0.05, -0.2]), np.array([1.0, 4.0])
    w = np.linspace(1, 20, 200)
    s = 1j * w
    g = sum((b1[i] * s + b0[i]) / (s * s + 2 * zeta[i] * wn[i] * s + wn[i] ** 2) for i in range(2))
    data = FrequencyData(w, g, 0.01 * np.abs(g))
    start = ModalEstimate(tuple(ModeEstimate(a, z, 0.0) for a, z in zip(wn, zeta)), 9.0, (1.0, 20.0), (), (), ())
    [fitted] = with_complex_residues([data], [start])
    assert np.allclose([m.b1 for m in fitted.modes], b1, rtol=1e-8) and np.allclose([m.b0 for m in fitted.modes], b0, rtol=1e-8)
    assert fitted.max_normalized_residual < 1e-6
    real = FrequencyData(w, g - sum(b1[i] * s / (s * s + 2 * zeta[i] * wn[i] * s + wn[i] ** 2) for i in range(2)), data.bound)
    [fitted] = with_complex_residues([real], [start])
    assert np.allclose([m.b1 for m in fitted.modes], 0.0, atol=1e-10)


def test_a_complex_residue_proposal_brackets_b1_around_the_estimate_and_says_why():
    est = ModalEstimate((ModeEstimate(10.0, 0.01, 2.0, False, 0.03),), 1.5, (1.0, 20.0), (), (), ())
    text = format_prior_proposal(est, "x.csv", complex_reason="because")
    lo = float(text.split("b1_min = ")[1].split()[0])
    hi = float(text.split("b1_max = ")[1].split()[0])
    assert lo < 0.03 < hi and "COMPLEX RESIDUES (b1 free): because" in text
    assert "b1 = 0.0" not in text and "b1 = 0.0" in format_prior_proposal(est, "x.csv")


@needs_realdata
def test_real_beam_seven_modes_flags_the_spurious_one(tmp_path, capsys):
    _, prior, err = propose(tmp_path, capsys, "ladisk-pyuff-beam", 7)
    assert "computational mode" in err
    assert prior.read_text().count("# CHECK THIS MODE") == 1


def test_prior_proposes_the_same_modes_for_the_same_rows_in_another_order(tmp_path):
    """Issue 40 (a new user's finding): a data file's rows in another order are the same data;
    `prior` proposed other modes for them (LSCF read the lines as given)."""
    import numpy as np

    from setmem_hil.cli.main import main
    from setmem_hil.io.data_file import write_data_csv
    from setmem_hil.model.frequency_data import FrequencyData
    from setmem_hil.sim_backends.beam import beam_parameters

    truth = beam_parameters().truncated(3)
    w = np.geomspace(0.6, 25.0, 200)
    g = truth.frequency_response(w)
    rng = np.random.default_rng(4)
    bound = 0.03 * np.abs(g) + 1e-3
    data = FrequencyData(w, g + bound * rng.uniform(0, 0.9, w.size) * np.exp(2j * np.pi * rng.uniform(size=w.size)), bound)
    shuffled = data.subset(rng.permutation(w.size))
    write_data_csv(data, tmp_path / "sorted.csv")
    write_data_csv(shuffled, tmp_path / "shuffled.csv")
    texts = []
    for name in ("sorted", "shuffled"):
        assert main(["prior", "--data", str(tmp_path / f"{name}.csv"), "--modes", "3", "--out", str(tmp_path / f"{name}.toml")]) == 0
        texts.append((tmp_path / f"{name}.toml").read_text().split("\n", 1)[1])  # the first line names the file
    assert texts[0] == texts[1]
