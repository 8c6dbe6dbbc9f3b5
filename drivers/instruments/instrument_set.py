"""The instruments a procedure names: profiles checked, instruments opened, identities probed.

``[backend] kind = "instruments"`` names three ``[instruments.<name>]`` tables: the exciter (a
SCPI generator or a Modbus controller), and the force and response lock-ins. This module

* :func:`check_instruments`: loads every profile and checks it fits its role (``run --check``,
  ``probe`` and the run all start here; nothing is opened);
* :func:`probe_instruments`: connects to each instrument, checks its identity, reads its status
  and error queue, switches the exciter's output *off* (read back: a run killed with the output
  on may have left it so) and never switches an output on (``setmem-hil probe``);
* :func:`open_instrument_experiment`: opens everything, checks every identity *before* any
  output is touched, forces the exciter's output off during its init, and returns the
  :class:`~setmem_hil.drivers.instruments.phasor_dwell.PhasorDwellExperiment`.

The clock is the wall clock unless the caller (the emulation in :mod:`setmem_hil.loopback`)
passes the emulated bench's.
"""

from __future__ import annotations

import datetime
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from setmem_hil.drivers.clock import Clock, WallClock
from setmem_hil.drivers.instruments.lockin import LockIn
from setmem_hil.drivers.instruments.modbus_generator import ModbusGenerator, parse_modbus_resource
from setmem_hil.drivers.instruments.phasor_dwell import DriveChannel, PhasorDwellExperiment, PhasorDwellSettings, SensorChannel
from setmem_hil.drivers.instruments.profile import (DaqProfile, DbcProfile, LockInProfile, ModbusProfile, Profile, ScopeProfile, ScpiGeneratorProfile,
                                                    load_profile, profile_warnings)
from setmem_hil.drivers.instruments.scpi_generator import ScpiGenerator
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceError, DeviceIdentityError, ProcedureError
from setmem_hil.io.channel_match_file import read_channel_match
from setmem_hil.io.procedure import InstrumentSettings, Procedure
from setmem_hil.model.channel_match import ChannelMatch

__all__ = ["check_instruments", "instrument_warnings", "open_instrument", "probe_instruments", "ProbeResult", "open_instrument_experiment"]

log = logging.getLogger(__name__)

_ROLE_KINDS = {"exciter": ("scpi-generator", "modbus", "dbc"), "force": ("scpi-lockin", "nidaqmx", "scpi-scope"),
               "response": ("scpi-lockin", "nidaqmx", "scpi-scope")}
SYNC_TRIGGER_LEVEL_V = 1.0  # the generator's sync output: a logic level (3.3 or 5 V, half into 50 ohm)


def _one_of(kinds: tuple[str, ...]) -> str:
    return kinds[0] if len(kinds) == 1 else ", ".join(kinds[:-1]) + " or " + kinds[-1]


def _source(procedure: Procedure) -> str:
    return procedure.source_path or procedure.name


def check_instruments(procedure: Procedure) -> dict[str, tuple[InstrumentSettings, Profile, str]]:
    """``{name: (settings, profile, role)}`` for the backend's three roles; ProcedureError otherwise."""
    backend = procedure.backend
    found = {}
    named = [("exciter", backend.exciter), ("force", backend.force)] + [("response", n) for n in backend.response_instruments()]
    for role, name in named:
        settings = procedure.instruments[name]
        where = f"[instruments.{name}] key 'profile'"
        try:
            profile = load_profile(settings.profile, relative_to=procedure.source_path or None)
        except ProcedureError as exc:
            if exc.source == settings.profile:  # unknown shipped name: say where it was asked for
                raise ProcedureError(_source(procedure), where, exc.problem) from None
            raise
        if profile.kind not in _ROLE_KINDS[role]:
            raise ProcedureError(_source(procedure), where, f"profile {settings.profile!r} is a {profile.kind} ({profile.model}); "
                                 f"the {role} needs a {_one_of(_ROLE_KINDS[role])} profile")
        if role == "exciter" and settings.channel not in profile.channels:
            raise ProcedureError(_source(procedure), f"[instruments.{name}] key 'channel'",
                                 f"channel {settings.channel} does not exist on a {profile.model} (channels {list(profile.channels)})")
        if isinstance(profile, (ModbusProfile, DbcProfile)):
            from setmem_hil.drivers.instruments.dbc_generator import parse_can_resource

            try:
                (parse_modbus_resource if isinstance(profile, ModbusProfile) else parse_can_resource)(settings.resource)
            except ValueError as exc:
                raise ProcedureError(_source(procedure), f"[instruments.{name}] key 'resource'", str(exc)) from None
        if isinstance(profile, ScopeProfile):
            _check_scope(procedure, settings, profile)
        _check_daq_channel(procedure, settings, profile, role)
        missing = missing_driver_package(settings, profile)
        if missing:
            raise ProcedureError(_source(procedure), where, missing)
        if name in found:  # one oscilloscope in the force and the response roles
            role = f"{found[name][2]}+{role}"
        found[name] = (settings, profile, role)
    kinds = {found[name][1].kind for name in (backend.force, *backend.response_instruments())}
    if len(kinds) > 1:
        raise ProcedureError(_source(procedure), "[backend] key 'response'", "force and response must both be lock-ins or both "
                             f"DAQ channels, found {' and '.join(sorted(kinds))}")
    refusal = _multisine_refusal(procedure, found) if procedure.dwell_signal == "multisine" else None
    if refusal:
        raise ProcedureError(_source(procedure), "[dwell] key 'signal'", refusal)
    return found


