"""Rig time to reach mu-bar < 1: the 6.3.2 campaign through a time-domain backend (issue 15).

Each campaign runs the thesis's section 6.3.2 procedure on the fake shaker + DAQ device (the exact
time-domain beam, sensor noise, virtual clock) through the sine dwell, in process (CoreRig: the
same dwell numerics as the serial, CAN and Modbus loopback rigs, without their wire formats).
Rig time is the device time of every dwell (settling, excitation, acquisition), initial points
included, as ``summary.json`` reports it. Configurations:

* ``single-sine``: today's loop (one frequency per iteration, the thesis ranking);
* ``per_rig_second``: candidates ranked by expected improvement per second of rig time;
* ``batch-2``, ``batch-3``: two or three frequencies per iteration (batch design);
* ``batch-3/per_rig_second``: both;
* ``multisine...``: ``[dwell] signal = "multisine"``: the 15 initial points in one multisine
  record, each iteration's frequencies in one record, with the options above;
* ``.../h2``: the same with the thesis's H2 design (issue 38); the others run the default robust
  design. With ``single-sine/h2`` among the configurations the ratios are to it.

A naive "wait five time constants" rig is reported as a computed figure: every dwell waits
``5 / (zeta omega_1)`` for the slowest (first) mode of the true beam (zeta = 0.01, omega_1 =
1 rad/s: 500 s) plus the same fit window, with the single-sine loop's dwells.

``--backend scope`` runs the same campaign through the emulated instruments instead
(``procedures/instruments_scope_emulated.toml``: a 33500B playing single sines or the record as an
arbitrary waveform, a DS1104Z sampling the force and three responses, the channel match
measured on the emulated tee first; seed = the procedure's seed), for ``single-sine`` and the
shipped fast configuration ``multisine/batch-5``; rig time is what the instruments' clock
counted (levelling records, re-records after clipping, 1-2-5 time bases included) and
coverage is over every output's points. ``--generator`` plays them through another shipped
generator profile's emulator (``rigol-dg800``: 14-bit binary packages; ``siglent-sdg2000x``:
16-bit TrueArb).

Usage::

    .venv/bin/python benchmarks/rig_time.py --seeds 1-10 --workers 2
    .venv/bin/python benchmarks/rig_time.py --seeds 101-120 --backend scope --only single-sine,multisine/batch-5
    .venv/bin/python benchmarks/rig_time.py --seeds 101-120 --backend scope --only multisine/batch-5 --generator rigol-dg800
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from concurrent.futures import ProcessPoolExecutor

CONFIGS = {
    "single-sine": {},
    "per_rig_second": {"ranking": "per_rig_second"},
    "batch-2": {"per_iteration": 2},
    "batch-3": {"per_iteration": 3},
    "batch-3/per_rig_second": {"per_iteration": 3, "ranking": "per_rig_second"},
    "multisine": {"signal": "multisine"},
    "multisine/per_rig_second": {"signal": "multisine", "ranking": "per_rig_second"},
    "multisine/batch-2": {"signal": "multisine", "per_iteration": 2},
    "multisine/batch-3": {"signal": "multisine", "per_iteration": 3},
    "multisine/batch-3/per_rig_second": {"signal": "multisine", "per_iteration": 3, "ranking": "per_rig_second"},
    "multisine/batch-5": {"signal": "multisine", "per_iteration": 5},
    "multisine/batch-5/window-60": {"signal": "multisine", "per_iteration": 5, "max_window_s": 60.0},
    # the thesis's H2 loop (issue 38); every configuration above runs the procedure's default design
    "single-sine/h2": {"design": "h2"},
    "multisine/batch-5/h2": {"signal": "multisine", "per_iteration": 5, "design": "h2"},
}


def run_scope(config: str, seed: int, generator: str = "keysight-33500b") -> dict:
    """One campaign through the emulated generator + oscilloscope (module docstring)."""
    import tempfile
    from pathlib import Path

    import numpy as np

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.procedure_file import parse_procedure_text
    from setmem_hil.sim_backends.beam import beam_parameters_at

    shipped = Path(__file__).resolve().parents[1] / "procedures" / "instruments_scope_emulated.toml"
    base = parse_procedure_text(shipped.read_text(), str(shipped))
    options = dict(CONFIGS[config])
    signal = options.pop("signal", "sine")
    design = options.pop("design", None)
    options.pop("max_window_s", None)
    with tempfile.TemporaryDirectory() as where:  # no match file there: measured on the emulated tee
        fgen = dataclasses.replace(base.instruments["fgen"], profile=generator)
        procedure = dataclasses.replace(base, seed=seed, dwell_signal=signal, source_path=str(Path(where) / "scope.toml"),
                                        input_design=dataclasses.replace(base.input_design, **options),
                                        instruments={**base.instruments, "fgen": fgen})
        t0 = time.perf_counter()
        measured = []
        with open_experiment(procedure, seed) as exp:
            for name in ("measure", "measure_multisine"):
                inner = getattr(exp, name)

                def spy(arg, inner=inner, single=(name == "measure")):
                    out = inner(arg)
                    measured.extend([out] if single else (out[1:] if len(arg) == 1 else out))
                    return out

                setattr(exp, name, spy)
            summary = run_campaign(procedure, exp, seed=seed, design=design)
    inside = [abs(g - complex(np.ravel(beam_parameters_at(x, 1.0).frequency_response(np.array([m.omega_rad_s])))[0])) <= b
              for m in measured for x, (g, b) in zip((1.0, 0.7, 0.4), [(m.response, m.bound), *m.others])]
    return {
        "config": config, "seed": seed, "reached": summary.reached_goal, "rig_s": summary.rig_s,
        "experiments": summary.experiments_added, "iterations": len(summary.iterations),
        "dwells": len(measured), "coverage": float(np.mean(inside)), "wall_s": time.perf_counter() - t0,
        "window_s": [m.rig_s for m in measured],
    }


def run_one(config: str, seed: int, backend: str = "time-domain", generator: str = "keysight-33500b") -> dict:
    if backend == "scope":
        try:
            return run_scope(config, seed, generator)
        except Exception as exc:  # noqa: BLE001 - a campaign that stops is a row of the table, not the end of it
            print(f"{config} seed {seed}: stopped: {exc}"[:300], flush=True)
            return {"config": config, "seed": seed, "reached": False, "rig_s": float("nan"), "experiments": 0, "iterations": 0,
                    "dwells": 0, "coverage": float("nan"), "wall_s": 0.0, "window_s": []}
    import numpy as np

    from setmem_hil.campaign.runner import run_campaign
    from setmem_hil.experiment_factory import dwell_experiment, dwell_settings
    from setmem_hil.io.procedure import default_procedure
    from setmem_hil.sim_backends.core_rig import CoreRig
    from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

    base = default_procedure()
    options = dict(CONFIGS[config])
    signal = options.pop("signal", "sine")
    design = options.pop("design", None)
    window = options.pop("max_window_s", None)
    procedure = dataclasses.replace(base, seed=seed, dwell_signal=signal, input_design=dataclasses.replace(base.input_design, **options))
    core = FakeDeviceCore.from_procedure(procedure, seed)
    t0 = time.perf_counter()
    measured = []
    settings = dwell_settings(procedure)
    if window is not None:
        settings = dataclasses.replace(settings, max_window_s=window)
    with dwell_experiment(procedure, CoreRig(core), settings) as exp:
        inner = exp.measure

        def measure(w):
            m = inner(w)
            measured.append(m)
            return m

        exp.measure = measure
        inner_record = exp.measure_multisine

        def measure_multisine(ws):
            ms = inner_record(ws)
            measured.extend(ms[1:] if len(ws) == 1 else ms)  # a single line went through measure()
            return ms

        exp.measure_multisine = measure_multisine
        summary = run_campaign(procedure, exp, seed=seed, design=design)
    truth = core.true_response(np.array([m.omega_rad_s for m in measured]))
    inside = np.abs(np.array([m.response for m in measured]) - truth) <= np.array([m.bound for m in measured])
    return {
        "config": config, "seed": seed, "reached": summary.reached_goal, "rig_s": summary.rig_s,
        "experiments": summary.experiments_added, "iterations": len(summary.iterations),
        "dwells": len(measured), "coverage": float(inside.mean()), "wall_s": time.perf_counter() - t0,
        "window_s": [m.rig_s for m in measured],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default="1-10", help="A-B (inclusive), or N for 1-N")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--only", help="comma-separated configurations")
    parser.add_argument("--backend", choices=("time-domain", "scope"), default="time-domain",
                        help="the in-process time-domain rig, or the emulated generator + oscilloscope")
    parser.add_argument("--generator", default="keysight-33500b", help="with --backend scope: the generator's shipped profile")
    args = parser.parse_args()
    configs = args.only.split(",") if args.only else list(CONFIGS)
    first, _, last = args.seeds.partition("-")
    seeds = range(1, int(first) + 1) if not last else range(int(first), int(last) + 1)
    jobs = [(c, s) for c in configs for s in seeds]
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(run_one, *zip(*jobs), [args.backend] * len(jobs), [args.generator] * len(jobs)))
    reference = "single-sine/h2" if "single-sine/h2" in configs else "single-sine"
    baseline = statistics.median(r["rig_s"] for r in results if r["config"] == reference) if reference in configs else None
    print("| configuration | rig time to goal, median (s) | max (s) | ratio to single-sine | reached | experiments (median) | iterations (median) | coverage (min) |")
    print("|---|---|---|---|---|---|---|---|")
    for c in configs:
        rs = [r for r in results if r["config"] == c]
        med = statistics.median(r["rig_s"] for r in rs)
        ratio = f"{med / baseline:.2f}" if baseline else "-"
        print(f"| {c} | {med:.0f} | {max(r['rig_s'] for r in rs):.0f} | {ratio} | {sum(r['reached'] for r in rs)}/{len(rs)} | "
              f"{statistics.median(r['experiments'] for r in rs):g} | {statistics.median(r['iterations'] for r in rs):g} | "
              f"{min(r['coverage'] for r in rs):.3f} |")
    if "single-sine" in configs and args.backend == "time-domain":
        rs = [r for r in results if r["config"] == "single-sine"]
        naive = [r["rig_s"] + r["dwells"] * 5.0 / (0.01 * 1.0) for r in rs]
        print(f"| naive: wait 5 time constants of mode 1 per dwell (computed) | {statistics.median(naive):.0f} | {max(naive):.0f} | "
              f"{statistics.median(naive) / baseline:.2f} | - | - | - | - |")
    print(f"\nwall time per campaign: median {statistics.median(r['wall_s'] for r in results):.1f} s")


if __name__ == "__main__":
    main()
