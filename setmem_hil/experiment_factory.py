"""The experiment factory: a procedure's ``[backend] kind`` to an Experiment (context manager).

``open_experiment(procedure, seed)`` returns, for ``procedure.backend.kind``:

``sim``
    :class:`setmem_hil.sim_backends.simulated_beam.SimulatedBeamExperiment` (frequency-domain
    simulation, no dwell).
``serial-loopback``
    a :class:`~setmem_hil.sim_backends.fake_serial_device.FakeSerialDevice` (the time-domain
    beam behind the serial line protocol on ``socket://127.0.0.1:<free port>``), a
    :class:`~setmem_hil.drivers.serial_rig.SerialRig` and a
    :class:`~setmem_hil.drivers.sine_dwell.SineDwellExperiment` on it.
``time-domain``
    the fake shaker + DAQ (:class:`~setmem_hil.sim_backends.fake_device_core.FakeDeviceCore`:
    exact time-domain beam, sensor noise, virtual clock) called in process
    (:class:`~setmem_hil.sim_backends.core_rig.CoreRig`) and a SineDwellExperiment on it: the
    dwell numerics without a wire format, and the one device backend that plays multisines.
``can-virtual`` / ``modbus-loopback``
    :func:`setmem_hil.loopback.rigs.open_can_virtual_rig` /
    :func:`setmem_hil.loopback.rigs.open_modbus_loopback_rig` and a SineDwellExperiment on the rig.

This composition module is the only place (with :mod:`setmem_hil.loopback`) that knows both the
hardware drivers and the simulation; the campaign sees only the
:class:`~setmem_hil.model.experiment.Experiment` protocol.

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

import time
from dataclasses import dataclass, replace

import numpy as np

from typing import TYPE_CHECKING

from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import BACKENDS, Procedure
from setmem_hil.model.experiment import Experiment
from setmem_hil.sim_backends.beam import BEAM_N_MODES, scaled_beam
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

if TYPE_CHECKING:  # each backend's stack is imported when that backend opens (a run's journal exists at once)
    from setmem_hil.drivers.sine_dwell import DwellSettings, SineDwellExperiment

__all__ = ["open_experiment", "dwell_settings", "dwell_experiment", "ManagedSimulatedBeam"]

LOOPBACK_RIGS = ("serial-loopback", "can-virtual", "modbus-loopback")


def _open_loopback_rig(kind: str, procedure: Procedure, seed: int):
    from setmem_hil.loopback import rigs

    opener = {"serial-loopback": rigs.open_serial_loopback_rig, "can-virtual": rigs.open_can_virtual_rig,
              "modbus-loopback": rigs.open_modbus_loopback_rig}[kind]
    return opener(procedure, seed)


@dataclass
class ManagedSimulatedBeam(SimulatedBeamExperiment):
    """The frequency-domain simulated beam, usable as a context manager.

    It has no dwell, so each measurement's ``rig_s`` is the time the time-domain sine dwell
    (the loopback rigs' :class:`~setmem_hil.drivers.sine_dwell.SineDwellExperiment`, default
    settings) would plan for it with the current interval model: skip plus first window, without
    window extensions. A planning figure, comparable between strategies, not a measured one.
    """

    dwell_model: object = None

    def __enter__(self) -> "ManagedSimulatedBeam":
        return self

    def update_model(self, model) -> None:
        self.dwell_model = model

    def measure_many(self, omega_rad_s, noise_gain=1.0):
        from setmem_hil.drivers.sine_dwell import DwellSettings
        from setmem_hil.estimation.dwell_estimate import plan_dwell

        measured = super().measure_many(omega_rad_s, noise_gain)
        if self.dwell_model is None:
            return measured
        settings = DwellSettings()
        return [replace(m, rig_s=float(sum(getattr(plan_dwell(settings, self.dwell_model, m.omega_rad_s), k) for k in ("skip_s", "window_s"))))
                for m in measured]

    def measure_multisine(self, omegas_rad_s) -> list:
        """One multisine record (as the time-domain dwell would play it): each line carries the
        force share of :func:`~setmem_hil.estimation.multisine.design_multisine` (peak 1 N), so
        its noise and bound grow by ``1 / a_k``; the record's planned time is shared equally."""
        from setmem_hil.drivers.sine_dwell import DwellSettings
        from setmem_hil.estimation.dwell_estimate import plan_multisine, record_duration_s
        from setmem_hil.estimation.multisine import design_multisine

        lines = [float(w) for w in omegas_rad_s]
        if len(lines) == 1:
            return self.measure_many(lines)
        settings = DwellSettings()
        plan = plan_multisine(settings, self.dwell_model, lines)
        signal = design_multisine(lines, settings.amplitude_n, record_duration_s(settings, plan))
        gains = settings.amplitude_n / np.asarray(signal.amplitudes_n)
        measured = SimulatedBeamExperiment.measure_many(self, lines, gains)
        share = (plan.skip_s + plan.window_s) / len(lines)
        return [replace(m, rig_s=share) for m in measured]

    def __exit__(self, *exc) -> None:
        self.close()


