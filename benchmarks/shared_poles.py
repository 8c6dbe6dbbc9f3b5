"""Benchmark: identification with shared poles (issue 25).

Prints, in one run:

* three simulated displacement sensors at 0.4, 0.7 and 1.0 of the cantilever (thesis 6.1; residues
  phi_i(tip) phi_i(x_k); 27 points each at their own frequencies; noise up to 0.9 of the thesis's
  fully damped bound), seeds 1-10: truth inside every interval, and per mode the width of the shared a1, a0
  intervals over the narrowest single-sensor interval of the same data;
* speed: 2 outputs x 384 points x 6 modes (the thesis beam's first six modes);
* the real free-free beam (`../shared/realdata/`, points 1 and 2, relaxed bound), when present:
  the common prior (`setmem-hil prior`), the joint identification's time, and per mode the
  shared natural-frequency and damping widths over the narrower of the two points identified
  alone with the same prior.

Run: ``.venv/bin/python benchmarks/shared_poles.py``.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from setmem_hil.identification.algorithm import identify, identify_outputs  # noqa: E402
from setmem_hil.io.procedure import thesis_beam_prior  # noqa: E402
from setmem_hil.model.frequency_data import FrequencyData  # noqa: E402
from setmem_hil.model.modal_model import ModalParameters  # noqa: E402
from setmem_hil.model.prior import ModePrior, Prior  # noqa: E402
from setmem_hil.sim_backends.beam import beam_parameters  # noqa: E402
from test_shared_poles import sensors  # noqa: E402

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata"


def simulated() -> None:
    prior = thesis_beam_prior()
    ratios = {("a1", m): [] for m in range(3)} | {("a0", m): [] for m in range(3)}
    inside = 0
    for seed in range(1, 11):
        truths, datas = sensors(seed)
        singles = [identify(d, prior).model for d in datas]
        joint = identify_outputs(datas, [prior] * 3)
        inside += all(m.contains(t).all() for m, t in zip(joint.models, truths))
        for col, name in ((0, "a1"), (1, "a0")):
            shared = joint.models[0].upper[:, col] - joint.models[0].lower[:, col]
            narrowest = np.min([s.upper[:, col] - s.lower[:, col] for s in singles], axis=0)
            for m in range(3):
                ratios[(name, m)].append(shared[m] / narrowest[m])
    print(f"3 simulated sensors, seeds 1-10: truth inside every interval in {inside}/10")
    for (name, m), r in ratios.items():
        print(f"  {name} mode {m + 1}: shared / narrowest single width  min {min(r):.3f}  mean {np.mean(r):.3f}  max {max(r):.4f}")


def speed() -> None:
    base = beam_parameters().truncated(6)
    rng = np.random.default_rng(0)
    datas = []
    for factors in (np.ones(6), rng.uniform(0.3, 1.3, 6) * rng.choice([-1, 1], 6)):
        values = base.values.copy()
        values[:, 3] *= factors
        truth = ModalParameters(values)
        w = np.geomspace(0.5, base.natural_frequencies[-1] * 1.3, 384)
        g = truth.frequency_response(w)
        bound = 0.03 * np.abs(g) + 1e-4
        datas.append(FrequencyData(w, g + bound * 0.8 * np.exp(2j * np.pi * rng.uniform(size=w.size)), bound))
    prior = Prior(tuple(ModePrior(0.95 * x, 1.05 * x, 0.1, b1_min=0.0, b1_max=0.0, b0_min=-10, b0_max=10) for x in base.natural_frequencies))
    t = time.perf_counter()
    identify_outputs(datas, [prior, prior])
    print(f"speed: 2 outputs x 384 points x 6 modes jointly (both outputs alone first, included): {time.perf_counter() - t:.2f} s (goal < 3 s)")


def real() -> None:
    """``prior`` then ``identify`` on the public beam's points 1 and 2 (relaxed bound), and the
    shared natural-frequency and damping widths over the narrower single point's (each point
    identified alone with the same prior)."""
    from setmem_hil.cli.data_options import load_output_priors
    from setmem_hil.io.data_file import read_data_csv

    p1 = REALDATA / "ladisk-pyuff-beam" / "frf_displacement_relaxed.csv"
    p2 = REALDATA / "ladisk-pyuff-beam-point2" / "frf_displacement_relaxed.csv"
    if not p1.is_file():
        print(f"real beam: skipped ({REALDATA} absent)")
        return
    exe = [sys.executable, "-m", "setmem_hil.cli.main"]
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder)
        proposal = subprocess.run(exe + ["prior", "--data", str(p1), "--data", str(p2), "--modes", "6", "--out", str(out / "prior.toml")],
                                  capture_output=True, text=True)
        print(f"real beam, points 1 + 2 (relaxed bound, 6 common modes): prior exit {proposal.returncode}; "
              + next((line for line in proposal.stdout.splitlines() if "complex residues" in line), "real residues"))
        priors, _ = load_output_priors(str(out / "prior.toml"), 2)
        datas = [read_data_csv(p) for p in (p1, p2)]
        t = time.perf_counter()
        joint = identify_outputs(datas, list(priors))
        print(f"  joint identification: {time.perf_counter() - t:.2f} s (2 outputs x 384 points x 6 modes, complex residues)")
        alone = [identify(d, q).model for d, q in zip(datas, priors)]
    print("  mode   f (Hz)     omega_n width ratio   a1 width ratio   (shared / narrower single point)")
    for i in range(len(priors[0].modes)):
        shared = joint.models[0]
        wn = lambda m: np.sqrt(m.upper[i, 1]) - np.sqrt(m.lower[i, 1])  # noqa: E731
        a1 = lambda m: m.upper[i, 0] - m.lower[i, 0]  # noqa: E731
        f_hz = np.sqrt(0.5 * (shared.lower[i, 1] + shared.upper[i, 1])) / (2 * np.pi)
        print(f"  {i + 1:4d}   {f_hz:8.2f}   {wn(shared) / min(wn(m) for m in alone):19.3f}   {a1(shared) / min(a1(m) for m in alone):14.3f}")


if __name__ == "__main__":
    simulated()
    speed()
    real()