# the Python packages each kind of profile is driven through: (module, pip requirement)
_VISA = (("pyvisa", "setmem-hil[instruments]"),)
DRIVER_PACKAGES = {
    "scpi-generator": _VISA, "scpi-lockin": _VISA, "scpi-scope": _VISA,
    "dbc": (("can", "python-can"), ("cantools", "setmem-hil[can]")),
    "nidaqmx": (("nidaqmx", "setmem-hil[daq]"),),
    "modbus": (("pymodbus", "pymodbus"),),
}


def missing_driver_package(settings: InstrumentSettings, profile: Profile) -> str | None:
    """What a run would miss to drive this instrument (a package not installed), said with the
    command that installs it; None when everything is there. ``run --check`` reports it before
    a run would stop on it at the first connection (issue 40)."""
    import importlib.util

    needed = list(DRIVER_PACKAGES.get(profile.kind, ()))
    if profile.kind.startswith("scpi-") and getattr(settings, "visa_library", "@py") == "@py":
        needed.append(("pyvisa_py", "setmem-hil[instruments]"))  # PyVISA's pure-Python backend
    if isinstance(profile, DbcProfile) and profile.canopen_identity is not None:
        needed.append(("canopen", "setmem-hil[can]"))
    for module, requirement in needed:
        if importlib.util.find_spec(module) is None:
            return (f"profile {settings.profile!r} ({profile.model}) is driven through the Python package {module!r}, which is not "
                    f"installed; install it with: pip install '{requirement}'")
    return None


def _check_scope(procedure: Procedure, settings: InstrumentSettings, profile: ScopeProfile) -> None:
    """The oscilloscope's channels exist on its model; the procedure parser checked the rest."""
    if not settings.channel_roles:
        raise ProcedureError(_source(procedure), f"[instruments.{settings.name}] key 'channels'", "an oscilloscope needs "
                             "channels = { force = N, response = [N, ...] }")
    used = [*settings.channel_roles["force"], *settings.channel_roles["response"], *([settings.trigger_channel] if settings.trigger_channel else [])]
    missing = [c for c in used if c not in profile.channels]
    if missing:
        raise ProcedureError(_source(procedure), f"[instruments.{settings.name}] key 'channels'",
                             f"channel {missing[0]} does not exist on a {profile.model} (channels {list(profile.channels)})")


def _multisine_refusal(procedure: Procedure, found: dict) -> str | None:
    """Why this instrument rig cannot play multisine records, naming the instrument (issue 26);
    None when it can: sampled sensors (an oscilloscope or a DAQ) and a generator profile with an
    ``[arbitrary]`` table."""
    backend = procedure.backend
    settings, profile, _ = found[backend.force]
    if profile.kind == "scpi-lockin":
        return (f"multisine needs sampled sensors (an oscilloscope or a DAQ) and an arbitrary-waveform generator; "
                f"[instruments.{settings.name}] is a lock-in ({profile.model}), which demodulates one frequency")
    exciter = found[backend.exciter][1]
    if not isinstance(exciter, ScpiGeneratorProfile) or exciter.arbitrary is None:
        return (f"multisine needs an exciter that plays arbitrary waveforms; [instruments.{backend.exciter}] ({exciter.model}) "
                "has no [arbitrary] table in its profile (the shipped 33500B, DG800 and SDG profiles have one)")
    return None