def dwell_settings(procedure: Procedure) -> DwellSettings:
    """DwellSettings from the procedure (amplitude, ``learn_poles``, ``max_window_s``)."""
    from setmem_hil.drivers.sine_dwell import DwellSettings

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
    from setmem_hil.drivers.sine_dwell import SineDwellExperiment

    sim = procedure.backend.simulation
    n_modelled = procedure.prior.n_modes
    extra = None
    if procedure.unmodelled_bound is not None:  # stated in [identification]: it decides
        extra = unmodelled_bound(procedure)
    elif sim.unmodelled_dynamics and n_modelled < BEAM_N_MODES:
        extra = unmodelled_bound(procedure)

    settings = settings or dwell_settings(procedure)
    return SineDwellExperiment(rig, procedure.safety, settings, model=procedure.prior.initial_bounds(), extra_bound=extra)


def unmodelled_bound(procedure: Procedure):
    """``|W1(j omega)|`` as a function when ``[identification] unmodelled_bound`` is ``"w1"``
    (the default on instrument backends), else None."""
    if (procedure.unmodelled_bound or "w1") != "w1":
        return None
    weights = procedure.weights

    def extra(omega_rad_s: float) -> float:
        return float(weights.w1_magnitude(omega_rad_s))

    return extra


def open_instruments(procedure: Procedure, seed: int):
    """Real instruments, or their emulators when the procedure has ``[backend.emulation]``."""
    extra = unmodelled_bound(procedure)
    if procedure.backend.emulation is not None:
        from setmem_hil.loopback.instrument_emulation import open_emulated_instruments

        return open_emulated_instruments(procedure, seed, extra_bound=extra)
    from setmem_hil.drivers.instruments.instrument_set import open_instrument_experiment

    return open_instrument_experiment(procedure, extra_bound=extra)


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
            first_mode_rad_s=sim.first_mode_rad_s,
            sensors=tuple(sim.sensors),
            actuator=sim.actuator,
            control_output=sim.control_output - 1,
            truth_modes=tuple(sim.truth_modes),
            dwell_model=procedure.prior.initial_bounds(),
        )
    if kind == "instruments":
        return open_instruments(procedure, seed)
    if kind == "time-domain":
        from setmem_hil.sim_backends.core_rig import CoreRig
        from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

        return dwell_experiment(procedure, CoreRig(FakeDeviceCore.from_procedure(procedure, seed)))
    if kind not in LOOPBACK_RIGS:
        raise ProcedureError(source, "[backend] key 'kind'", f"expected one of {list(BACKENDS)}, found {kind!r}")
    settings = dwell_settings(procedure)  # validated before any device is started
    rig = _open_loopback_rig(kind, procedure, seed)
    try:
        return dwell_experiment(procedure, rig, settings)
    except BaseException:
        rig.close()
        raise


