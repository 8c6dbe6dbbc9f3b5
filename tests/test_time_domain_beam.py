"""Time-domain beam against independent truth: the complex frequency response and modal poles."""

import numpy as np
import pytest

from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.time_domain_beam import TimeDomainBeam


def _phasor(t, y, omega):
    # least squares on cos/sin: y = Re(Y e^{j w t})
    X = np.column_stack([np.cos(omega * t), -np.sin(omega * t)])
    a, b = np.linalg.lstsq(X, y, rcond=None)[0]
    return a + 1j * b


@pytest.mark.parametrize("omega", [0.5, 3.0, 25.0])
def test_steady_state_equals_transfer_function(omega):
    # one well-damped mode, so it settles quickly; truth by direct complex evaluation
    a1, a0, b1, b0 = 2 * 0.3 * 2.0, 4.0, 0.5, 3.0
    beam = TimeDomainBeam(ModalParameters(np.array([[a1, a0, b1, b0]])))
    beam.set_sine(omega, 2.0)
    dt = 2 * np.pi / omega / 32
    beam.simulate(int(40 / dt) + 1, dt)  # 40 s >> 1/(zeta wn) = 1.7 s
    n = 32 * 8
    force, disp = beam.simulate(n, dt)
    t = dt * np.arange(n)
    s = 1j * omega
    g_true = (b1 * s + b0) / (s * s + a1 * s + a0)
    assert _phasor(t, disp, omega) / _phasor(t, force, omega) == pytest.approx(g_true, rel=1e-9)
    # the force is the exact continuous sine (no zero-order-hold delay)
    assert np.abs(_phasor(t, force, omega)) == pytest.approx(2.0, rel=1e-12)


def test_free_response_decays_with_the_modal_poles():
    p = beam_parameters(2)
    beam = TimeDomainBeam(p)
    beam.x = np.array([1.0, 0.0, 0.0, 0.0])  # displace mode 1 only
    dt = 0.05
    _, y = beam.simulate(4001, dt)
    t = dt * np.arange(4001)
    wn, zeta, b0 = 1.0, 0.01, 4.0
    wd = wn * np.sqrt(1 - zeta**2)
    # analytic free response of x'' + 2 zeta wn x' + wn^2 x = 0, x(0)=1, x'(0)=0
    x = np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t))
    assert np.max(np.abs(y - b0 * x)) < 1e-9


def test_stop_removes_force_and_is_repeatable():
    beam = TimeDomainBeam(beam_parameters(3))
    beam.set_sine(2.0, 1.0)
    beam.simulate(50, 0.1)
    beam.stop()
    f, _ = beam.simulate(20, 0.1)
    assert np.all(f == 0)
    with pytest.raises(ValueError, match="omega_rad_s"):
        beam.set_sine(-1.0, 1.0)
