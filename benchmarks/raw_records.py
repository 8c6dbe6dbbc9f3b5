"""Benchmark: the cost of keeping every dwell's raw record in ``RUN_DIR/raw.h5`` (issue 39).

A DS1104Z record of 3 x 1.2 M samples (force and two responses, 8-bit codes times the vertical
scale plus offset, as the scope delivers volts) plus its time axis, written as the sine dwell
writes it (:func:`setmem_hil.estimation.dwell_record.dwell_record` through
:class:`setmem_hil.io.raw_store.RawStore`: its own file, fsynced, renamed; the index rebuilt),
then read back. Prints the file size, the write and read times, the compression ratio, and the
size per hour of rig time at the record's own length (1.2 M samples at 100 kSa/s: 12 s per
record, so 300 records an hour, back to back: the worst case). For comparison, the same
record's sine fit (the dwell's own computation, :func:`results_from_inputs`) is timed too: the
write must not be the bottleneck.

Run: ``.venv/bin/python benchmarks/raw_records.py [--samples N] [--repeats R]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from setmem_hil.estimation.dwell_estimate import DwellPlan, DwellSettings
from setmem_hil.estimation.dwell_record import DwellInputs, dwell_record, results_from_inputs
from setmem_hil.io.raw_store import RawStore, read_raw_records


def scope_volts(rng, t, amplitude_v, phase, omega, scale_v):
    """An 8-bit scope's reading of a noisy sine: codes times the vertical scale (10 divisions, 25 codes a division)."""
    clean = amplitude_v * np.sin(omega * t + phase) + rng.normal(0, 0.003, t.size)
    codes = np.clip(np.round(clean / (scale_v / 25.0)), -127, 127)
    return codes * (scale_v / 25.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1_200_000)
    parser.add_argument("--rate", type=float, default=100e3, help="sample rate (Sa/s)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(1)
    n, rate, omega = args.samples, args.rate, 2 * np.pi * 49.5
    t = np.arange(n) / rate
    channels = [scope_volts(rng, t, a, p, omega, s) for a, p, s in ((0.8, 0.0, 0.2), (0.5, -1.1, 0.1), (0.3, -0.7, 0.05))]
    inputs = DwellInputs(DwellSettings(), None, (), None, DwellPlan(omega, rate, 2.0, n / rate, n), t, channels[0], channels[1],
                         (channels[2],), 0, 2.0 + n / rate, 0)
    record = dwell_record(inputs, rig="DS1104Z benchmark")
    raw_bytes = sum(np.asarray(d).nbytes for d in record.datasets.values())
    writes, reads = [], []
    with tempfile.TemporaryDirectory() as folder:
        store = RawStore(folder)
        for k in range(args.repeats):
            start = time.perf_counter()
            path = store.write((k + 1,), record)
            writes.append(time.perf_counter() - start)
        size = path.stat().st_size
        start = time.perf_counter()
        back = read_raw_records(folder)
        reads.append((time.perf_counter() - start) / len(back))
        index_bytes = (Path(folder) / "raw.h5").stat().st_size
    start = time.perf_counter()
    results_from_inputs(inputs)
    fit_s = time.perf_counter() - start
    per_hour = 3600.0 / (n / rate)
    print(f"record: 3 channels x {n} samples + time axis at {rate / 1e3:g} kSa/s ({n / rate:g} s), {raw_bytes / 1e6:.1f} MB in memory")
    print(f"file: {size / 1e6:.1f} MB (ratio {raw_bytes / size:.2f}), index {index_bytes / 1e3:.1f} kB")
    print(f"write: median {np.median(writes):.3f} s (min {min(writes):.3f}, max {max(writes):.3f}) over {args.repeats}; "
          f"read back: {np.median(reads):.3f} s")
    print(f"the dwell's own fit of the same record: {fit_s:.3f} s (write / fit = {np.median(writes) / fit_s:.2f})")
    print(f"rig time: {per_hour:.0f} such records an hour back to back -> {size * per_hour / 1e9:.2f} GB per hour of rig time "
          f"(write time {np.median(writes) * per_hour / 36:.1f} % of the hour)")


if __name__ == "__main__":
    main()
