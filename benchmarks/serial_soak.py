"""Soak run of the serial transport under fault injection: faults injected and survived per kind.

Run: ``.venv/bin/python benchmarks/serial_soak.py [--dwells 150] [--rate 0.03]``

Every fault kind of the fake device core and the serial fake is enabled (frame kinds per
response frame, data kinds per capture; ``disconnect`` at ``rate / 6`` because it ends the
dwell). A fault counts as *survived* when the measurement during which it was injected returned
a response whose bound contains the true 8-mode response; *fatal* when the measurement raised.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.drivers.serial_rig import SerialRig
from setmem_hil.drivers.sine_dwell import SineDwellExperiment
from setmem_hil.errors import DataQualityError, DeviceError
from setmem_hil.io.procedure import SafetyLimits, default_procedure, thesis_beam_prior
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.fake_device_core import FAULT_KINDS, FakeDeviceCore, FaultSettings
from setmem_hil.sim_backends.fake_serial_device import FakeSerialDevice


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dwells", type=int, default=150)
    ap.add_argument("--rate", type=float, default=0.03)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--message-chars", type=int, default=300)
    args = ap.parse_args(argv)
    truth = beam_parameters()
    faults = FaultSettings(args.rate, FAULT_KINDS, args.seed, (("disconnect", args.rate / 6),))
    core = FakeDeviceCore.from_procedure(default_procedure(), args.seed, faults=faults)
    dev = FakeSerialDevice(core)
    rig = SerialRig(dev.url, RetryPolicy(reply_timeout_s=0.1))
    exp = SineDwellExperiment(rig, SafetyLimits(), model=thesis_beam_prior().initial_bounds())
    rng = np.random.default_rng(args.seed)
    survived, fatal = Counter(), Counter()
    ok = failed = inside = 0
    t0 = time.time()
    try:
        for w in np.exp(rng.uniform(np.log(0.3), np.log(40.0), args.dwells)):
            before = dict(core.faults.injected)
            try:
                m = exp.measure(float(w))
            except (DeviceError, DataQualityError) as exc:
                failed += 1
                delta = {k: core.faults.injected[k] - before[k] for k in FAULT_KINDS}
                fatal.update({k: v for k, v in delta.items() if v})
                print(f"measurement at {w:.3f} rad/s failed: {exc}"[: args.message_chars])
                continue
            ok += 1
            good = abs(m.response - truth.frequency_response(w)[0]) <= m.bound
            inside += good
            delta = {k: core.faults.injected[k] - before[k] for k in FAULT_KINDS}
            (survived if good else fatal).update({k: v for k, v in delta.items() if v})
    finally:
        exp.close()
        dev.close()
    print(f"{args.dwells} measurements over serial in {time.time() - t0:.1f} s: {ok} returned "
          f"({inside} with the truth inside the bound), {failed} raised a typed error")
    print(f"{'kind':<16}{'injected':>9}{'survived':>9}{'fatal':>7}")
    for k in FAULT_KINDS:
        print(f"{k:<16}{core.faults.injected[k]:9d}{survived[k]:9d}{fatal[k]:7d}")
    st = rig.link.stats
    print(f"host: {st['requests']} requests, {st['retries']} retries, {st['timeouts']} timeouts, "
          f"{st['frame_errors']} frame errors, {st['stale_discarded']} stale frames discarded, "
          f"{st['garbage_discarded']} partial lines discarded; {rig.reconnects} reconnects; "
          f"dwell: {exp.counters}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
