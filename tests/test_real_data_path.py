"""Issue 14: from a lab's FRF file (CSV or UFF 58, any quantity) to a prior and certified intervals.

UFF files are written with pyuff (an independent implementation of the format); synthetic FRFs
come from known modal parameters, so the estimates and the intervals are checked against the
truth. Tests on the public real data sets skip when ../shared/realdata is absent.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.estimation.modal_estimate import estimate_modes
from setmem_hil.io.frf_file import load_frf
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"
needs_realdata = pytest.mark.skipif(not REALDATA.is_dir(), reason=f"real data sets not present at {REALDATA}")

# a lightly damped 3-mode structure at real scale: 80, 210, 390 Hz, zeta 2e-3..5e-3, receptance ~1e-6 m/N
TRUTH = ModalParameters.from_modal(2 * np.pi * np.array([80.0, 210.0, 390.0]), np.array([0.004, 0.002, 0.005]),
                                   np.array([3.0, -2.0, 4.0]))
F_HZ = np.arange(40.0, 600.0, 0.5)


def _receptance():
    return TRUTH.frequency_response(2 * np.pi * F_HZ)


def _write_uff(path: Path, values: np.ndarray, ordinate: int, coherence: np.ndarray | None = None) -> None:
    import pyuff

    sets = [pyuff.prepare_58(func_type=4, rsp_node=1, rsp_dir=3, ref_node=1, ref_dir=3, data=values, x=F_HZ,
                             id1="synthetic FRF", rsp_ent_name="beam", ref_ent_name="beam", abscissa_spacing=1,
                             abscissa_spec_data_type=18, ordinate_spec_data_type=ordinate, orddenom_spec_data_type=13)]
    if coherence is not None:
        sets.append(pyuff.prepare_58(func_type=6, rsp_node=1, rsp_dir=3, ref_node=1, ref_dir=3, data=coherence, x=F_HZ,
                                     id1="coherence", rsp_ent_name="beam", ref_ent_name="beam", abscissa_spacing=1,
                                     abscissa_spec_data_type=18, ordinate_spec_data_type=0, orddenom_spec_data_type=0))
    uff = pyuff.UFF(str(path))
    uff.write_sets(sets, mode="overwrite")


@pytest.mark.parametrize("quantity, ordinate, factor", [
    ("displacement", 8, lambda s: 1.0), ("velocity", 11, lambda s: s), ("acceleration", 12, lambda s: s * s)])
def test_uff_in_any_quantity_reads_as_receptance_with_its_bound(tmp_path, quantity, ordinate, factor):
    s = 1j * 2 * np.pi * F_HZ
    native = _receptance() * factor(s)
    _write_uff(tmp_path / "frf.uff", native, ordinate)
    loaded = load_frf(tmp_path / "frf.uff", bound_rel=0.05, bound_abs=0.0)
    assert loaded.quantity == quantity
    np.testing.assert_allclose(loaded.data.omega_rad_s, 2 * np.pi * F_HZ)
    np.testing.assert_allclose(loaded.data.response, _receptance(), rtol=1e-5)  # UFF stores single precision
    np.testing.assert_allclose(loaded.data.bound, 0.05 * np.abs(_receptance()), rtol=1e-5)


def test_uff_quantity_contradicting_the_file_and_missing_bound_are_errors(tmp_path, capsys):
    _write_uff(tmp_path / "frf.uff", _receptance() * (1j * 2 * np.pi * F_HZ) ** 2, 12)
    prior = tmp_path / "p.toml"
    prior.write_text("[[mode]]\nomega_min = 400\nomega_max = 600\nzeta_max = 0.1\nb1 = 0\n")
    args = ["identify", "--data", str(tmp_path / "frf.uff"), "--prior", str(prior), "--out", str(tmp_path / "r.json")]
    assert main(args) == 2 and "carries no error bound" in capsys.readouterr().err
    assert main(args + ["--quantity", "velocity", "--bound-rel", "0.05"]) == 2
    assert "acceleration per force, not velocity" in capsys.readouterr().err


def test_coherence_gives_the_h1_random_error_bound(tmp_path):
    gamma2 = np.full(F_HZ.size, 0.9)
    _write_uff(tmp_path / "frf.uff", _receptance(), 8, coherence=gamma2.astype(complex))
    loaded = load_frf(tmp_path / "frf.uff", averages=5)
    eps = math.sqrt(1 - 0.9) / (math.sqrt(0.9) * math.sqrt(10))  # Bendat & Piersol, by hand
    np.testing.assert_allclose(loaded.data.bound, 3 * eps * np.abs(_receptance()), rtol=1e-5)


def test_modal_estimate_finds_the_true_poles_and_residues():
    w = 2 * np.pi * F_HZ
    g = _receptance()
    rng = np.random.default_rng(3)
    noise = 0.01 * np.abs(g) * (rng.standard_normal(g.size) + 1j * rng.standard_normal(g.size)) / math.sqrt(2)
    est = estimate_modes(FrequencyData(w, g + noise, 0.03 * np.abs(g)), 3)
    found = [m for m in est.modes if not m.low_pseudo_mode]
    assert len(found) == 3
    np.testing.assert_allclose([m.omega_n_rad_s for m in found], TRUTH.natural_frequencies, rtol=2e-3)
    np.testing.assert_allclose([m.zeta for m in found], TRUTH.damping_ratios, rtol=0.2)
    np.testing.assert_allclose([m.b0 for m in found], TRUTH.values[:, 3], rtol=0.1)


@pytest.mark.slow
def test_prior_then_identify_contains_the_truth(tmp_path, capsys):
    w = 2 * np.pi * F_HZ
    g = _receptance()
    rng = np.random.default_rng(5)
    bound = 0.02 * np.abs(g) + 1e-9
    u = rng.uniform(0, 1, g.size)
    noise = 0.9 * bound * np.sqrt(u) * np.exp(2j * np.pi * rng.uniform(0, 1, g.size))
    lines = ["omega,re,im,bound"] + [f"{float(a)!r},{float(b.real)!r},{float(b.imag)!r},{float(c)!r}" for a, b, c in zip(w, g + noise, bound)]
    (tmp_path / "frf.csv").write_text("\n".join(lines) + "\n")
    assert main(["prior", "--data", str(tmp_path / "frf.csv"), "--modes", "3", "--out", str(tmp_path / "prior.toml")]) == 0
    text = (tmp_path / "prior.toml").read_text()
    assert text.count("[[mode]]") == 3 and "ASSUMPTIONS" in text and "RELATIVE TO THIS PRIOR" in text
    assert (tmp_path / "prior-stability.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["identify", "--data", str(tmp_path / "frf.csv"), "--prior", str(tmp_path / "prior.toml"), "--out", str(tmp_path / "r.json")]) == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    lo = np.array([[m[k][0] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    hi = np.array([[m[k][1] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    assert np.all((lo <= TRUTH.values) & (TRUTH.values <= hi))
    assert all(m["verified"] for m in doc["modes"])


@needs_realdata
def test_real_beam_prior_then_identify_relaxed_and_honest(tmp_path, capsys):
    beam = REALDATA / "ladisk-pyuff-beam"
    prior = tmp_path / "prior.toml"
    assert main(["prior", "--data", str(beam / "frf_displacement_relaxed.csv"), "--modes", "6", "--out", str(prior)]) == 0
    assert prior.read_text().count("[[mode]]") == 6
    assert main(["identify", "--data", str(beam / "frf_displacement_relaxed.csv"), "--prior", str(prior), "--out", str(tmp_path / "r.json")]) == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    resonances_hz = [142.18, 278.67, 460.40, 687.16, 958.53]  # the data set's README (peaks of the measured FRF)
    for m, f in zip(doc["modes"][1:], resonances_hz):
        f_lo, f_hi = (math.sqrt(a) / (2 * math.pi) for a in m["a0"])
        assert f_lo <= f + 0.5 and f - 0.5 <= f_hi and f_hi - f_lo < 1.0  # within half a line, narrower than a line
    capsys.readouterr()
    code = main(["identify", "--data", str(beam / "frf_displacement.csv"), "--prior", str(prior), "--out", str(tmp_path / "h.json")])
    err = capsys.readouterr().err
    assert code == 3 and "rad/s" in err and not (tmp_path / "h.json").exists()  # the modal model misses the honest bound


def test_prior_with_residual_terms_brackets_them_and_identify_contains_the_truth(tmp_path):
    """A lower residual (mass line of a mode below the band): estimated, bracketed, identified."""
    w = 2 * np.pi * F_HZ
    r_true = -0.5  # G + r/s^2: a rigid-body-like mass line, -r/omega^2 = +0.5/omega^2
    g = _receptance() + r_true / (1j * w) ** 2
    rng = np.random.default_rng(7)
    bound = 0.02 * np.abs(g)
    g_meas = g + 0.9 * bound * np.sqrt(rng.uniform(size=g.size)) * np.exp(2j * np.pi * rng.uniform(size=g.size))
    lines = ["omega,re,im,bound"] + [f"{float(a)!r},{float(b.real)!r},{float(b.imag)!r},{float(c)!r}" for a, b, c in zip(w, g_meas, bound)]
    (tmp_path / "frf.csv").write_text("\n".join(lines) + "\n")
    assert main(["prior", "--data", str(tmp_path / "frf.csv"), "--modes", "3", "--residuals", "lower", "--out", str(tmp_path / "p.toml")]) == 0
    text = (tmp_path / "p.toml").read_text()
    assert "[residuals]" in text and "lower_min" in text and "lower_max" in text
    assert main(["identify", "--data", str(tmp_path / "frf.csv"), "--prior", str(tmp_path / "p.toml"), "--out", str(tmp_path / "r.json")]) == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    lo, hi = doc["residuals"]["lower"]
    assert lo <= r_true <= hi
    modes = np.array([[m[k][0] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]]), np.array([[m[k][1] for k in ("a1", "a0", "b1", "b0")] for m in doc["modes"]])
    assert np.all((modes[0] <= TRUTH.values) & (TRUTH.values <= modes[1]))
