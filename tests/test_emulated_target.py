"""The emulated rig (issue 45): the structure in closed loop with the firmware's core, stepped in
C (sim_backends/sil_loop.c). Truth: the same loop stepped here sample by sample in Python, with
the structure discretised by scipy (cont2discrete, zero-order hold) and the firmware's core called
one sample at a time; and the structure's own frequency response for the bypassed rig."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.emulated_target import EmulatedClosedLoop, TargetEmulation
from setmem_hil.sim_backends.firmware_core import FirmwareCore, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler (cc or $CC) to build the reference firmware")

FS = 500.0
SECTION = [[0.3, -0.5, 0.25, 1.0, -1.6, 0.7]]  # a stable section, positive gain: a toy compensator


def python_loop(structure, emulation: TargetEmulation, n: int, amplitude: float, omega: float, gain: float):
    A, B, C, _ = structure.state_space_matrices()
    Ad, Bd, Cd, _, _ = scipy.signal.cont2discrete((A, B, C, np.zeros((1, 1))), 1 / FS, method="zoh")
    core = FirmwareCore(FS, 2)
    _load(core, gain)
    x, pipeline, u_out, y_out = np.zeros(A.shape[0]), [0.0] * emulation.extra_delay_samples, [], []
    for k in range(n):
        y = float((Cd @ x).ravel()[0])
        v = core.tick(y)
        if pipeline:
            pipeline.append(v)
            v = pipeline.pop(0)
        u = emulation.dac_gain * v + amplitude * np.sin(omega * k / FS)
        x = Ad @ x + Bd[:, 0] * u
        u_out.append(u)
        y_out.append(y)
    return np.array(u_out), np.array(y_out)


def _load(core: FirmwareCore, gain: float) -> None:
    core.command("LOAD 1")
    s = SECTION[0]
    core.command(f"SOS 0 {s[0]!r} {s[1]!r} {s[2]!r} {s[4]!r} {s[5]!r}")
    core.command("LIMIT 100")
    core.command("WATCHDOG 0")
    if gain:
        assert core.command(f"ENGAGE {gain!r}") == "OK"


@pytest.mark.parametrize("emulation", [TargetEmulation(), TargetEmulation(extra_delay_samples=3, dac_gain=1.3)])
def test_the_loop_stepped_in_c_is_the_loop_stepped_sample_by_sample(emulation):
    structure = beam_parameters().truncated(4)
    loop = EmulatedClosedLoop(structure, FS, 2, emulation)
    _load(loop.core, 0.5)
    loop.set_generator(0.2, 6.0)
    first, second = loop.run(1500), loop.run(1500)  # two calls: the state carries over
    u_ref, y_ref = python_loop(structure, emulation, 3000, 0.2, 6.0, 0.5)
    assert np.allclose(np.concatenate([first.u, second.u]), u_ref, rtol=0, atol=1e-12 * np.max(np.abs(u_ref)))
    assert np.allclose(np.concatenate([first.y, second.y]), y_ref, rtol=0, atol=1e-12 * np.max(np.abs(y_ref)))


def test_the_bypassed_rig_responds_as_the_structure_with_its_hold():
    from setmem_hil.estimation.sine_fit import fit_sine

    structure = beam_parameters().truncated(3)
    loop = EmulatedClosedLoop(structure, FS, 1)
    w = 6.0
    loop.set_generator(0.1, w)
    loop.run(int(1000 * FS))  # 1000 s: the first mode's transient (time constant 100 s) gone
    record = loop.run(int(20 * 2 * np.pi / w * FS))
    g = fit_sine(record.t_s, record.y, w).phasor / fit_sine(record.t_s, record.u, w).phasor
    hold = (1 - np.exp(-1j * w / FS)) / (1j * w / FS)  # the held staircase's fundamental
    truth = structure.frequency_response(w)[0] * hold
    assert abs(g - truth) < 1e-3 * abs(truth)
