"""Residual terms for out-of-band modes (issue 14 item 3): lower (mass line) and upper residual."""

import numpy as np
import pytest

from setmem_hil.errors import InconsistentDataError, InputFormatError
from setmem_hil.identification.algorithm import identify
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.model.prior import ModePrior, Prior, ResidualPrior, parse_prior_mapping
from setmem_hil.sim_backends.noise import bounded_complex_noise

WN = np.array([10.0, 27.0])
R_LOWER, R_UPPER = 60.0, 0.004  # true residuals: -60 / w^2 and +0.004 in receptance


def case(seed=0, rel=0.03):
    truth = ModalParameters.from_modal(WN, [0.01, 0.012], [50.0, 300.0], 0.0)
    w = np.concatenate([WN[0] * np.array([0.9, 0.96, 1.0, 1.03, 1.1]), WN[1] * np.array([0.9, 0.96, 1.0, 1.03, 1.1]),
                        np.array([4.0, 5.0, 16.0, 45.0, 60.0])])
    w = np.sort(w)
    g_true = truth.frequency_response(w) - R_LOWER / w**2 + R_UPPER
    bound = rel * np.abs(g_true)
    g = g_true + bounded_complex_noise(bound, np.random.default_rng(seed))
    modes = tuple(ModePrior(0.9 * wn, 1.1 * wn, 0.2, 0.0, 0.0) for wn in WN)
    return FrequencyData(w, g, bound), modes, truth


def test_model_response_includes_residuals():
    p = ModalParameters(np.array([[0.2, 100.0, 0.0, 50.0]]), lower_residual=3.0, upper_residual=0.5)
    w = np.array([2.0, 30.0])
    s = 1j * w
    expected = 50.0 / (s**2 + 0.2 * s + 100.0) + 3.0 / s**2 + 0.5  # r_l / s^2 + r_u
    assert np.allclose(p.frequency_response(w), expected, rtol=1e-14)


@pytest.mark.parametrize("seed", range(5))
def test_residual_intervals_contain_the_truth(seed):
    data, modes, truth = case(seed)
    result = identify(data, Prior(modes, residuals=ResidualPrior(lower=True, upper=True)))
    assert result.model.contains(truth).all()
    (l_lo, l_hi), (u_lo, u_hi) = result.residuals["lower"], result.residuals["upper"]
    assert l_lo <= R_LOWER <= l_hi and u_lo <= R_UPPER <= u_hi
    assert l_hi - l_lo < R_LOWER  # informative, not merely valid
    doc = result.to_document()
    assert set(doc["residuals"]) == {"lower", "upper"} and len(doc["residuals"]["lower"]) == 2


def test_prior_bounds_on_residuals_are_respected():
    data, modes, truth = case(0)
    result = identify(data, Prior(modes, residuals=ResidualPrior(lower=True, upper=True, lower_min=50.0, lower_max=70.0)))
    lo, hi = result.residuals["lower"]
    assert 50.0 <= lo <= R_LOWER <= hi <= 70.0


def test_without_residuals_the_same_data_are_inconsistent():
    data, _, _ = case(0, rel=0.01)
    plain = Prior(tuple(ModePrior(0.9 * w, 1.1 * w, 0.2, 0.0, 0.0, -1e3, 1e3) for w in WN))
    with pytest.raises(InconsistentDataError):
        identify(data, plain)


def test_only_enabled_residuals_are_reported():
    data, modes, truth = case(1)
    result = identify(data, Prior(modes, residuals=ResidualPrior(upper=True, lower=True)))
    assert set(result.residuals) == {"lower", "upper"}
    only_lower = identify(data, Prior(modes, residuals=ResidualPrior(lower=True, upper=True, upper_min=R_UPPER, upper_max=R_UPPER)))
    assert set(only_lower.to_document()["residuals"]) == {"lower", "upper"}
    plain = identify(data, Prior(modes, residuals=ResidualPrior(lower=True)))
    assert set(plain.to_document()["residuals"]) == {"lower"}


def test_residuals_table_parsing():
    doc = {"mode": [{"omega_min": 1.0, "omega_max": 2.0, "zeta_max": 0.1}],
           "residuals": {"lower": True, "upper": False, "lower_min": -1.0, "lower_max": 2.0}}
    prior = parse_prior_mapping(doc, "PRIOR.toml")
    assert prior.residuals.enabled == ("lower",) and prior.residuals.bounds("lower") == (-1.0, 2.0)
    for bad in ({"lower": 1}, {"middle": True}, {"lower": True, "lower_min": 3.0, "lower_max": 2.0}, {"upper_min": 0.0}):
        with pytest.raises(InputFormatError, match=r"\[residuals\]"):
            parse_prior_mapping({**doc, "residuals": bad}, "PRIOR.toml")


def test_identify_command_writes_residuals_and_verified(tmp_path):
    import json

    from setmem_hil.cli.main import main
    from setmem_hil.io.data_file import write_data_csv

    data, modes, _ = case(2)
    write_data_csv(data, tmp_path / "data.csv")
    lines = []
    for m in modes:
        lines += ["[[mode]]", f"omega_min = {float(m.omega_min)!r}", f"omega_max = {float(m.omega_max)!r}", f"zeta_max = {float(m.zeta_max)!r}", "b1 = 0.0"]
    lines += ["[residuals]", "lower = true", "upper = true"]
    (tmp_path / "prior.toml").write_text("\n".join(lines) + "\n")
    code = main(["identify", "--data", str(tmp_path / "data.csv"), "--prior", str(tmp_path / "prior.toml"), "--out", str(tmp_path / "r.json")])
    assert code == 0
    doc = json.loads((tmp_path / "r.json").read_text())
    lo, hi = doc["residuals"]["lower"]
    assert lo <= R_LOWER <= hi
    lo, hi = doc["residuals"]["upper"]
    assert lo <= R_UPPER <= hi
    assert all(m["verified"] is True for m in doc["modes"])