def true_structure(procedure: Procedure):
    """The structure a simulating backend simulates (all its modes), or None for real
    instruments: the truth ``setmem-hil validate`` checks the compensator against."""
    from setmem_hil.model.modal_model import ModalParameters
    from setmem_hil.sim_backends.beam import BEAM_DAMPING_RATIO, BEAM_RESIDUE, beam_natural_frequencies, beam_parameters

    backend = procedure.backend
    if backend.kind == "instruments":
        if backend.emulation is None:
            return None
        damping = backend.emulation.damping if backend.emulation.damping is not None else BEAM_DAMPING_RATIO
        return scaled_beam(ModalParameters.from_modal(beam_natural_frequencies(), damping, BEAM_RESIDUE, 0.0), backend.emulation.first_mode_rad_s)
    sim = backend.simulation
    if sim.truth_modes:  # a truth file's structure (issue 47)
        full = ModalParameters.from_mode_table(sim.truth_modes)
        return full if sim.unmodelled_dynamics else full.truncated(min(procedure.prior.n_modes, full.n_modes))
    control = sim.sensors[sim.control_output - 1]
    if (control, sim.actuator) == (1.0, 1.0):
        full = beam_parameters()
    else:  # several sensors (issue 25): the control sensor's view of the beam
        from setmem_hil.sim_backends.beam import beam_parameters_at

        full = beam_parameters_at(control, sim.actuator)
    if backend.kind == "sim":
        full = scaled_beam(full, sim.first_mode_rad_s)
    return full if sim.unmodelled_dynamics else full.truncated(procedure.prior.n_modes)


@dataclass(frozen=True)
class OpenedTarget:
    """A real-time target and the rig around it (the generator at the summing junction and the
    recorder of injection, drive and response), for ``setmem-hil verify``."""

    target: object  # setmem_hil.drivers.real_time_target.RealTimeTarget
    rig: object  # setmem_hil.verify.target_service.LoopRig, or None (the target measures: its analyser)
    wait: object = time.sleep  # lets the target run for some seconds (an emulated loop: its own steps)


def open_target(target_procedure, procedure: Procedure, seed: int = 1) -> OpenedTarget:
    """The target of a verification procedure (:mod:`setmem_hil.io.target_file`) on the run's
    structure: ``"emulated"`` is the run's simulated structure (all its modes) in closed loop
    with the reference firmware's own C core (:mod:`setmem_hil.sim_backends.emulated_target`);
    ``"serial"`` the reference firmware on a board at ``port`` (any pyserial URL), measured by
    its own analyser."""
    from setmem_hil.drivers.real_time_target import RealTimeTarget, SerialLineChannel

    t = target_procedure.target
    if t.kind == "serial":
        return OpenedTarget(RealTimeTarget(SerialLineChannel(t.port, t.baudrate), f"target on {t.port}"), None)
    from setmem_hil.sim_backends.emulated_target import EmulatedClosedLoop, TargetEmulation

    structure = true_structure(procedure)
    if structure is None:
        raise ProcedureError(str(target_procedure.name), "[target] kind", "\"emulated\" needs a run on a simulated structure")
    e = t.emulation
    loop = EmulatedClosedLoop(structure, t.fs_hz, t.delay_samples,
                              TargetEmulation(e.extra_delay_samples, e.dac_gain, e.antialias_corner_hz, e.drop_link_after_lines, e.undamped,
                                              force_channel=e.force_channel),
                              noise_rms=e.noise_rms, seed=seed)
    target = RealTimeTarget(loop.channel(), f"emulated target ({t.fs_hz:g} Hz)")
    if t.measure == "analyser":  # the target injects and sums; the rig's own generator and recorder stay unused
        return OpenedTarget(target, None, lambda seconds: loop.run(max(1, int(round(seconds * t.fs_hz)))))
    return OpenedTarget(target, loop)
