"""Issue 26: the emulated bench under a generator's arbitrary waveform (points held one sample
period) against SciPy's zero-order-hold simulation of the same state space, an independent
formulation (``scipy.signal.lsim`` with ``interp=False`` on a fine grid)."""

import numpy as np
import scipy.signal as sg

from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.instrument_bench import BenchSettings, EmulatedBench


def test_a_held_waveform_record_is_the_zero_order_hold_response():
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    points = np.random.default_rng(1).uniform(-1, 1, 200)
    bench.set_generator(amplitude_v=0.2, output_on=True)
    bench.set_arbitrary(points, 50.0)
    bench.clock.sleep(1.3)  # the waveform has played 65 points before the record
    force, outputs = bench.record(bench.clock.now(), 0.013, 400)  # 5.2 s: the 200-point waveform repeats
    A, B, C, _ = beam_parameters().state_space_matrices()
    t = np.arange(0.0, 1.3 + 0.013 * 399 + 1e-9, 1e-4)
    u = bench.true_gain * 0.2 * points[np.floor(t * 50 + 1e-9).astype(int) % 200]
    _, y, _ = sg.lsim(sg.StateSpace(A, B, C[:1], np.zeros((1, 1))), u, t, interp=False)
    at = np.round((1.3 + 0.013 * np.arange(400)) / 1e-4).astype(int)
    assert np.max(np.abs(outputs[0] - y[at])) < 1e-9 * np.max(np.abs(y))
    assert np.array_equal(force, u[at])
    assert bench.force_amplitude_n == bench.true_gain * 0.2 * np.max(np.abs(points))


def test_the_sync_marks_each_cycle_and_the_force_trigger_a_rising_step():
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    points = np.array([0.0, -0.5, 0.5, 1.0, -1.0, -0.2, 0.3, 0.0])
    bench.set_generator(amplitude_v=1.0, output_on=True)
    bench.set_arbitrary(points, 8.0)  # one cycle a second
    bench.clock.sleep(0.3)
    assert bench.sync_edge_after(0.3) == 1.0 and bench.sync_edge_after(1.0) == 1.0
    # rising through 0 N: from point 1 (-0.5) to 2 (+0.5) at 2/8 s, from 5 (-0.2) to 6 (+0.3) at 6/8 s
    assert bench.force_rising_after(0.3, 0.0) == 6 / 8 and bench.force_rising_after(0.8, 0.0) == 1 + 2 / 8
    assert bench.force_rising_after(0.3, 3.0) == 3 / 8  # through 3 N (4 N a unit point) only from 0.5 to 1.0


def test_records_thousands_of_seconds_in_follow_the_exact_hold_by_hold_response():
    """A bug this caught: the holds' edges were a running sum of 1 / rate, which at thousands of
    seconds drifted past the index test's room, and the structure was driven by the wrong point
    (a campaign's line phase off by a whole sample period). Truth: SciPy's exact zero-order-hold
    discretisation stepped point by point, an independent formulation."""
    rate = 32.173128965177945  # the rate a 0.95 rad/s top line gets (POINTS_PER_PERIOD)
    points = np.cos(5.9495 * np.arange(165580) / rate)
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    bench.set_generator(amplitude_v=0.2, output_on=True)
    bench.set_arbitrary(points, rate)
    A, B, C, _ = beam_parameters().state_space_matrices()
    Ad, Bd, *_ = sg.cont2discrete((A, B, C[:1], np.zeros((1, 1))), 1 / rate, method="zoh")
    u = bench.true_gain * 0.2 * points
    x, exact = np.zeros(A.shape[0]), []
    for k in range(int(4200 * rate)):
        exact.append(C[0] @ x)
        x = Ad @ x + Bd[:, 0] * u[k]
    for start in (3600.0, 4000.0, 4100.0):  # records every few hundred seconds, as a campaign takes them
        bench.clock.sleep(start + 0.003 - bench.clock.now())
        k0 = int(np.ceil(bench.clock.now() * rate))
        force, outputs = bench.record(k0 / rate, 1 / rate, 200)
        assert np.max(np.abs(outputs[0] - exact[k0:k0 + 200])) < 1e-8 * np.max(np.abs(exact)), start
        assert np.array_equal(force, u[k0:k0 + 200])