def instrument_warnings(procedure: Procedure) -> list[str]:
    """What ``run --check`` warns about in the instruments' profiles (see :func:`profile_warnings`);
    an oscilloscope's channel match that is missing, malformed or too old is an error there too."""
    checked = check_instruments(procedure)
    for settings, profile, _ in checked.values():
        path = channel_match_path(procedure, settings)
        if isinstance(profile, ScopeProfile) and path is not None and (procedure.backend.emulation is None or path.exists()):
            _channel_match(procedure, settings)  # (an emulated rig measures a missing one on its emulated tee)
    return [f"[instruments.{name}] {warning}" for name, (_, profile, _) in checked.items() for warning in profile_warnings(profile)]


def open_instrument(settings: InstrumentSettings, profile: Profile, clock: Clock | None = None):
    """Open one instrument (no command sent yet): a ScpiGenerator, ModbusGenerator, LockIn or
    ScpiScope (which waits for its records on ``clock``, the wall clock by default)."""
    if isinstance(profile, ModbusProfile):
        return ModbusGenerator(settings.name, profile, settings.resource)
    if isinstance(profile, DbcProfile):
        from setmem_hil.drivers.instruments.dbc_generator import DbcGenerator

        return DbcGenerator(settings.name, profile, settings.resource)
    link = VisaLink(settings.name, settings.resource, visa_library=settings.visa_library,
                    termination=profile.termination, timeout_s=settings.timeout_s or profile.timeout_s)
    try:
        if isinstance(profile, ScpiGeneratorProfile):
            return ScpiGenerator(settings.name, profile, link, channel=settings.channel, load_ohms=settings.load_ohms)
        if isinstance(profile, ScopeProfile):
            from setmem_hil.drivers.instruments.scpi_scope import ScpiScope

            channels = (*settings.channel_roles["force"], *settings.channel_roles["response"])
            return ScpiScope(settings.name, profile, link, channels, *scope_trigger(settings, profile), clock or WallClock())
        assert isinstance(profile, LockInProfile)
        return LockIn(settings.name, profile, link)
    except BaseException:
        link.close()
        raise


@dataclass(frozen=True)
class ProbeResult:
    name: str
    role: str
    model: str
    resource: str
    ok: bool
    answer: str  # the identity reply, or the error


def probe_instruments(procedure: Procedure) -> list[ProbeResult]:
    """Connect to each instrument, check identity and error queue; no output is switched on
    (queries only, and the exciter's output switched off once its identity is confirmed)."""
    results = []
    for name, (settings, profile, role) in check_instruments(procedure).items():
        inst = None
        if isinstance(profile, DaqProfile):  # NI-DAQmx has no identity query of a channel
            results.append(ProbeResult(name, role, profile.model, settings.resource, True, "NI-DAQmx channel (not queried)"))
            continue
        try:
            inst = open_instrument(settings, profile)
            answer = inst.check_identity()
            if isinstance(inst, LockIn):
                answer += f"; reference {inst.reference_frequency_hz():.6g} Hz"
            elif role == "exciter" and isinstance(inst, (ScpiGenerator, ModbusGenerator)):
                inst.set_output(False)  # the one command probe sends: safe always, and a killed run may have left it on
                answer += "; output switched off (read back)"
            results.append(ProbeResult(name, role, profile.model, settings.resource, True, answer))
        except DeviceError as exc:
            results.append(ProbeResult(name, role, profile.model, settings.resource, False, str(exc)))
        finally:
            if inst is not None:
                inst.close()
    return results


def daq_input_setup(settings: InstrumentSettings, default_quantity: str):
    """How an NI-DAQmx channel is created (its sensor's quantity, IEPE current, coupling)."""
    from setmem_hil.drivers.instruments.nidaq_sensor import DaqInputSetup

    return DaqInputSetup(settings.quantity or default_quantity, settings.iepe_current_a, effective_coupling(settings))


def effective_coupling(settings: InstrumentSettings) -> str | None:
    """The coupling a DAQ channel gets: as set, else AC for an IEPE sensor (its output sits on a
    bias of several volts), else the device's default."""
    return settings.coupling or ("AC" if settings.iepe_current_a else None)


def ac_corner(settings: InstrumentSettings, daq: DaqProfile) -> float:
    """The AC-coupling corner (Hz) of a DAQ channel, 0 for a DC-coupled one."""
    return daq.ac_coupling_corner_hz if effective_coupling(settings) == "AC" else 0.0


