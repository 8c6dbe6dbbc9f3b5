"""The closed loop on the emulated target (issue 45): how fast the software-in-the-loop runs,
and what the implemented loop's analysis and a verification cost.

* samples per second of the loop stepped in C (``sim_backends/sil_loop.c``, the beam's eight
  modes and the firmware's core) against the same loop stepped sample by sample in Python (the
  firmware's core called through ctypes), measured in this run: their ratio;
* the implemented mu-bar of the thesis's 3-mode H2 loop at 1 kHz, one sample of delay;
* ``setmem-hil verify`` on a one-iteration run with four frequencies and three gain steps.

    .venv/bin/python benchmarks/closed_loop.py
"""

from __future__ import annotations

import importlib.util
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def loop_speed() -> tuple[float, float]:
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.emulated_target import EmulatedClosedLoop
    from setmem_hil.sim_backends.firmware_core import FirmwareCore

    structure = beam_parameters()
    loop = EmulatedClosedLoop(structure, 1000.0, 1)
    loop.set_generator(0.1, 6.0)
    n = 200_000
    t0 = time.perf_counter()
    loop.run(n)
    c_rate = n / (time.perf_counter() - t0)
    # the same loop, one sample per Python step
    Ad, Bd, C = loop._Ad, loop._Bd, loop._C
    core, x = FirmwareCore(1000.0, 1), np.zeros(Ad.shape[0])
    m = 20_000
    t0 = time.perf_counter()
    for k in range(m):
        y = float(C[0] @ x)
        u = core.tick(y) + 0.1 * np.sin(6.0 * k / 1000.0)
        x = Ad @ x + Bd * u
    py_rate = m / (time.perf_counter() - t0)
    return c_rate, py_rate


def implemented_cost() -> tuple[float, float, float]:
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.model.weights import THESIS_WEIGHTS
    from setmem_hil.robust.analysis import analyze_robust_performance
    from setmem_hil.robust.implemented_loop import implemented_mu_bar
    from setmem_hil.sim_backends.beam import beam_parameters

    model = IntervalModel.point(beam_parameters().truncated(3))
    analysis = analyze_robust_performance(model)
    t0 = time.perf_counter()
    loop = implemented_mu_bar(model, THESIS_WEIGHTS, analysis.controller, 1000.0, 1, analysis.mu_peak_omega)
    return time.perf_counter() - t0, analysis.mu_peak, loop.mu_bar


def verify_cost() -> float:
    from setmem_hil.cli.main import main

    spec = importlib.util.spec_from_file_location("_synthetic_run", REPO / "tests" / "_synthetic_run.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = module.one_iteration_run(Path(tmp) / "run")[0]
        target = Path(tmp) / "target.toml"
        target.write_text((REPO / "procedures" / "closed_loop_emulated.toml").read_text().replace(
            "periods = 20", "periods = 12\nfrequencies_rad_s = [0.9, 4.0, 6.27, 17.5]"))
        t0 = time.perf_counter()
        code = main(["verify", str(run_dir), "--procedure", str(target), "--out", str(Path(tmp) / "out"), "--quiet"])
        assert code == 0
        return time.perf_counter() - t0


def main() -> None:
    c_rate, py_rate = loop_speed()
    print(f"closed loop, 8 modes + firmware core: {c_rate / 1e6:.2f} M samples/s in C, {py_rate / 1e3:.0f} k samples/s "
          f"stepped in Python: {c_rate / py_rate:.0f}x")
    seconds, continuous, implemented = implemented_cost()
    print(f"implemented mu-bar (3-mode H2 loop, 1 kHz, 1 sample delay): {implemented:.4f} against continuous {continuous:.4f}, "
          f"{seconds:.2f} s")
    print(f"setmem-hil verify, one-iteration run, 4 frequencies x 3 gains: {verify_cost():.1f} s")


if __name__ == "__main__":
    main()
