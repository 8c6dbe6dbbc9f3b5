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