def _check_daq_channel(procedure: Procedure, settings: InstrumentSettings, profile: Profile, role: str) -> None:
    """``iepe_current_a`` and ``coupling`` belong to NI-DAQmx channels; IEPE needs a force or
    acceleration sensor (nidaqmx's IEPE channel types) and AC coupling (the sensor's bias)."""
    where = f"[instruments.{settings.name}]"
    if not isinstance(profile, DaqProfile):
        given = [k for k in ("iepe_current_a", "coupling") if (settings.iepe_current_a if k == "iepe_current_a" else settings.coupling)]
        if given:
            raise ProcedureError(_source(procedure), f"{where} key '{given[0]}'", f"only NI-DAQmx channels have it; {settings.name!r} is a {profile.model}")
        return
    if settings.iepe_current_a:
        quantity = settings.quantity or ("force" if role == "force" else "displacement")
        if quantity not in ("force", "acceleration"):
            raise ProcedureError(_source(procedure), f"{where} key 'iepe_current_a'",
                                 f"IEPE excitation is made for force and acceleration sensors (nidaqmx's IEPE force and accelerometer "
                                 f"channels); this sensor's quantity is {quantity!r}")
        if settings.coupling == "DC":
            raise ProcedureError(_source(procedure), f"{where} key 'coupling'",
                                 "an IEPE sensor's output sits on a bias of several volts: use coupling = \"AC\" (the default with IEPE)")


def open_daq_experiment(procedure: Procedure, checked: dict, *, extra_bound=None, nidaqmx_module=None):
    """Source + NI-DAQ: the sine dwell on a sampled rig (:mod:`.sampled_rig`)."""
    from setmem_hil.drivers.instruments.nidaq_sensor import NidaqSensor
    from setmem_hil.drivers.instruments.sampled_rig import DaqChannel, SampledInstrumentRig
    from setmem_hil.drivers.instruments.sampled_dwell import SampledDwellExperiment
    from setmem_hil.drivers.sine_dwell import DwellSettings

    backend = procedure.backend
    exciter, force = procedure.instruments[backend.exciter], procedure.instruments[backend.force]
    responses = [procedure.instruments[name] for name in backend.response_instruments()]  # control output first (issue 25)
    daq: DaqProfile = checked[force.name][1]
    source = open_instrument(exciter, checked[exciter.name][1])
    try:
        identity = source.check_identity()
        source.initialise()
        sensor = NidaqSensor(force.resource, [r.resource for r in responses], force.volt_per_unit, [r.volt_per_unit for r in responses],
                             range_v=daq.range_v, terminal=daq.terminal, nidaqmx_module=nidaqmx_module,
                             setups=[daq_input_setup(s, "force" if s is force else "displacement") for s in (force, *responses)])
        limits = procedure.safety
        # the sensor refuses a channel at its rails in volts; the dwell's own check then must not
        # flag a channel with a larger full scale than another's: the largest full scale
        response_range = max(daq.range_v / r.volt_per_unit for r in responses)
        rig = SampledInstrumentRig(source, sensor, exciter.newton_per_volt, exciter.max_drive_v or math.inf, limits.max_amplitude_n,
                                   force_range_n=daq.range_v / force.volt_per_unit, response_range=response_range,
                                   sample_rate_hz=1000.0, force=DaqChannel(force.calibration_uncertainty, "force", ac_corner(force, daq)),
                                   responses=tuple(DaqChannel(r.calibration_uncertainty, r.quantity or "displacement", ac_corner(r, daq))
                                                   for r in responses))
    except BaseException:
        source.close()
        raise
    settings = DwellSettings(amplitude_n=min(1.0, procedure.safety.max_amplitude_n))
    return SampledDwellExperiment(rig, procedure.safety, settings, model=procedure.prior.initial_bounds(), extra_bound=extra_bound,
                                  identities={source.name: identity})


def _open_identified(checked: dict, clock: Clock, owned: tuple) -> tuple[dict, dict[str, str]]:
    """Open every checked instrument (``{name: driver}``, in the order checked: the exciter first),
    check every identity before any init command (a wrong instrument never sees one), then
    initialise them (the exciter's output forced off before anything else). On any failure
    everything opened, and ``owned``, is closed."""
    opened = {}
    try:
        for name, (settings, profile, role) in checked.items():
            opened[name] = open_instrument(settings, profile, clock)
        identities = {inst.name: inst.check_identity() for inst in opened.values()}
        for inst in opened.values():
            inst.initialise()
    except BaseException:
        for inst in opened.values():
            inst.close()
        for thing in owned:
            thing.close()
        raise
    return opened, identities


