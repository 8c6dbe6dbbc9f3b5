"""``kind = "instruments"`` with ``[backend.emulation]``: the real drivers against emulated instruments.

For each instrument a procedure names, an emulator of its model listens on the resource's
127.0.0.1 port (port 0: a free port, written back into the resource), backed by one
:class:`~setmem_hil.sim_backends.instrument_bench.EmulatedBench` (the 8-mode beam on a virtual
clock). The drivers then open the instruments exactly as on a real rig, through PyVISA
(pyvisa-py) and pymodbus, and share the bench's clock, so a campaign runs in seconds.

Which emulator: SCPI generator profiles whose model names the 33500B (or 33600A), a DG800 or a
Siglent SDG1000X/2000X, lock-in profiles for the SR830, SR860 or SR865A, and any Modbus profile (the emulated controller
implements the profile's own register map). The emulated response sensor measures displacement.
"""

from __future__ import annotations

import dataclasses
import re

from setmem_hil.drivers.instruments.instrument_set import (calibrate_scope_channels, channel_match_path, check_instruments,
                                                         open_instrument_experiment)
from setmem_hil.drivers.instruments.phasor_dwell import PhasorDwellExperiment
from setmem_hil.drivers.instruments.profile import LockInProfile, ModbusProfile, ScopeProfile, ScpiGeneratorProfile
from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import Procedure
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import BEAM_DAMPING_RATIO, BEAM_RESIDUE, beam_natural_frequencies, beam_parameters_at, scaled_beam
from setmem_hil.sim_backends.instrument_bench import BenchSettings, EmulatedBench
from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, InstrumentServer, LockInEmulator, SiglentGeneratorEmulator
from setmem_hil.sim_backends.modbus_controller_emulator import ModbusControllerEmulator
from setmem_hil.sim_backends.scope_emulators import KeysightScopeEmulator, RigolScopeEmulator

__all__ = ["open_emulated_instruments", "start_emulators", "emulator_model", "with_damping", "calibrate_emulated_channels"]

_SOCKET = re.compile(r"^TCPIP0?::(127\.0\.0\.1|localhost)::(\d+)::SOCKET$", re.IGNORECASE)
_MODBUS_TCP = re.compile(r"^tcp://(127\.0\.0\.1|localhost):(\d+)$")


def emulator_model(profile) -> str | None:
    """The emulator that answers for a profile's model (None: no emulator for it)."""
    if isinstance(profile, ModbusProfile):
        return "modbus"
    for pattern, model in ((r"335\d\d|33500|336\d\d", "33500B"), (r"DG8", "DG800"), (r"SR830", "SR830"), (r"SR860", "SR860"),
                           (r"SR865A", "SR865A"), (r"SDG2\d*0*X", "SDG2000X"), (r"SDG1\d*0*X", "SDG1000X"),
                           (r"DS1\d*Z", "DS1000Z"), (r"InfiniiVision", "InfiniiVision")):
        if re.search(pattern, profile.model, re.IGNORECASE):
            return model
    return None


EMULATED_LINK_TIMEOUT_S = 60.0
"""Reply timeout of the links to emulated instruments. An emulator answers within microseconds of
work, so only a loaded machine (a busy CI runner) could make a reply late; with the profiles'
timeouts (2-5 s) such a delay became a device fault, a retry and another noise realisation, and
the campaign's result depended on the machine's load (issue 46). The timeout and its retry are
tested by delaying a reply on purpose (:meth:`InstrumentServer.delay_replies`)."""


