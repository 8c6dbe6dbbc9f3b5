"""Fault survey of the CAN and Modbus transports: faults injected and survived, per kind (issue 8).

For each fault kind alone, the same short dwells (same seed) are acquired through the transport
once without faults and once with the kind injected at ``rate``. A kind is *survived* when
every acquisition completed and its samples are bit-identical to the fault-free run: the fault
was detected or tolerated, corrupted data were discarded and never used, and the retries did
not disturb the device's state (the exciter and the virtual clock). The survey also reports
what the host detected (``transport_statistics``).

Run ``python -m setmem_hil.loopback.fault_survey`` for the table.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np

from setmem_hil.errors import DeviceError
from setmem_hil.loopback.rigs import open_can_virtual_rig, open_modbus_loopback_rig
from setmem_hil.io.procedure import Procedure, SimulationSettings, default_procedure

CAN_KINDS = ("timeout", "truncate", "corrupt", "duplicate", "reorder", "disconnect", "error_frame", "bus_off")
MODBUS_KINDS = ("timeout", "truncate", "corrupt", "duplicate", "reorder", "disconnect", "exception")
RTU_KINDS = ("timeout", "truncate", "corrupt", "disconnect", "exception")


@dataclasses.dataclass(frozen=True)
class KindResult:
    """One row of the survey.

    Attributes
    ----------
    transport, kind : str
    injected : int
        Faults of this kind the fake device injected.
    survived : bool
        Every acquisition completed with samples identical to the fault-free run.
    error : str
        The error that ended the run, if any.
    detected : dict
        The host's counters (timeouts, CRC errors, retries, reconnects, ...).
    wall_s : float
    """

    transport: str
    kind: str
    injected: int
    survived: bool
    error: str
    detected: dict
    wall_s: float


def _procedure(transport: str, faults: dict) -> Procedure:
    proc = default_procedure()
    kind, framer = ("can-virtual", None) if transport == "can" else ("modbus-loopback", transport.split("-")[1])
    backend = dataclasses.replace(
        proc.backend, kind=kind, simulation=SimulationSettings(noise_profile="fully_damped"), faults=faults,
        transport={"framer": framer} if framer else {},
    )
    return dataclasses.replace(proc, backend=backend)


def _opener(transport: str) -> Callable:
    return open_can_virtual_rig if transport == "can" else open_modbus_loopback_rig


def _acquire(rig, omegas, n_samples: int) -> list:
    blocks = []
    for i, omega in enumerate(omegas):
        rig.begin_measurement(i)
        fs = 32 * omega / (2 * np.pi)
        rig.sensor.set_sample_rate(fs)
        rig.exciter.set_sine(omega, 0.5)
        rig.sensor.wait(10.0)
        blocks.append(rig.sensor.acquire(n_samples / fs))
        rig.exciter.stop()
    return blocks


def survey(
    transport: str, kinds: tuple[str, ...], rate: float = 0.05, seed: int = 1, omegas=(3.0, 9.0), n_samples: int = 300
) -> list[KindResult]:
    """Run the survey for ``transport`` in ``("can", "modbus-socket", "modbus-rtu")``."""
    opener = _opener(transport)
    with opener(_procedure(transport, {}), seed) as rig:
        clean = _acquire(rig, omegas, n_samples)
    rows = []
    for kind in kinds:
        t0 = time.perf_counter()
        error, survived, blocks = "", False, None
        rig = opener(_procedure(transport, {"rate": rate, "kinds": [kind], "seed": seed}), seed)
        try:
            blocks = _acquire(rig, omegas, n_samples)
        except DeviceError as exc:
            error = str(exc)
        finally:
            injected = rig.owned[0].injected.get(kind, 0)
            detected = rig.transport_statistics()
            rig.close()
        if blocks is not None:
            survived = all(
                np.array_equal(a.t_s, b.t_s) and np.array_equal(a.force, b.force) and np.array_equal(a.response, b.response)
                for a, b in zip(clean, blocks)
            )
        rows.append(KindResult(transport, kind, injected, survived, error, detected, time.perf_counter() - t0))
    return rows


def main() -> None:  # pragma: no cover - a report, exercised by hand
    for transport, kinds in (("can", CAN_KINDS), ("modbus-socket", MODBUS_KINDS), ("modbus-rtu", RTU_KINDS)):
        for r in survey(transport, kinds):
            print(f"{r.transport:14s} {r.kind:12s} injected {r.injected:4d}  survived {str(r.survived):5s}  "
                  f"{r.wall_s:5.2f} s  {r.error or r.detected}")


if __name__ == "__main__":  # pragma: no cover
    main()