def open_instrument_experiment(procedure: Procedure, *, clock: Clock | None = None, extra_bound: Callable[[float], float] | None = None,
                               on_measurement: Callable[[int], None] | None = None, owned: tuple = (),
                               channel_match: ChannelMatch | None = None) -> PhasorDwellExperiment:
    """Open, identify (all three before any output is touched) and initialise the instruments.
    ``channel_match``: an oscilloscope's match given directly instead of its file."""
    checked = check_instruments(procedure)
    if isinstance(checked[procedure.backend.force][1], DaqProfile):
        return open_daq_experiment(procedure, checked, extra_bound=extra_bound)
    if isinstance(checked[procedure.backend.force][1], ScopeProfile):
        return open_scope_experiment(procedure, checked, clock=clock or WallClock(), extra_bound=extra_bound, owned=owned,
                                     channel_match=channel_match)
    opened, identities = _open_identified(checked, clock or WallClock(), owned)
    backend = procedure.backend
    exciter = procedure.instruments[backend.exciter]
    force = procedure.instruments[backend.force]
    responses = [procedure.instruments[name] for name in backend.response_instruments()]  # control output first (issue 25)
    channels = [SensorChannel(r.volt_per_unit, r.calibration_uncertainty, r.quantity or "displacement") for r in responses]
    return PhasorDwellExperiment(
        source=opened[exciter.name], force=opened[force.name], response=opened[responses[0].name],
        force_sensor=SensorChannel(force.volt_per_unit, force.calibration_uncertainty, force.quantity or "force"),
        response_sensor=channels[0],
        drive=DriveChannel(exciter.newton_per_volt, exciter.max_drive_v if exciter.max_drive_v is not None else math.inf),
        limits=procedure.safety,
        clock=clock or WallClock(),
        settings=PhasorDwellSettings(amplitude_n=min(1.0, procedure.safety.max_amplitude_n)),
        extra_bound=extra_bound,
        max_response=procedure.safety.max_response,
        on_measurement=on_measurement,
        owned=owned,
        identities=identities,
        model=procedure.prior.initial_bounds(),
        other_responses=tuple(opened[r.name] for r in responses[1:]),
        other_sensors=tuple(channels[1:]),
    )


def scope_trigger(settings: InstrumentSettings, profile: ScopeProfile) -> tuple[str, float]:
    """Where the oscilloscope triggers: ``trigger_channel`` (the generator's sync), else its EXT
    input where it has one (the sync wired there), else the force channel's rising zero crossing."""
    if settings.trigger_channel is not None:
        return f"ch{settings.trigger_channel}", SYNC_TRIGGER_LEVEL_V
    if profile.has_ext_trigger:
        return "ext", SYNC_TRIGGER_LEVEL_V
    return f"ch{settings.channel_roles['force'][0]}", 0.0


def open_scope_experiment(procedure: Procedure, checked: dict, *, clock: Clock, extra_bound=None, owned: tuple = (),
                          channel_match: ChannelMatch | None = None):
    """Generator + oscilloscope: the sine dwell on one scope's channels (:mod:`.scope_rig`); both
    identities are checked before either instrument is initialised (the generator's output off
    first), and the channel match (``channel_match``, else the procedure's file) against the scope's."""
    from setmem_hil.drivers.instruments.scope_rig import ScopeChannel, ScopeDwellExperiment, ScopeRig
    from setmem_hil.drivers.sine_dwell import DwellSettings

    backend = procedure.backend
    exciter, scope_settings = procedure.instruments[backend.exciter], procedure.instruments[backend.force]

    def channel(number: int, default_quantity: str) -> ScopeChannel:
        sensor = scope_settings.channel_sensors[number]
        return ScopeChannel(number, sensor.volt_per_unit, sensor.calibration_uncertainty, sensor.quantity or default_quantity)

    force = channel(scope_settings.channel_roles["force"][0], "force")
    responses = tuple(channel(c, "displacement") for c in scope_settings.response_channels(backend.control_output))
    try:
        match = channel_match if channel_match is not None else _channel_match(procedure, scope_settings)
    except BaseException:
        for thing in owned:
            thing.close()
        raise
    opened, identities = _open_identified(checked, clock, owned)
    source, scope = opened[exciter.name], opened[scope_settings.name]
    rig = ScopeRig(source, scope, force, responses, exciter.newton_per_volt, exciter.max_drive_v or math.inf,
                   procedure.safety.max_amplitude_n, clock, owned=owned, match=match)
    try:
        if match is not None:
            _check_match_identity(match, identities[scope.name], scope_settings)
            identities[f"{scope.name} channel match"] = (f"{scope_settings.channel_match if channel_match is None else 'measured for this run'}, "
                                                         f"{match.utc}, {len(match.gains)} gains within "
                                                         f"{max(g.bound for g in match.gains):.2%}")
        rig.sensor.measure_noise()  # the output is off: the sensors at rest
    except BaseException:
        rig.close()
        raise
    settings = DwellSettings(amplitude_n=min(1.0, procedure.safety.max_amplitude_n))
    return ScopeDwellExperiment(rig, procedure.safety, settings, model=procedure.prior.initial_bounds(), extra_bound=extra_bound,
                                identities=identities)