def start_emulators(procedure: Procedure, seed: int, tee: bool = False) -> tuple[Procedure, EmulatedBench, list]:
    """Start an emulator for each instrument; returns the procedure with the resources they
    listen on, the bench, and the servers (close them when done). ``tee``: the oscilloscope's
    force and response channels all wired to the generator's output (a channel match)."""
    source = procedure.source_path or procedure.name
    emulation = procedure.backend.emulation
    checked = check_instruments(procedure)
    backend = procedure.backend
    exciter, force = procedure.instruments[backend.exciter], procedure.instruments[backend.force]
    responses = [procedure.instruments[name] for name in backend.response_instruments()]  # control output first
    sensors = _sensor_channels(procedure)
    for where, quantity, _ in sensors[1:]:
        if quantity != "displacement":
            raise ProcedureError(source, f"{where} key 'quantity'", "the emulated response sensor measures displacement")
    outputs = _emulated_outputs(procedure)
    bench = EmulatedBench(outputs[0], BenchSettings(
        newton_per_volt=exciter.newton_per_volt, drive_gain_ratio=emulation.drive_gain_ratio,
        force_volt_per_unit=sensors[0][2], response_volt_per_unit=sensors[1][2],
        noise_v_per_rthz=(emulation.noise_v_per_rthz, emulation.noise_v_per_rthz), seed=seed,
        relock_s=emulation.relock_s, other_response_volt_per_unit=tuple(s[2] for s in sensors[2:]),
    ), other_outputs=tuple(outputs[1:]))
    lockin_of = dict(zip((r.name for r in responses), EmulatedBench.response_names(len(responses))))
    servers = []
    resources = {}
    try:
        for name, (settings, profile, role) in checked.items():
            model = emulator_model(profile)
            if model is None:
                raise ProcedureError(source, f"[instruments.{name}] key 'profile'", f"no emulator for a {profile.model}; "
                                     "emulation knows the 33500B, DG800, Siglent SDG1000X/2000X, SR830, SR860, SR865A, Rigol DS1000Z, Keysight "
                                     "InfiniiVision and Modbus register maps")
            if isinstance(profile, ModbusProfile):
                m = _MODBUS_TCP.match(settings.resource)
                if not m:
                    raise ProcedureError(source, f"[instruments.{name}] key 'resource'", f"emulation listens on tcp://127.0.0.1:PORT, found {settings.resource!r}")
                server = ModbusControllerEmulator(bench, profile, port=int(m.group(2))).start()
                resources[name] = f"tcp://127.0.0.1:{server.port}"
            else:
                m = _SOCKET.match(settings.resource)
                if not m:
                    raise ProcedureError(source, f"[instruments.{name}] key 'resource'", f"emulation listens on TCPIP::127.0.0.1::PORT::SOCKET, found {settings.resource!r}")
                if isinstance(profile, ScopeProfile):
                    emulator = _scope_emulator(bench, settings, model, seed, backend.control_output, tee)
                elif isinstance(profile, ScpiGeneratorProfile) and model.startswith("SDG"):
                    emulator = SiglentGeneratorEmulator(bench, model, channel=settings.channel)
                elif isinstance(profile, ScpiGeneratorProfile):
                    emulator = GeneratorEmulator(bench, model, channel=settings.channel)
                else:
                    assert isinstance(profile, LockInProfile)
                    emulator = LockInEmulator(bench, "force" if role == "force" else lockin_of[name], model)
                server = InstrumentServer(emulator, port=int(m.group(2)))
                resources[name] = server.resource
            servers.append(server)
    except BaseException:
        for server in servers:
            server.close()
        raise
    instruments = {n: dataclasses.replace(s, resource=resources.get(n, s.resource), timeout_s=EMULATED_LINK_TIMEOUT_S)
                   for n, s in procedure.instruments.items()}
    return dataclasses.replace(procedure, instruments=instruments), bench, servers


def _sensor_channels(procedure: Procedure) -> list[tuple[str, str, float]]:
    """``(where, quantity, volt_per_unit)`` of the force sensor, then every response sensor in
    measurement order (control output first): instruments, or one oscilloscope's channels."""
    backend = procedure.backend
    scope = procedure.instruments[backend.force]
    if scope.channel_roles:
        def one(ch: int, default: str) -> tuple[str, str, float]:
            sensor = scope.channel_sensors[ch]
            return f"[instruments.{scope.name}.channel.{ch}]", sensor.quantity or default, sensor.volt_per_unit

        return [one(scope.channel_roles["force"][0], "force")] + [one(c, "displacement") for c in scope.response_channels(backend.control_output)]
    every = [scope] + [procedure.instruments[name] for name in backend.response_instruments()]
    return [(f"[instruments.{i.name}]", i.quantity or ("force" if k == 0 else "displacement"), i.volt_per_unit) for k, i in enumerate(every)]


def _sensor_positions(procedure: Procedure) -> list[float]:
    """``[backend.emulation] sensors`` (file order) in measurement order (control output first)."""
    backend, emulation = procedure.backend, procedure.backend.emulation
    scope = procedure.instruments[backend.force]
    if scope.channel_roles:
        where = dict(zip(scope.channel_roles["response"], emulation.sensors))
        return [where[c] for c in scope.response_channels(backend.control_output)]
    where = dict(zip(backend.responses or (backend.response,), emulation.sensors))
    return [where[name] for name in backend.response_instruments()]


