"""Transport-specific fault kinds (CAN error frames and bus-off, Modbus exception responses).

The transport-independent kinds (timeouts, truncated/corrupted/duplicated/reordered frames,
disconnects, data faults) live in :mod:`setmem_hil.sim_backends.fake_device_core`. A procedure's
``[backend.faults]`` table names kinds of both sets in one ``kinds`` list; :func:`split_faults`
separates them so the core sees only its own kinds, and :class:`TransportFaults` draws the
transport kinds with the same ``rate`` from an independent, seeded generator.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import ProcedureError
from setmem_hil.io.fault_kinds import CAN_FAULT_KINDS, FAULT_KINDS, MODBUS_FAULT_KINDS  # noqa: F401 (re-exported)


@dataclasses.dataclass
class TransportFaults:
    """Seeded draws of transport-specific fault kinds, with counters of injections.

    Parameters
    ----------
    rate : float
        Probability per opportunity (per command handled by the fake device).
    kinds : tuple of str
        Enabled transport kinds.
    seed : int
        Seed; the generator is ``default_rng((seed, 0x7A05))``.
    rates : tuple of (kind, rate)
        Per-kind overrides of ``rate`` (``[backend.faults.rates]``).
    """

    rate: float = 0.0
    kinds: tuple[str, ...] = ()
    seed: int = 0
    rates: tuple[tuple[str, float], ...] = ()
    injected: dict[str, int] = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self._rng = np.random.default_rng((self.seed, 0x7A05))
        self.injected = {k: 0 for k in self.kinds}

    def rate_of(self, kind: str) -> float:
        return dict(self.rates).get(kind, self.rate)

    def draw(self, kind: str) -> bool:
        rate = self.rate_of(kind)
        if rate <= 0 or kind not in self.kinds:
            return False
        hit = bool(self._rng.random() < rate)
        if hit:
            self.injected[kind] += 1
        return hit


def split_faults(procedure, transport_kinds: tuple[str, ...]) -> tuple[Any, TransportFaults]:
    """Return ``(procedure_for_core, transport_faults)``.

    ``procedure_for_core`` is a copy of ``procedure`` whose ``backend.faults`` lists only the
    core's kinds, in ``kinds`` and in the per-kind ``rates`` table (so
    ``FakeDeviceCore.from_procedure`` accepts it); without a ``kinds`` key every core kind and
    every transport kind is enabled.

    Raises
    ------
    ProcedureError
        A kind that neither the core nor this transport knows (names the key and the kinds).
    """
    faults: Mapping[str, Any] = dict(procedure.backend.faults or {})
    source = procedure.source_path or procedure.name
    if "kinds" in faults:
        kinds = faults["kinds"]
        if isinstance(kinds, str) or not all(isinstance(k, str) for k in kinds):
            raise ProcedureError(source, "[backend.faults] key 'kinds'", f"expected a list of names, found {kinds!r}")
        unknown = [k for k in kinds if k not in FAULT_KINDS and k not in transport_kinds]
        if unknown:
            raise ProcedureError(
                source, "[backend.faults] key 'kinds'",
                f"unknown kinds {unknown}; expected some of {list(FAULT_KINDS) + list(transport_kinds)}",
            )
        core_kinds = [k for k in kinds if k in FAULT_KINDS]
        mine = tuple(k for k in kinds if k in transport_kinds)
        core_faults = dict(faults, kinds=core_kinds)
    else:
        mine = tuple(transport_kinds)
        core_faults = dict(faults)
    rates = faults.get("rates", {})
    my_rates: list[tuple[str, float]] = []
    if isinstance(rates, Mapping):
        for kind, r in rates.items():
            if kind in transport_kinds:
                if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 <= float(r) <= 1.0:
                    raise ProcedureError(source, f"[backend.faults.rates] key '{kind}'", f"expected a number in [0, 1], found {r!r}")
                my_rates.append((kind, float(r)))
        core_faults["rates"] = {k: r for k, r in rates.items() if k not in transport_kinds}
        if not core_faults["rates"]:
            del core_faults["rates"]
    rate = faults.get("rate", 0.0)
    seed = faults.get("seed", 0)
    backend = dataclasses.replace(procedure.backend, faults=core_faults)
    core_procedure = dataclasses.replace(procedure, backend=backend)
    rate_ok = isinstance(rate, (int, float)) and not isinstance(rate, bool)
    transport = TransportFaults(
        float(rate) if rate_ok else 0.0, mine, int(seed) if isinstance(seed, int) else 0, tuple(my_rates)
    )
    return core_procedure, transport


def injected_counts(core_faults, transport_faults: "TransportFaults | None" = None) -> dict[str, int]:
    """Faults injected so far per kind, over the core's kinds and the transport's (non-zero only).

    Every fake device reports its ``injected`` property through this one function.
    """
    counts = {k: v for k, v in core_faults.injected.items() if v}
    if transport_faults is not None:
        counts.update({k: v for k, v in transport_faults.injected.items() if v})
    return counts


class BackgroundFakeDevice:
    """Lifecycle every background fake device shares (CAN, Modbus): ``start()`` returns the
    device, ``stop()`` ends it, ``close()`` is ``stop()`` (the interface a rig's owned resources
    have), a context manager, and ``injected`` counts the faults injected so far per kind.

    Needs ``self.core`` (the fake device core) and ``self.transport_faults``.
    """

    def start(self):
        raise NotImplementedError

    def stop(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self.stop()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def injected(self) -> dict[str, int]:
        """Faults injected so far, per kind (core and transport kinds)."""
        return injected_counts(self.core.faults, self.transport_faults)