MATCH_MAX_AGE_H = 24.0  # a channel match older than this is refused: the gains drift with temperature (measure it each day)


def channel_match_path(procedure: Procedure, settings: InstrumentSettings) -> Path | None:
    """Where the oscilloscope's ``channel_match`` file is (relative to the procedure file), or None."""
    if settings.channel_match is None:
        return None
    base = Path(procedure.source_path).parent if procedure.source_path else Path.cwd()
    return base / settings.channel_match


def _channel_match(procedure: Procedure, settings: InstrumentSettings):
    """The procedure's channel match, read and checked for age (ProcedureError naming the key)."""
    path = channel_match_path(procedure, settings)
    if path is None:
        return None
    where = f"[instruments.{settings.name}] key 'channel_match'"
    if not path.exists():
        raise ProcedureError(_source(procedure), where, f"{path} does not exist: wire the generator to every channel through a tee "
                             "and run setmem-hil calibrate-channels first (docs/technician-guide.md)")
    match = read_channel_match(path)
    try:
        measured = datetime.datetime.fromisoformat(match.utc)
    except ValueError:
        raise ProcedureError(str(path), "key 'utc'", f"not an ISO 8601 time: {match.utc!r}") from None
    age_h = (datetime.datetime.now(datetime.timezone.utc) - measured).total_seconds() / 3600.0
    if not -1.0 < age_h <= MATCH_MAX_AGE_H:
        raise ProcedureError(_source(procedure), where, f"{path} was measured {age_h:.0f} h ago; a channel match holds for "
                             f"{MATCH_MAX_AGE_H:.0f} h (the gains drift): run setmem-hil calibrate-channels again")
    return match


def _check_match_identity(match, identity: str, settings: InstrumentSettings) -> None:
    """The match was measured on this oscilloscope (maker, model and serial number)."""
    if [f.strip() for f in match.identity.split(",")[:3]] != [f.strip() for f in identity.split(",")[:3]]:
        raise DeviceIdentityError(f"{settings.name}: the channel match {settings.channel_match} was measured on "
                                  f"{match.identity!r}, but this oscilloscope is {identity!r}: run setmem-hil calibrate-channels with it")


def calibrate_scope_channels(procedure: Procedure, *, clock: Clock | None = None, owned: tuple = (),
                             progress: Callable[[int, int], None] = lambda done, total: None):
    """Open the generator and the oscilloscope (identities first, the output off) and measure
    the scope's channel match (:mod:`.scope_channel_match`) against its force channel, the
    generator's output wired to every channel used through a tee. Closes both."""
    from setmem_hil.drivers.instruments.scope_channel_match import measure_channel_match

    checked = check_instruments(procedure)
    backend = procedure.backend
    scope_settings = procedure.instruments[backend.force]
    if not isinstance(checked[backend.force][1], ScopeProfile):
        raise ProcedureError(_source(procedure), "[backend] key 'force'", "calibrate-channels needs an oscilloscope in the force role "
                             f"([instruments.{backend.force}] is a {checked[backend.force][1].kind})")
    exciter = procedure.instruments[backend.exciter]
    force_channel = scope_settings.channel_roles["force"][0]
    force_peak_v = procedure.safety.max_amplitude_n * scope_settings.channel_sensors[force_channel].volt_per_unit
    opened, _ = _open_identified(checked, clock or WallClock(), owned)
    try:
        return measure_channel_match(opened[exciter.name], opened[scope_settings.name], force_channel,
                                     exciter.max_drive_v if exciter.max_drive_v is not None else math.inf, force_peak_v, progress)
    finally:
        for inst in opened.values():
            inst.close()
        for thing in owned:
            thing.close()