def _scope_emulator(bench: EmulatedBench, settings, model: str, seed: int, control_output: int, tee: bool = False):
    """The scope's channels wired as the procedure says: force, the responses (the bench's
    ``response``, ``response2``... in measurement order), the generator's sync on trigger_channel;
    with ``tee`` the force and response channels all on the generator's output instead."""
    roles = settings.channel_roles
    names = EmulatedBench.response_names(len(roles["response"]))
    wiring = {roles["force"][0]: "force", **dict(zip(settings.response_channels(control_output), names))}
    volt_per_unit = {"force": settings.channel_sensors[roles["force"][0]].volt_per_unit}
    volt_per_unit.update({name: settings.channel_sensors[c].volt_per_unit for c, name in wiring.items() if name != "force"})
    if tee:
        wiring = {c: "drive" for c in wiring}
    if settings.trigger_channel is not None:
        wiring[settings.trigger_channel] = "sync"
    if model == "DS1000Z":
        return RigolScopeEmulator(bench, wiring, volt_per_unit, seed=seed)
    return KeysightScopeEmulator(bench, wiring, volt_per_unit, ext_sync=settings.trigger_channel is None, seed=seed)


def _emulated_outputs(procedure: Procedure) -> list[ModalParameters]:
    """The emulated beam as each response sensor sees it, control output first: every mode
    at the emulation's damping, residues ``phi_i(actuator) phi_i(sensor)`` (issue 25; the
    thesis's ``b0 = 4`` for a sensor at the tip with the force at the tip)."""
    emulation = procedure.backend.emulation
    damping = emulation.damping if emulation.damping is not None else BEAM_DAMPING_RATIO
    outputs = []
    for x in _sensor_positions(procedure):
        if x == 1.0 and emulation.actuator == 1.0:  # the thesis's beam exactly (b0 = 4 for every mode)
            residues = BEAM_RESIDUE
        else:
            residues = beam_parameters_at(x, emulation.actuator).values[:, 3]
        outputs.append(scaled_beam(ModalParameters.from_modal(beam_natural_frequencies(), damping, residues, 0.0), emulation.first_mode_rad_s))
    return outputs


def open_emulated_instruments(procedure: Procedure, seed: int, extra_bound=None) -> PhasorDwellExperiment:
    """Start the emulators for the procedure's instruments and open the experiment on them. An
    oscilloscope whose ``channel_match`` file does not exist is matched first on the emulated
    tee (what ``calibrate-channels`` does; a real rig refuses to run without the file)."""
    match = None
    scope = procedure.instruments.get(procedure.backend.force)
    path = None if scope is None else channel_match_path(procedure, scope)
    if path is not None and not path.exists():
        match = calibrate_emulated_channels(procedure, seed)
    wired, bench, servers = start_emulators(procedure, seed)
    experiment = open_instrument_experiment(wired, clock=bench.clock, extra_bound=extra_bound, channel_match=match,
                                            on_measurement=lambda index: bench.reseed((index,)), owned=tuple(servers))
    experiment.bench = bench  # tests read the emulated truth and the peak force through it
    return experiment


def calibrate_emulated_channels(procedure: Procedure, seed: int, progress=lambda done, total: None):
    """The channel match of the procedure's emulated oscilloscope (its channels on a tee)."""
    wired, bench, servers = start_emulators(procedure, seed, tee=True)
    return calibrate_scope_channels(wired, clock=bench.clock, owned=tuple(servers), progress=progress)


def with_damping(procedure: Procedure, damping: float, calibration: float | None = None) -> Procedure:
    """The emulated procedure with every mode at ``damping``; the response sensor's sensitivity
    scaled by ``damping / 0.01`` so that the taller resonance still fits the lock-in's full scale
    (what a technician does when the lock-in overloads); ``calibration`` replaces both sensors'
    calibration uncertainty when given."""
    backend = procedure.backend
    if backend.emulation is None:
        raise ProcedureError(procedure.source_path or procedure.name, "[backend.emulation]", "with_damping needs an emulated procedure")
    instruments = dict(procedure.instruments)
    for role, name in (("force", backend.force), *(("response", n) for n in backend.response_instruments())):
        settings = instruments[name]
        changes = {} if calibration is None else {"calibration_uncertainty": calibration}
        if role == "response":
            changes["volt_per_unit"] = settings.volt_per_unit * damping / BEAM_DAMPING_RATIO
        instruments[settings.name] = dataclasses.replace(settings, **changes)
    emulation = dataclasses.replace(backend.emulation, damping=damping)
    return dataclasses.replace(procedure, instruments=instruments, backend=dataclasses.replace(backend, emulation=emulation))
