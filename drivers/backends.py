"""The backends factory: a procedure's ``[backend] kind`` to an Experiment (context manager).

``open_experiment(procedure, seed)`` returns, for ``procedure.backend.kind``:

``sim``
    :class:`setmem_hil.sim_backends.simulated_beam.SimulatedBeamExperiment` (frequency-domain
    simulation, no dwell).
``serial-loopback``
    a :class:`~setmem_hil.sim_backends.fake_serial_device.FakeSerialDevice` (the time-domain
    beam behind the serial line protocol on ``socket://127.0.0.1:<free port>``), a
    :class:`~setmem_hil.drivers.serial_rig.SerialRig` and a
    :class:`~setmem_hil.drivers.sine_dwell.SineDwellExperiment` on it.
``can-virtual`` / ``modbus-loopback``
    ``setmem_hil.drivers.can_rig.open_can_virtual_rig(procedure, seed)`` /
    ``setmem_hil.drivers.modbus_rig.open_modbus_loopback_rig(procedure, seed)`` (imported
    lazily) and a SineDwellExperiment on the rig.

Every dwell experiment gets the procedure's safety limits, the prior's interval model for its
transient poles, and, when the simulated structure keeps its unmodelled modes
(``simulation.unmodelled_dynamics`` with fewer modelled modes than the beam's 8), the extra
bound ``|W1(j omega)|`` of the procedure's weights (section 6.2: the identification's noise
bound must also cover the unmodelled dynamics). The dwell amplitude is
``min(1, safety.max_amplitude_n)``. ``[backend.transport]`` may set ``learn_poles`` (carry
the transient poles from dwell to dwell: shorter dwells near modes at the same variance, but a
resumed campaign no longer repeats an uninterrupted one bit for bit) and ``max_window_s``.
``close()`` (or leaving the ``with`` block) commands zero
output and tears the fake device down.

Example
-------
>>> from setmem_hil.io.procedure import default_procedure
>>> with open_experiment(default_procedure(), seed=1) as exp:
...     m = exp.measure(2.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from setmem_hil.drivers.retry import RetryPolicy
from setmem_hil.drivers.sine_dwell import DwellSettings, SineDwellExperiment
from setmem_hil.errors import ProcedureError
from setmem_hil.campaign.experiment import Experiment
from setmem_hil.io.procedure import BACKENDS, Procedure
from setmem_hil.sim_backends.beam import BEAM_N_MODES
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment


@dataclass
class ManagedSimulatedBeam(SimulatedBeamExperiment):
    """The frequency-domain simulated beam, usable as a context manager."""

    def __enter__(self) -> "ManagedSimulatedBeam":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class OwningRig:
    """A rig that also closes the resources behind it (the fake device) when closed.

    Attribute access is delegated to the wrapped rig, so its optional capabilities
    (``begin_measurement``, ``reconnect``, ...) stay visible.
    """

    def __init__(self, rig, *owned):
        self._rig = rig
        self._owned = owned

    @property
    def owned(self) -> tuple:
        """The resources closed with the rig (e.g. the fake device)."""
        return self._owned

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._rig, name)

    def close(self) -> None:
        try:
            self._rig.close()
        finally:
            for res in self._owned:
                res.close()


def retry_policy(transport: Mapping[str, Any], source: str = "procedure") -> RetryPolicy:
    """RetryPolicy from ``[backend.transport]`` (keys ``reply_timeout_s``, ``max_attempts``,
    ``backoff_s``, ``backoff_max_s``; other keys belong to other transports and are ignored)."""
    kw = {}
    for key, kind in (("reply_timeout_s", float), ("max_attempts", int), ("backoff_s", float), ("backoff_max_s", float)):
        if key in transport:
            value = transport[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0 or (kind is int and value != int(value)):
                raise ProcedureError(source, f"[backend.transport] key '{key}'", f"expected a positive {kind.__name__}, found {value!r}")
            kw[key] = kind(value)
    return RetryPolicy(**kw)


def dwell_settings(procedure: Procedure) -> DwellSettings:
    """DwellSettings from the procedure (amplitude, ``learn_poles``, ``max_window_s``)."""
    transport = procedure.backend.transport
    source = procedure.source_path or procedure.name
    learn = transport.get("learn_poles", False)
    if not isinstance(learn, bool):
        raise ProcedureError(source, "[backend.transport] key 'learn_poles'", f"expected true or false, found {learn!r}")
    window = transport.get("max_window_s", DwellSettings.max_window_s)
    if isinstance(window, bool) or not isinstance(window, (int, float)) or not window > 0:
        raise ProcedureError(source, "[backend.transport] key 'max_window_s'", f"expected a positive number of seconds, found {window!r}")
    return DwellSettings(amplitude_n=min(1.0, procedure.safety.max_amplitude_n), learn_poles=learn, max_window_s=float(window))


def dwell_experiment(procedure: Procedure, rig, settings: DwellSettings | None = None) -> SineDwellExperiment:
    """A SineDwellExperiment on ``rig`` configured from the procedure (see the module docs)."""
    sim = procedure.backend.simulation
    n_modelled = procedure.prior.n_modes
    extra = None
    if sim.unmodelled_dynamics and n_modelled < BEAM_N_MODES:
        weights = procedure.weights

        def extra(omega_rad_s: float) -> float:
            return float(weights.w1_magnitude(omega_rad_s))

    settings = settings or dwell_settings(procedure)
    return SineDwellExperiment(rig, procedure.safety, settings, model=procedure.prior.initial_bounds(), extra_bound=extra)


def open_experiment(procedure: Procedure, seed: int) -> Experiment:
    """The Experiment for ``procedure.backend.kind`` (a context manager; see the module docs).

    Raises
    ------
    ProcedureError
        Unknown backend kind or bad transport option.
    setmem_hil.errors.DeviceError
        The fake device or its transport could not be started.
    """
    kind = procedure.backend.kind
    source = procedure.source_path or procedure.name
    if kind == "sim":
        sim = procedure.backend.simulation
        return ManagedSimulatedBeam(
            noise_profile=sim.noise_profile,
            seed=seed,
            unmodelled_dynamics=sim.unmodelled_dynamics,
            n_modelled=procedure.prior.n_modes,
            noise_scale=sim.noise_scale,
            w1_num=tuple(procedure.weights.w1_num),
            w1_den=tuple(procedure.weights.w1_den),
        )
    if kind not in BACKENDS:
        raise ProcedureError(source, "[backend] key 'kind'", f"expected one of {list(BACKENDS)}, found {kind!r}")
    settings = dwell_settings(procedure)  # validated before any device is started
    if kind == "serial-loopback":
        from setmem_hil.drivers.serial_rig import SerialRig
        from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
        from setmem_hil.sim_backends.fake_serial_device import FakeSerialDevice

        policy = retry_policy(procedure.backend.transport, source)
        core = FakeDeviceCore.from_procedure(procedure, seed)
        device = FakeSerialDevice(core)
        try:
            rig = SerialRig(device.url, policy)
        except BaseException:
            device.close()
            raise
        owning = OwningRig(rig, device)
        try:
            return dwell_experiment(procedure, owning, settings)
        except BaseException:
            owning.close()
            raise
    if kind == "can-virtual":
        from setmem_hil.drivers.can_rig import open_can_virtual_rig

        return dwell_experiment(procedure, open_can_virtual_rig(procedure, seed), settings)
    if kind == "modbus-loopback":
        from setmem_hil.drivers.modbus_rig import open_modbus_loopback_rig

        return dwell_experiment(procedure, open_modbus_loopback_rig(procedure, seed), settings)
    raise ProcedureError(source, "[backend] key 'kind'", f"expected one of {list(BACKENDS)}, found {kind!r}")
