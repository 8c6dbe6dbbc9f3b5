"""Procedure files (``procedures/*.toml``): loading and validation.

A procedure file describes one campaign (thesis chapter 5 loop on one rig): the backend and
its transport, the safety limits, the prior (``[[mode]]`` tables as in PRIOR.toml, section
3.2.2 / 6.1), the noise model of simulated backends (section 6.2), the initial frequencies, the
goal (``mu-bar <= mu_target``, eq. 5.1) and experiment budget, the input-design settings
(section 5.2, 6.3.2) and the control weights W1, W2 (eq. 6.1, 6.13).

Every key is described once, in :data:`SCHEMA` (table, key, type, unit, default, meaning); the
validator, the unknown-key messages and ``docs/procedures.md`` all follow it. Every problem
raises :class:`setmem_hil.errors.ProcedureError` naming the file, the table and the key::

    procedures/x.toml: [[mode]] 2: omega_min 7.3 > omega_max 5.4
    procedures/x.toml: [safety]: max_amplitude_n -1 must be > 0

Example
-------
>>> p = parse_procedure_text('''
... name = "tiny"
... [[mode]]
... omega_min = 0.9
... omega_max = 1.1
... zeta_max = 0.5
... b1 = 0
... [initial]
... omega_rad_s = [0.8, 1.2]
... ''', "tiny.toml")
>>> p.prior.modes[0].omega_max, p.initial_omegas_rad_s
(1.1, (0.8, 1.2))
"""

from __future__ import annotations

import difflib
import os
from dataclasses import replace
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from setmem_hil.errors import InputFormatError, ProcedureError
from setmem_hil.model.prior import ModePrior, Prior, parse_mode_table, parse_toml_text
from setmem_hil.io.procedure import (
    BACKENDS,
    RANKINGS,
    LOOPBACK_BACKENDS,
    DWELL_SIGNALS,
    MULTISINE_BACKENDS,
    SENSOR_QUANTITIES,
    UNMODELLED_BOUNDS,
    ChannelSensor,
    EmulationSettings,
    InstrumentSettings,
    NOISE_PROFILES,
    STRATEGIES,
    DESIGN_METHODS,
    BackendSettings,
    Goal,
    InputDesignSettings,
    Procedure,
    SafetyLimits,
    SimulationSettings,
)
from setmem_hil.io.procedure_writer import format_procedure  # noqa: F401  (re-exported: load and write side by side)
from setmem_hil.io.toml_table import REQUIRED, CheckedTable, KeySpec
from setmem_hil.io.toml_table import describe_value as _fmt
from setmem_hil.io.toml_table import type_name as _type_name
from setmem_hil.io.fault_kinds import CAN_FAULT_KINDS, FAULT_KINDS, MODBUS_FAULT_KINDS, TRANSPORT_FAULT_KINDS
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

__all__ = ["load_procedure", "parse_procedure_text", "format_procedure", "parse_procedure_mapping", "KeySpec", "SCHEMA", "FAULT_KINDS"]

# Fault kinds of the fake devices: setmem_hil.io.fault_kinds (one source of truth, part of the schema).
SEED_MAX = 2**63 - 1


_S, _SIM, _G, _ID = SafetyLimits(), SimulationSettings(), Goal(), InputDesignSettings()
_W = THESIS_WEIGHTS
_REQUIRED = REQUIRED

SCHEMA: tuple[KeySpec, ...] = (
    # top level
    KeySpec("", "name", "string", "", "file name stem", "Name of the procedure; used in the default output directory and stored in the journal."),
    KeySpec("", "description", "string", "", "\"\"", "Free text shown in the report."),
    KeySpec("", "seed", "integer", "", 1, "Random seed of the run (simulated noise, fault draws, random strategies); stored in the journal.", ge=0, le=SEED_MAX),
    KeySpec("", "backend", "table", "", "", "Where the measurements come from."),
    KeySpec("", "safety", "table", "", "", "Limits enforced by the drivers before any command is sent."),
    KeySpec("", "mode", "tables", "", _REQUIRED, "The prior: one [[mode]] table per modelled mode, in ascending frequency (same keys as PRIOR.toml)."),
    KeySpec("", "identification", "table", "", "", "Settings of the set-membership identification (section 3.2.3)."),
    KeySpec("", "initial", "table", "", _REQUIRED, "The initial experiment design."),
    KeySpec("", "goal", "table", "", "", "When the campaign stops."),
    KeySpec("", "input_design", "table", "", "", "How the next frequency is chosen (chapter 5)."),
    KeySpec("", "weights", "table", "", "", "Control-design weights W1 (unmodelled dynamics bound) and W2 (performance)."),
    KeySpec("", "design", "table", "", "", "How each iteration's compensator is designed."),
    KeySpec("", "discrepancy", "table", "", "", "Model-discrepancy checks."),
    KeySpec("", "dwell", "table", "", "", "How each measurement excites the structure."),
    KeySpec("", "instruments", "instrument-tables", "", "{}", "The real instruments, one [instruments.<name>] table each (kind = \"instruments\"); the names are what [backend] exciter, force and response refer to."),
    # [backend]
    KeySpec("backend", "kind", "choice", "", "sim", "Backend: the frequency-domain simulated beam or a fake device behind a loopback transport.", choices=BACKENDS),
    KeySpec("backend", "simulation", "table", "", "", "The simulated structure (behind every backend, including the fake devices)."),
    KeySpec("backend", "transport", "table", "", "{}", "Options of the loopback transport (timeouts, retries, CAN channel, Modbus framing...); the keys depend on kind, see below. Not allowed with kind = \"sim\"."),
    KeySpec("backend", "faults", "table", "", "", "Fault injection of the fake devices (issue 8). Not allowed with kind = \"sim\"."),
    KeySpec("backend", "exciter", "string", "", "required with kind = \"instruments\"", "The [instruments.<name>] that drives the shaker (a generator or a Modbus controller)."),
    KeySpec("backend", "force", "string", "", "required with kind = \"instruments\"", "The [instruments.<name>] lock-in reading the force sensor."),
    KeySpec("backend", "response", "names", "", "required with kind = \"instruments\"", "The [instruments.<name>] reading the response sensor (a lock-in or a DAQ channel); an array of names for several response sensors (lock-ins or DAQ channels, issue 25): every dwell reads all of them, shared poles."),
    KeySpec("backend", "control_output", "output", "", 1, "With several response instruments: the one whose model the robust analysis, the H2 design and the input design use (the collocated sensor), by index from 1 in the order of response or by name.", ge=1),
    KeySpec("backend", "emulation", "table", "", "absent: real instruments", "kind = \"instruments\" only: start emulators of the named instruments on their 127.0.0.1 resources, backed by the simulated beam on a virtual clock (CI, demos, rehearsals)."),
    KeySpec("backend.emulation", "drive_gain_ratio", "number", "", 1.0, "True drive gain of the emulated amplifier over the declared newton_per_volt.", gt=0.0, le=10.0),
    KeySpec("backend.emulation", "noise_v_per_rthz", "number", "V/sqrt(Hz)", 2e-6, "Noise density at the emulated lock-ins' inputs.", ge=0.0, le=1.0),
    KeySpec("backend.emulation", "damping", "number", "", "0.01 (the beam's)", "Damping ratio of every emulated mode (lightly damped structures: 0.002, 0.0005).", gt=0.0, le=0.5),
    KeySpec("backend.emulation", "relock_s", "number", "s", 0.0, "Time the emulated lock-ins need to relock their reference after a frequency step.", ge=0.0, le=60.0),
    KeySpec("backend.emulation", "sensors", "numbers", "", "[1.0] (the tip)", "Where each response instrument's emulated displacement sensor sits on the cantilever (fraction of its length from the clamp), one per name in [backend] response, in that order (issue 25); required with several response instruments.", gt=0.0, le=1.0),
    KeySpec("backend.emulation", "first_mode_rad_s", "number", "rad/s", 1.0, "First natural frequency of the emulated beam; all its modes scale with it and its residues with its square, as [backend.simulation] first_mode_rad_s does for the simulation (time-scale [weights] with it).", gt=0.0, le=1e9),
    KeySpec("backend.emulation", "actuator", "number", "", 1.0, "Where the emulated shaker's force acts (fraction of the length from the clamp; the thesis: the tip).", gt=0.0, le=1.0),
    KeySpec("backend.simulation", "noise_profile", "choice", "", _SIM.noise_profile, "Additive-noise bound R(omega) of section 6.2: fully damped model (6.3.2), SNR 10 (6.3.3), resonance noise (6.3.4) or none.", choices=NOISE_PROFILES),
    KeySpec("backend.simulation", "noise_scale", "number", "", _SIM.noise_scale, "Multiplies the noise bound.", ge=0.0),
    KeySpec("backend.simulation", "first_mode_rad_s", "number", "rad/s", _SIM.first_mode_rad_s, "First natural frequency of the simulated beam; all its modes scale with it, its residues with its square, and the simulated noise bounds follow the response (time-scale [weights] with it).", gt=0.0, le=1e9),
    KeySpec("backend.simulation", "unmodelled_dynamics", "bool", "", _SIM.unmodelled_dynamics, "Keep modes 4-8 in the simulated truth and add |W1| to each point's bound."),
    KeySpec("backend.simulation", "sensors", "numbers", "", list(_SIM.sensors), "Displacement sensors along the cantilever, as fractions of its length from the clamp; every dwell reads all of them (shared poles, issue 25). kind = \"sim\" and \"time-domain\".", gt=0.0, le=1.0),
    KeySpec("backend.simulation", "actuator", "number", "", _SIM.actuator, "Where the force acts, as a fraction of the length from the clamp (the thesis: the tip).", gt=0.0, le=1.0),
    KeySpec("backend.simulation", "truth", "string", "", "", "A truth file (TOML, relative to this file) whose [[mode]] tables (omega_rad_s or omega_hz, zeta, b0, b1) replace the simulated beam: rehearse a campaign on your own structure. The prior models the lowest modes; higher ones are unmodelled dynamics. kind = \"sim\" only."),
    KeySpec("backend.simulation", "control_output", "output", "", _SIM.control_output, "The sensor whose model the robust analysis, the H2 design and the input design use (the collocated one): its index from 1 in the order of sensors, or its name \"x=<position>\"; the others tighten the shared poles.", ge=1),
    # [backend.transport]: one schema per backend kind, the same limits for every transport
    *(spec for kind in LOOPBACK_BACKENDS for spec in (
        KeySpec(f"transport:{kind}", "reply_timeout_s", "number", "s", "per transport", "Wait for one device reply before retrying (serial 0.2, CAN/Modbus 0.1).", ge=1e-3, le=60.0),
        KeySpec(f"transport:{kind}", "max_attempts", "integer", "", "per transport", "Tries per command before a device fault is declared (serial 6, CAN/Modbus 7).", ge=1, le=100),
        KeySpec(f"transport:{kind}", "backoff_s", "number", "s", "per transport", "First wait between retries, doubling (0 = retry at once; serial 0.002, CAN/Modbus 0.01).", ge=0.0, le=10.0),
        KeySpec(f"transport:{kind}", "backoff_max_s", "number", "s", "per transport", "Largest wait between retries (serial 0.05, CAN/Modbus 0.32).", ge=0.0, le=60.0),
        KeySpec(f"transport:{kind}", "response_noise_per_bound", "number", "", 1.0, "The fake device's sensor noise relative to the error bound.", gt=0.0, le=1e6),
        KeySpec(f"transport:{kind}", "learn_poles", "bool", "", False, "Carry the transient poles from dwell to dwell (shorter dwells near modes; a resumed run no longer repeats an uninterrupted one bit for bit)."),
        KeySpec(f"transport:{kind}", "max_window_s", "number", "s", 120.0, "Longest acquisition window of one dwell.", gt=0.0),
    )),
    KeySpec("transport:can-virtual", "channel", "string", "", "a unique name", "python-can virtual channel of the fake device."),
    KeySpec("transport:can-virtual", "node", "integer", "", 0x21, "CAN node id of the device.", ge=1, le=0x7F),
    KeySpec("transport:can-virtual", "gap_timeout_s", "number", "s", 0.2, "Wait for missing sample frames before asking for a resend.", ge=1e-3, le=60.0),
    KeySpec("transport:modbus-loopback", "framer", "choice", "", "socket", "Modbus framing over the TCP connection.", choices=("socket", "rtu")),
    KeySpec("transport:modbus-loopback", "unit", "integer", "", 1, "Modbus unit (device) id.", ge=1, le=247),
    KeySpec("backend.faults", "rate", "number", "", 0.0, "Probability of each enabled fault per opportunity (per frame or per capture).", ge=0.0, le=1.0),
    KeySpec("backend.faults", "kinds", "strings", "", "all", "Enabled fault kinds: " + ", ".join(FAULT_KINDS) + "; with can-virtual also " + ", ".join(CAN_FAULT_KINDS) + "; with modbus-loopback also " + ", ".join(MODBUS_FAULT_KINDS) + "."),
    KeySpec("backend.faults", "seed", "integer", "", 0, "Seed of the fault draws.", ge=0, le=SEED_MAX),
    KeySpec("backend.faults", "rates", "kind-rates", "", "{}", "Per-kind probabilities overriding rate, e.g. rates = { timeout = 0.1, corrupt = 0.02 }."),
    # [instruments.<name>]
    KeySpec("instrument", "profile", "string", "", _REQUIRED, "Instrument profile: a shipped name (keysight-33500b, rigol-dg800, srs-sr830, srs-sr860, modbus-shaker-controller) or the path of a profile file, relative to the procedure."),
    KeySpec("instrument", "resource", "string", "", _REQUIRED, "Where it is: a PyVISA resource string (TCPIP::HOST::5025::SOCKET, USB0::...::INSTR, ASRL/dev/ttyUSB0::INSTR); Modbus: tcp://HOST:PORT or rtu:///dev/ttyUSB0?baudrate=19200&parity=E."),
    KeySpec("instrument", "channel", "integer", "", 1, "Output channel of a generator; on an oscilloscope, [instruments.<name>.channel.N] tables instead: each channel's sensor (volt_per_unit, calibration_uncertainty, quantity).", ge=1, le=16),
    KeySpec("instrument", "channels", "scope-channels", "", "required for an oscilloscope", "An oscilloscope's roles: channels = { force = 1, response = [2, 3] } (one force channel, one or more response channels; the same scope is then both [backend] force and response; several response channels are several outputs, control_output indexing them)."),
    KeySpec("instrument", "trigger_channel", "integer", "", "EXT where the profile has it, else the force channel", "The oscilloscope channel wired to the generator's sync output (the record's trigger).", ge=1, le=16),
    KeySpec("instrument", "channel_match", "string", "", "none: the datasheet's gain accuracy on every point", "An oscilloscope's channel-match file (setmem-hil calibrate-channels), relative to the procedure: each channel's gain at each V/div, so a point's bound carries the match's uncertainty instead of both channels' gain accuracy."),
    KeySpec("instrument.channel", "volt_per_unit", "number", "V/unit", _REQUIRED, "This channel's sensor sensitivity: volts per newton (force) or per response unit.", gt=0.0),
    KeySpec("instrument.channel", "calibration_uncertainty", "number", "", 0.0, "Relative uncertainty of this channel's volt_per_unit; part of every point's bound.", ge=0.0, le=0.5),
    KeySpec("instrument.channel", "quantity", "choice", "", "force (the force channel) / displacement", "What this channel's sensor measures.", choices=SENSOR_QUANTITIES),
    KeySpec("instrument", "newton_per_volt", "number", "N/V", "required for the exciter", "Nominal force amplitude per volt of drive amplitude (peak); for planning only: the measured force sets the level.", gt=0.0),
    KeySpec("instrument", "max_drive_v", "number", "V", "the instrument's limit", "Never command more than this peak drive voltage.", gt=0.0),
    KeySpec("instrument", "load_ohms", "number", "ohm", "high impedance", "Generator output load setting (the amplifier's input impedance).", gt=0.0),
    KeySpec("instrument", "volt_per_unit", "number", "V/unit", "required for sensors", "Sensor sensitivity: volts per newton (force), per metre, per m/s or per m/s^2 (response).", gt=0.0),
    KeySpec("instrument", "calibration_uncertainty", "number", "", 0.0, "Relative uncertainty of volt_per_unit; part of every point's bound and of the force limit.", ge=0.0, le=0.5),
    KeySpec("instrument", "quantity", "choice", "", "force (force role) / displacement (response role)", "What the sensor measures; the point is converted to receptance.", choices=SENSOR_QUANTITIES),
    KeySpec("instrument", "iepe_current_a", "number", "A", "0 (no excitation)", "NI-DAQmx channels: IEPE current excitation for an accelerometer or force sensor (e.g. 0.004); the channel is created as nidaqmx's IEPE accelerometer (quantity = \"acceleration\") or IEPE force channel (quantity = \"force\"), with volt_per_unit as its sensitivity.", ge=0.0, le=0.025),
    KeySpec("instrument", "coupling", "choice", "", "AC with iepe_current_a, else DC", "NI-DAQmx channels: input coupling; AC removes an IEPE sensor's bias, and its high-pass (the profile's ac_coupling_corner_hz) enters every point's bound.", choices=("AC", "DC")),
    KeySpec("instrument", "visa_library", "string", "", "@py", "PyVISA library: @py (pyvisa-py, pure Python), @ivi (a vendor VISA) or FILE.yaml@sim (pyvisa-sim)."),
    # [safety]
    KeySpec("safety", "max_amplitude_n", "number", "N", _S.max_amplitude_n, "Largest exciter amplitude ever commanded.", gt=0.0),
    KeySpec("safety", "omega_min_rad_s", "number", "rad/s", _S.omega_min_rad_s, "Lowest excitation frequency allowed.", gt=0.0),
    KeySpec("safety", "omega_max_rad_s", "number", "rad/s", _S.omega_max_rad_s, "Highest excitation frequency allowed (must exceed omega_min_rad_s).", gt=0.0),
    KeySpec("safety", "max_dwell_s", "number", "s", _S.max_dwell_s, "Longest single sine dwell (settling plus averaging).", gt=0.0),
    KeySpec("safety", "max_response", "number", "response unit", "none", "Instrument backends: switch the output off and stop when the measured response amplitude exceeds this (in the response sensor's quantity).", gt=0.0),
    # [[mode]] (validated by setmem_hil.model.prior.parse_mode_table)
    KeySpec("mode", "omega_min", "number", "rad/s", _REQUIRED, "Lower bound of the natural frequency.", gt=0.0),
    KeySpec("mode", "omega_max", "number", "rad/s", _REQUIRED, "Upper bound of the natural frequency (>= omega_min)."),
    KeySpec("mode", "zeta_max", "number", "", _REQUIRED, "Upper bound of the damping ratio, in (0, 10].", gt=0.0, le=10.0),
    KeySpec("mode", "b1", "number", "", "free", "Fix b1 (b1 = 0 for a displacement sensor, section 6.2.2)."),
    KeySpec("mode", "b1_min", "number", "", "-inf", "Lower bound of b1 (instead of b1)."),
    KeySpec("mode", "b1_max", "number", "", "+inf", "Upper bound of b1 (instead of b1)."),
    KeySpec("mode", "b0_min", "number", "", "-inf", "Lower bound of the residue b0."),
    KeySpec("mode", "b0_max", "number", "", "+inf", "Upper bound of the residue b0."),
    # [identification]
    KeySpec("identification", "gamma", "number", "", 1.1, "Target embedding conservatism ratio of the partitioning (section 3.2.3); > 1.", gt=1.0),
    KeySpec("identification", "max_partitions", "integer", "", 200, "Largest number of frequency partitions per mode.", ge=1),
    KeySpec("identification", "unmodelled_bound", "choice", "", "w1", "Add |W1(j omega)| from [weights] to every measured point's bound (\"w1\"), or nothing (\"none\"). Default \"w1\" on instrument backends; simulated backends add it when they simulate unmodelled modes.", choices=UNMODELLED_BOUNDS),
    # [initial]
    KeySpec("initial", "omega_rad_s", "numbers", "rad/s", _REQUIRED, "Initial frequencies, measured in this order (give this or log_spaced).", gt=0.0),
    KeySpec("initial", "log_spaced", "table", "", "", "Initial frequencies log-spaced: numpy.geomspace(min, max, n) (give this or omega_rad_s)."),
    KeySpec("initial.log_spaced", "min", "number", "rad/s", _REQUIRED, "Lowest initial frequency.", gt=0.0),
    KeySpec("initial.log_spaced", "max", "number", "rad/s", _REQUIRED, "Highest initial frequency (>= min).", gt=0.0),
    KeySpec("initial.log_spaced", "n", "integer", "", _REQUIRED, "Number of points (>= 2 unless min = max).", ge=1, le=100000),
    # [goal]
    KeySpec("goal", "mu_target", "number", "", _G.mu_target, "Stop when the peak of mu-bar (robust performance, eq. 5.1) is at or below this.", gt=0.0),
    KeySpec("goal", "max_experiments", "integer", "", _G.max_experiments, "Experiment budget: the campaign stops after this many experiments added by input design.", ge=0, le=100000),
    # [input_design]
    KeySpec("input_design", "strategy", "choice", "", _ID.strategy, "mu: the thesis's mu-sensitivity design (chapter 5); log-sweep, random, max-reduction: comparison strategies.", choices=STRATEGIES),
    KeySpec("input_design", "candidates_base", "integer", "", _ID.candidates_base, "Number of candidate frequencies at the first iteration (section 6.3.2: 500).", ge=1, le=10**7),
    KeySpec("input_design", "candidates_per_iteration", "integer", "", _ID.candidates_per_iteration, "Candidates added per iteration (section 6.3.2: 500 + 25 k).", ge=0, le=10**6),
    KeySpec("input_design", "candidate_omega_min_rad_s", "number", "rad/s", "0.1 T", "Lowest candidate frequency (inside the safety range). Default 0.1 T, T the weights' reference frequency (half W2's pole frequency: 1 rad/s for the thesis weights), clipped to the safety range.", gt=0.0),
    KeySpec("input_design", "candidate_omega_max_rad_s", "number", "rad/s", "1000 T", "Highest candidate frequency (inside the safety range). Default 1000 T, clipped to the safety range.", gt=0.0),
    KeySpec("input_design", "exact_resolve_top", "integer", "", _ID.exact_resolve_top, "The best candidates re-identified exactly before choosing.", ge=0, le=10**6),
    KeySpec("input_design", "per_iteration", "integer", "", _ID.per_iteration, "Frequencies added per iteration (batch design: each further choice re-estimated with the ones already chosen as predicted data, chapter 4).", ge=1, le=100),
    KeySpec("input_design", "ranking", "choice", "", _ID.ranking, "thesis: rank candidates by expected mu-bar improvement (eq. 5.3); per_rig_second: by expected improvement per second of rig time (the dwell the rig would plan at that frequency with the current pole intervals).", choices=RANKINGS),
    # [design]
    KeySpec("design", "method", "choice", "", "robust", "robust: the H2 design (or the previous iteration's compensator) tuned, at the same order, to minimise the certified mixed-mu peak of the current box (issue 38); h2: the thesis's H2 design (section 6.3.1), for comparison. Command line: --design.", choices=DESIGN_METHODS),
    # [weights]
    KeySpec("weights", "w1_num", "numbers", "", "thesis eq. 6.1", "W1 numerator coefficients, highest power of s first."),
    KeySpec("weights", "w1_den", "numbers", "", "thesis eq. 6.1", "W1 denominator coefficients (stable, degree >= numerator's)."),
    KeySpec("weights", "w2_num", "numbers", "", "thesis eq. 6.13", "W2 numerator coefficients, highest power of s first."),
    KeySpec("weights", "w2_den", "numbers", "", "thesis eq. 6.13", "W2 denominator coefficients (stable, degree >= numerator's)."),
    KeySpec("weights", "w2_extra_pole_rad_s", "number", "rad/s", _W.w2_extra_pole_rad_s, "Extra W2 pole for the H2 design (section 6.3.1); 0 for none.", ge=0.0),
    # [dwell]
    KeySpec("dwell", "signal", "choice", "", "sine", "sine: one frequency per dwell (today's loop); multisine: the initial points in one record and each iteration's frequencies ([input_design] per_iteration) in one record, a sum of sinusoids whose peak stays within max_amplitude_n, settling paid once (backends sim and time-domain).", choices=DWELL_SIGNALS),
    # [discrepancy]
    KeySpec("discrepancy", "check_each_iteration", "bool", "", False, "After every iteration, check where model and data disagree and name the missing effect (setmem_hil.discrepancy.workflow); results go to the journal and the report, the campaign's choices are unchanged."),
)

_BY_TABLE: dict[str, dict[str, KeySpec]] = {}
for _spec in SCHEMA:
    _BY_TABLE.setdefault(_spec.table, {})[_spec.key] = _spec


SEVERAL_SENSOR_KINDS = ("sim", "time-domain")
"""Backends whose simulated beam reads ``[backend.simulation] sensors`` (issue 25)."""


class _Table(CheckedTable):
    """A table of the procedure format (:data:`SCHEMA`), with where it is, for messages."""

    def __init__(self, source: str, name: str, mapping: Any, location: str | None = None):
        super().__init__(source, name, mapping, _BY_TABLE, location)


def _truth_modes(top: _Table, s: "_Table", kind: str, sim: SimulationSettings) -> tuple[str, tuple]:
    """The truth file's absolute path (a stored procedure names it wherever it is read again) and
    its modes (issue 47): kind = "sim", one sensor at the tip, unscaled."""
    from setmem_hil.io.truth_file import read_truth_file

    if kind != "sim":
        raise s.error(f"truth: a truth file is simulated by kind = \"sim\" only; kind is {kind!r}")
    if tuple(sim.sensors) != _SIM.sensors or sim.actuator != _SIM.actuator or sim.first_mode_rad_s != _SIM.first_mode_rad_s:
        raise s.error("truth: the file's modes are the structure as the sensor sees it; sensors, actuator and "
                      "first_mode_rad_s are the cantilever's and cannot be combined with it")
    base = Path(top.source).parent if top.source and not str(top.source).startswith("<") else Path.cwd()
    path = (base / sim.truth).resolve()
    return str(path), read_truth_file(path, top.source)


def _backend(top: _Table) -> BackendSettings:
    t = top.sub("backend")
    kind = t.get("kind", "sim")
    sim = _simulation(top, t.sub("simulation"), kind)
    transport = _transport_options(top, t, kind)
    faults = _faults(top, t, kind)
    if kind != "sim" and sim.first_mode_rad_s != 1.0:
        raise ProcedureError(top.source, "[backend.simulation] key 'first_mode_rad_s'",
                             f"only the frequency-domain simulation (kind = \"sim\") scales the beam this way; the {kind} backend simulates it at 1 rad/s"
                             + (" (emulated instruments: [backend.emulation] first_mode_rad_s)" if kind == "instruments" else ""))
    if kind not in LOOPBACK_BACKENDS:
        for key in ("transport", "faults"):
            if t.has(key):
                where = "; the instruments' settings go in [instruments.<name>] tables" if kind == "instruments" else ""
                raise ProcedureError(top.source, f"[backend.{key}]", f"only used by transport backends ({', '.join(LOOPBACK_BACKENDS)}); kind is {kind!r}{where}")
    roles = _instrument_roles(t)
    emulation = _emulation(t, roles["responses"] or ((roles["response"],) if roles["response"] else ()))
    if kind != "instruments":
        given = [k for k in ("exciter", "force", "response", "control_output", "emulation") if t.has(k)]
        if given:
            raise ProcedureError(top.source, f"[backend] key '{given[0]}'", f"only used with kind = \"instruments\"; kind is {kind!r}")
    return BackendSettings(kind=kind, simulation=sim, transport=transport, faults=faults, emulation=emulation, **roles)


def _simulation(top: _Table, s: _Table, kind: str) -> SimulationSettings:
    """``[backend.simulation]``: the simulated structure, its sensors and its actuator."""
    sim = SimulationSettings(
        noise_profile=s.get("noise_profile", _SIM.noise_profile),
        noise_scale=s.get("noise_scale", _SIM.noise_scale),
        unmodelled_dynamics=s.get("unmodelled_dynamics", _SIM.unmodelled_dynamics),
        first_mode_rad_s=s.get("first_mode_rad_s", _SIM.first_mode_rad_s),
        sensors=tuple(float(x) for x in s.get("sensors", list(_SIM.sensors))),
        actuator=s.get("actuator", _SIM.actuator),
        control_output=s.get("control_output", _SIM.control_output),
        truth=s.get("truth", ""),
    )
    if sim.truth:
        path, modes = _truth_modes(top, s, kind, sim)
        sim = replace(sim, truth=path, truth_modes=modes)
    if isinstance(sim.control_output, str):
        names = sim.sensor_names()
        if sim.control_output not in names:
            raise s.error(f"control_output {sim.control_output!r} is not one of the sensors {list(names)}")
        sim = replace(sim, control_output=names.index(sim.control_output) + 1)
    if sim.control_output > len(sim.sensors):
        raise s.error(f"control_output: {sim.control_output} but only {len(sim.sensors)} sensor(s)")
    if len(set(sim.sensors)) != len(sim.sensors):
        raise s.error(f"sensors: each position once, found {list(sim.sensors)}")
    if kind not in SEVERAL_SENSOR_KINDS and (sim.sensors != _SIM.sensors or sim.actuator != _SIM.actuator):
        raise ProcedureError(top.source, "[backend.simulation] key 'sensors'",
                             f"several sensors and another actuator are simulated by kind = \"sim\" and \"time-domain\" only "
                             f"(the serial, CAN and Modbus wire formats carry one response channel); kind is {kind!r}")
    return sim


def _faults(top: _Table, t: _Table, kind: str) -> dict[str, Any]:
    """``[backend.faults]``: the fake devices' injected faults, each kind known to the backend."""
    if not t.has("faults"):
        return {}
    f = t.sub("faults")
    known = tuple(FAULT_KINDS) + TRANSPORT_FAULT_KINDS.get(kind, ())
    faults: dict[str, Any] = {"rate": f.get("rate", 0.0), "seed": f.get("seed", 0)}
    if f.has("kinds"):  # absent: every kind the backend knows (the drivers' default)
        kinds = f.get("kinds")
        bad = [k for k in kinds if k not in known]
        if bad:
            raise f.error(f"kinds: unknown fault kind {bad[0]!r} for backend {kind!r} (known: {', '.join(known)})")
        faults["kinds"] = list(kinds)
    if f.has("rates"):
        rates = f.mapping["rates"]
        where = "[backend.faults.rates]"
        if not isinstance(rates, Mapping):
            raise ProcedureError(top.source, where, f"expected a table of kind = probability, found {_type_name(rates)} {_fmt(rates)}")
        for k, r in rates.items():
            if k not in known:
                close = difflib.get_close_matches(str(k), list(known), n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                raise ProcedureError(top.source, where, f"unknown fault kind {k!r}{hint} (known: {', '.join(known)})")
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not 0.0 <= float(r) <= 1.0:
                raise ProcedureError(top.source, where, f"{k}: expected a probability in [0, 1], found {_fmt(r)}")
        faults["rates"] = {str(k): float(r) for k, r in rates.items()}
    return faults


def _instrument_roles(t: _Table) -> dict[str, Any]:
    """``[backend]`` exciter, force, response(s) and control_output of kind = "instruments"."""
    roles: dict[str, Any] = {role: t.get(role, "") for role in ("exciter", "force")}
    responses = t.get("response", ())
    control = t.get("control_output", 1)
    if isinstance(control, str):
        if control not in responses:
            raise t.error(f"control_output {control!r} is not one of the response instruments {list(responses)}")
        control = responses.index(control) + 1
    if len(responses) > 1 and control > len(responses):  # one instrument: an oscilloscope's channels may count (_instruments)
        raise t.error(f"control_output: {control} but only {len(responses)} response instrument(s)")
    roles["response"] = (responses[control - 1] if len(responses) > 1 else responses[0]) if responses else ""
    roles["responses"] = responses if len(responses) > 1 else ()
    roles["control_output"] = control
    return roles


def _emulation(t: _Table, responses) -> EmulationSettings | None:
    """``[backend.emulation]``: the emulated instruments' structure and imperfections."""
    if not t.has("emulation"):
        return None
    e = t.sub("emulation")
    n_responses = max(1, len(responses))
    sensors = tuple(float(x) for x in e.get("sensors", [1.0] * (1 if n_responses == 1 else 0)))
    # one oscilloscope's several response channels: counted in _instruments
    if len(sensors) != n_responses and n_responses > 1:
        raise e.error(f"sensors: one position per response instrument ({n_responses}: {list(responses)}), found {list(sensors)}")
    return EmulationSettings(drive_gain_ratio=e.get("drive_gain_ratio", 1.0), noise_v_per_rthz=e.get("noise_v_per_rthz", 2e-6),
                             damping=e.get("damping", None), relock_s=e.get("relock_s", 0.0),
                             sensors=sensors, actuator=e.get("actuator", 1.0), first_mode_rad_s=e.get("first_mode_rad_s", 1.0))


def _instruments(top: _Table, backend: BackendSettings) -> dict[str, InstrumentSettings]:
    """``[instruments.<name>]`` tables, and the [backend] roles checked against them."""
    raw = top.mapping.get("instruments", {})
    if not isinstance(raw, Mapping):
        raise ProcedureError(top.source, "[instruments]", f"expected tables [instruments.<name>], found {_type_name(raw)} {_fmt(raw)}")
    if raw and backend.kind != "instruments":
        raise ProcedureError(top.source, "[instruments]", f"only used with [backend] kind = \"instruments\"; kind is {backend.kind!r}")
    found: dict[str, InstrumentSettings] = {}
    for name, table in raw.items():
        t = _Table(top.source, "instrument", table, location=f"[instruments.{name}]")
        channel_tables = t.mapping.get("channel") if isinstance(t.mapping.get("channel"), Mapping) else None
        found[name] = InstrumentSettings(
            name=str(name), profile=t.get("profile"), resource=t.get("resource"),
            channel=1 if channel_tables is not None else t.get("channel", 1),
            newton_per_volt=t.get("newton_per_volt"), max_drive_v=t.get("max_drive_v"), load_ohms=t.get("load_ohms"),
            volt_per_unit=t.get("volt_per_unit"), calibration_uncertainty=t.get("calibration_uncertainty", 0.0),
            quantity=t.get("quantity"), visa_library=t.get("visa_library", "@py"),
            iepe_current_a=t.get("iepe_current_a", 0.0), coupling=t.get("coupling"),
            channel_roles=_scope_channel_roles(t, backend) if t.has("channels") else {},
            trigger_channel=t.get("trigger_channel"),
            channel_match=t.get("channel_match"),
            channel_sensors=_channel_sensors(top.source, str(name), channel_tables or {}),
        )
    if backend.kind != "instruments":
        return found
    roles = [("exciter", backend.exciter, "newton_per_volt"), ("force", backend.force, "volt_per_unit")]
    roles += [("response", name, "volt_per_unit") for name in backend.response_instruments() or ("",)]
    for role, name, needs in roles:
        where = f"[backend] key '{role}'"
        if not name:
            raise ProcedureError(top.source, where, f"missing: name the [instruments.<name>] table of the {role} (kind = \"instruments\")")
        if name not in found:
            close = difflib.get_close_matches(name, list(found), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise ProcedureError(top.source, where, f"no [instruments.{name}] table{hint} (tables: {', '.join(found) or 'none'})")
        if getattr(found[name], needs) is None and not found[name].channel_roles:  # a scope's channels carry their own
            raise ProcedureError(top.source, f"[instruments.{name}]", f"missing key {needs!r} (the {role} needs it)")
    for inst in found.values():
        if inst.channel_match is not None and not inst.channel_roles:
            raise ProcedureError(top.source, f"[instruments.{inst.name}] key 'channel_match'", "only an oscilloscope (a table with "
                                 "channels = { force = N, response = [...] }) has a channel match")
    if found[backend.force].channel_roles:
        _check_scope_roles(top, backend, found[backend.force])
        return found
    if backend.control_output > max(1, len(backend.responses)):
        raise ProcedureError(top.source, "[backend] key 'control_output'", f"{backend.control_output} but only one response instrument")
    if backend.emulation is not None and len(backend.emulation.sensors) != len(backend.response_instruments()):
        raise ProcedureError(top.source, "[backend.emulation] key 'sensors'", f"one position per response instrument, found {list(backend.emulation.sensors)}")
    force = found[backend.force]
    if (force.quantity or "force") != "force":
        raise ProcedureError(top.source, f"[instruments.{force.name}] key 'quantity'", f"the force role's sensor must measure force, found {force.quantity!r}")
    for response in (found[name] for name in backend.response_instruments()):
        if response.quantity == "force":
            raise ProcedureError(top.source, f"[instruments.{response.name}] key 'quantity'", "the response role's sensor must measure displacement, velocity or acceleration")
        if backend.force == response.name:
            raise ProcedureError(top.source, "[backend] key 'response'", f"force and response name the same instrument {backend.force!r}; a lock-in reads one signal")
    return found


def _scope_channel_roles(t: _Table, backend: BackendSettings) -> dict[str, tuple[int, ...]]:
    """``channels = { force = 1, response = [2, 3] }``: one force channel, response channels as
    the file lists them, each channel once."""
    raw = t.mapping["channels"]
    if not isinstance(raw, Mapping) or set(raw) - {"force", "response"} or "force" not in raw or "response" not in raw:
        raise t.error(f"channels: expected {{ force = N, response = N or [N, ...] }}, found {_fmt(raw)}")
    force, response = raw["force"], raw["response"]
    response = [response] if isinstance(response, int) and not isinstance(response, bool) else response
    every = [force, *response] if isinstance(response, list) else None
    if every is None or not response or not all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= 16 for c in every):
        raise t.error(f"channels: channel numbers are integers from 1, found {_fmt(raw)}")
    if len(set(every)) != len(every):
        raise t.error(f"channels: each channel in one role, found {_fmt(raw)}")
    control = backend.control_output if isinstance(backend.control_output, int) else 1
    if control > len(response):
        raise ProcedureError(t.source, "[backend] key 'control_output'", f"{control} but the oscilloscope has {len(response)} response channel(s)")
    return {"force": (int(force),), "response": tuple(int(c) for c in response)}


def _channel_sensors(source: str, name: str, tables: Mapping) -> dict[int, ChannelSensor]:
    """``[instruments.<name>.channel.N]`` tables (an oscilloscope's sensors)."""
    sensors = {}
    for key, table in tables.items():
        if not str(key).isdigit():
            raise ProcedureError(source, f"[instruments.{name}.channel]", f"expected tables [instruments.{name}.channel.N] with N a channel number, found key {key!r}")
        c = _Table(source, "instrument.channel", table, location=f"[instruments.{name}.channel.{key}]")
        sensors[int(key)] = ChannelSensor(c.get("volt_per_unit"), c.get("calibration_uncertainty", 0.0), c.get("quantity"))
    return sensors


def _check_scope_roles(top: _Table, backend: BackendSettings, scope: InstrumentSettings) -> None:
    """One oscilloscope as both the force and the response (issue 26): every channel it uses has
    its sensor table, the roles name it, the emulation places one sensor per response channel."""
    where = f"[instruments.{scope.name}]"
    if backend.response_instruments() != (scope.name,):
        raise ProcedureError(top.source, "[backend] key 'response'", f"with an oscilloscope as the force, response names the same "
                             f"oscilloscope {scope.name!r} (one record samples force and responses together); its channels "
                             "table says which channel is which")
    for role in ("force", "response"):
        for ch in scope.channel_roles[role]:
            sensor = scope.channel_sensors.get(ch)
            if sensor is None:
                raise ProcedureError(top.source, f"[instruments.{scope.name}.channel.{ch}]", f"missing: channel {ch} is a {role} channel; "
                                     "give its volt_per_unit (and calibration_uncertainty, quantity)")
            quantity = sensor.quantity or ("force" if role == "force" else "displacement")
            if (quantity == "force") != (role == "force"):
                raise ProcedureError(top.source, f"[instruments.{scope.name}.channel.{ch}] key 'quantity'",
                                     f"channel {ch} is a {role} channel; its sensor measures {quantity}")
    if scope.trigger_channel is not None and scope.trigger_channel in scope.channel_roles["response"]:
        raise ProcedureError(top.source, f"{where} key 'trigger_channel'", f"channel {scope.trigger_channel} is a response channel; "
                             "trigger on the generator's sync (a spare channel or EXT) or on the force channel")
    n_outputs = len(scope.channel_roles["response"])
    if backend.emulation is not None and len(backend.emulation.sensors) != n_outputs:
        raise ProcedureError(top.source, "[backend.emulation] key 'sensors'", f"one position per response channel of "
                             f"{scope.name!r} ({n_outputs}), found {list(backend.emulation.sensors)}")


def _transport_options(top: _Table, backend: _Table, kind: str) -> dict[str, Any]:
    """``[backend.transport]`` checked against the schema of ``kind``: unknown keys (with a
    did-you-mean), wrong types and out-of-range values are errors naming the key. Only the keys
    given are returned (the drivers own the defaults)."""
    raw = backend.mapping.get("transport", {})
    if kind not in LOOPBACK_BACKENDS:
        if not isinstance(raw, Mapping):
            raise ProcedureError(top.source, "[backend.transport]", f"expected a table, found {_type_name(raw)} {_fmt(raw)}")
        return dict(raw)  # kind 'sim' refuses the table below; an unknown kind is refused by kind
    table = _Table(top.source, f"transport:{kind}", raw, location="[backend.transport]")
    return {key: table.get(key) for key in raw}


def _safety(top: _Table) -> SafetyLimits:
    t = top.sub("safety")
    limits = SafetyLimits(
        max_amplitude_n=t.get("max_amplitude_n", _S.max_amplitude_n),
        omega_min_rad_s=t.get("omega_min_rad_s", _S.omega_min_rad_s),
        omega_max_rad_s=t.get("omega_max_rad_s", _S.omega_max_rad_s),
        max_dwell_s=t.get("max_dwell_s", _S.max_dwell_s),
        max_response=t.get("max_response"),
    )
    if limits.omega_min_rad_s >= limits.omega_max_rad_s:
        raise t.error(f"omega_min_rad_s {_fmt(limits.omega_min_rad_s)} must be < omega_max_rad_s {_fmt(limits.omega_max_rad_s)}")
    return limits


def _prior(top: _Table) -> Prior:
    source = top.source
    if "mode" not in top.mapping:
        raise ProcedureError(source, "[[mode]]", "missing: give one [[mode]] table per modelled mode (the prior)")
    tables = top.mapping["mode"]
    if isinstance(tables, Mapping):
        raise ProcedureError(source, "[[mode]]", "found a single [mode] table; write [[mode]] (an array of tables, one per mode)")
    if not isinstance(tables, list) or not tables:
        raise ProcedureError(source, "[[mode]]", f"expected one or more [[mode]] tables, found {_type_name(tables)} {_fmt(tables)}")
    modes: list[ModePrior] = []
    for i, table in enumerate(tables):
        try:
            modes.append(parse_mode_table(table, source, i + 1))
        except ProcedureError:
            raise
        except InputFormatError as exc:
            raise ProcedureError(exc.source, exc.location, exc.problem) from None
    for i in range(1, len(modes)):
        if modes[i].omega_min < modes[i - 1].omega_min:
            raise ProcedureError(
                source, f"[[mode]] {i + 1}",
                f"modes must be in ascending frequency: omega_min {_fmt(modes[i].omega_min)} < omega_min {_fmt(modes[i - 1].omega_min)} of [[mode]] {i}",
            )
    ident = top.sub("identification")
    return Prior(tuple(modes), gamma=ident.get("gamma", 1.1), max_partitions=ident.get("max_partitions", 200))


def _initial(top: _Table, safety: SafetyLimits) -> tuple[float, ...]:
    if "initial" not in top.mapping:
        raise ProcedureError(top.source, "[initial]", "missing: give omega_rad_s = [...] or log_spaced = {min = ..., max = ..., n = ...}")
    t = top.sub("initial")
    if t.has("omega_rad_s") == t.has("log_spaced"):
        raise t.error("give exactly one of omega_rad_s and log_spaced")
    if t.has("omega_rad_s"):
        omegas = t.get("omega_rad_s")
    else:
        ls = t.sub("log_spaced")
        w_lo, w_hi, n = ls.get("min"), ls.get("max"), ls.get("n")
        if w_lo > w_hi:
            raise ls.error(f"min {_fmt(w_lo)} > max {_fmt(w_hi)}")
        if n < 2 and w_lo != w_hi:
            raise ls.error(f"n {n} must be >= 2 when min < max")
        omegas = tuple(float(w) for w in np.geomspace(w_lo, w_hi, n))
    seen: dict[float, int] = {}
    for i, w in enumerate(omegas):
        if not safety.omega_min_rad_s <= w <= safety.omega_max_rad_s:
            raise t.error(
                f"initial frequency {i + 1} ({_fmt(w)} rad/s) is outside the [safety] range "
                f"[{_fmt(safety.omega_min_rad_s)}, {_fmt(safety.omega_max_rad_s)}] rad/s"
            )
        if w in seen:
            raise t.error(f"initial frequency {i + 1} ({_fmt(w)} rad/s) repeats frequency {seen[w] + 1}")
        seen[w] = i
    return tuple(omegas)


def _goal(top: _Table) -> Goal:
    t = top.sub("goal")
    return Goal(mu_target=t.get("mu_target", _G.mu_target), max_experiments=t.get("max_experiments", _G.max_experiments))


def _input_design(top: _Table, safety: SafetyLimits) -> InputDesignSettings:
    t = top.sub("input_design")
    s = InputDesignSettings(
        strategy=t.get("strategy", _ID.strategy),
        candidates_base=t.get("candidates_base", _ID.candidates_base),
        candidates_per_iteration=t.get("candidates_per_iteration", _ID.candidates_per_iteration),
        candidate_omega_min_rad_s=t.get("candidate_omega_min_rad_s", _ID.candidate_omega_min_rad_s),
        candidate_omega_max_rad_s=t.get("candidate_omega_max_rad_s", _ID.candidate_omega_max_rad_s),
        exact_resolve_top=t.get("exact_resolve_top", _ID.exact_resolve_top),
        per_iteration=t.get("per_iteration", _ID.per_iteration),
        ranking=t.get("ranking", _ID.ranking),
    )
    lo, hi = s.candidate_omega_min_rad_s, s.candidate_omega_max_rad_s
    if lo is not None and hi is not None and lo >= hi:
        raise t.error(f"candidate_omega_min_rad_s {_fmt(lo)} must be < candidate_omega_max_rad_s {_fmt(hi)}")
    if lo is not None and lo < safety.omega_min_rad_s:
        raise t.error(f"candidate_omega_min_rad_s {_fmt(lo)} is below [safety] omega_min_rad_s {_fmt(safety.omega_min_rad_s)}")
    if hi is not None and hi > safety.omega_max_rad_s:
        raise t.error(f"candidate_omega_max_rad_s {_fmt(hi)} exceeds [safety] omega_max_rad_s {_fmt(safety.omega_max_rad_s)}")
    return s


def _check_weight(t: _Table, name: str, num: tuple[float, ...], den: tuple[float, ...]) -> None:
    if den[0] == 0.0:
        raise t.error(f"{name}_den: leading coefficient must be non-zero")
    if len(np.trim_zeros(np.asarray(num), "f")) == 0:
        raise t.error(f"{name}_num: all coefficients are zero")
    if len(num) > len(den):
        raise t.error(f"{name}: numerator degree {len(num) - 1} exceeds denominator degree {len(den) - 1} (improper weight)")
    if len(den) > 1:
        with np.errstate(all="ignore"):
            poles = np.roots(den)
        if not np.all(np.isfinite(poles)):
            raise t.error(f"{name}_den: cannot compute the poles")
        bad = poles[poles.real >= 0]
        if bad.size:
            pole = complex(bad[0])
            where = f"{pole.real:.4g}" if pole.imag == 0 else f"{pole.real:.4g} {'+-'[pole.imag < 0]} {abs(pole.imag):.4g}j"
            raise t.error(f"{name}_den has a pole at s = {where} (the weight must be stable)")


def _weights(top: _Table) -> Weights:
    t = top.sub("weights")
    w = Weights(
        w1_num=t.get("w1_num", _W.w1_num),
        w1_den=t.get("w1_den", _W.w1_den),
        w2_num=t.get("w2_num", _W.w2_num),
        w2_den=t.get("w2_den", _W.w2_den),
        w2_extra_pole_rad_s=t.get("w2_extra_pole_rad_s", _W.w2_extra_pole_rad_s),
    )
    if w.w2_extra_pole_rad_s == 0.0:
        w = Weights(w.w1_num, w.w1_den, w.w2_num, w.w2_den, None)
    _check_weight(t, "w1", w.w1_num, w.w1_den)
    _check_weight(t, "w2", w.w2_num, w.w2_den)
    return w


def parse_procedure_mapping(doc: Any, source: str, text: str = "") -> Procedure:
    """Validate a parsed procedure document.

    Parameters
    ----------
    doc : mapping
        The parsed TOML document.
    source : str
        File name for messages.
    text : str
        The file's text, kept in :attr:`Procedure.source_text` (stored in the journal).

    Raises
    ------
    ProcedureError
        Naming the file, the table and the key of the first problem found.
    """
    from setmem_hil.model.prior import MODE_KEYS
    from setmem_hil.model.units import hz_keys_to_rad_s

    if isinstance(doc, Mapping) and "target" in doc:
        raise ProcedureError(source, "top level", "a [target] table makes this a closed-loop verification procedure: run it with "
                             f"`setmem-hil verify RUN_DIR --procedure {source}` (a campaign's procedure has no [target])")
    doc = hz_keys_to_rad_s(doc, {**{t: set(keys) for t, keys in _BY_TABLE.items()}, "mode": set(MODE_KEYS)}, source)
    top = _Table(source, "", doc)
    stem = Path(source).stem if source and not source.startswith("<") else ""
    name = top.get("name", stem or "procedure")
    if not name.strip():
        raise top.error("name must not be empty")
    if any(ord(c) < 32 for c in name):
        raise top.error(f"name {name!r} contains control characters")
    description = top.get("description", "")
    seed = top.get("seed", 1)
    backend = _backend(top)
    if backend.kind != "sim" and not top.has("safety"):
        # a rig is driven: its limits must be stated, never taken silently from the defaults
        raise top.error(f"backend {backend.kind!r} drives an exciter: give a [safety] table (max_amplitude_n, "
                        "omega_min_rad_s, omega_max_rad_s, max_dwell_s); only kind = \"sim\" may omit it")
    safety = _safety(top)
    prior = _prior(top)
    initial = _initial(top, safety)
    goal = _goal(top)
    design = _input_design(top, safety)
    weights = _weights(top)
    discrepancy = top.sub("discrepancy").get("check_each_iteration", False)
    instruments = _instruments(top, backend)
    backend = _with_channel_outputs(backend, instruments)
    unmodelled_bound = top.sub("identification").get("unmodelled_bound")
    dwell_signal = top.sub("dwell").get("signal", "sine")
    design_method = top.sub("design").get("method", "robust")
    # instruments: check_instruments decides, from the profiles (lock-ins or sampled sensors)
    if dwell_signal == "multisine" and backend.kind not in (*MULTISINE_BACKENDS, "instruments"):
        raise ProcedureError(top.source, "[dwell] key 'signal'", f"multisine needs an exciter that plays a sum of sines "
                             f"(kind {' or '.join(repr(k) for k in MULTISINE_BACKENDS)}); the {backend.kind} exciter plays single sines only")
    return Procedure(
        name=name,
        prior=prior,
        initial_omegas_rad_s=initial,
        seed=seed,
        backend=backend,
        safety=safety,
        goal=goal,
        input_design=design,
        weights=weights,
        discrepancy_check=discrepancy,
        instruments=instruments,
        unmodelled_bound=unmodelled_bound,
        dwell_signal=dwell_signal,
        design_method=design_method,
        description=description,
        source_text=text,
    )


def _with_channel_outputs(backend: BackendSettings, instruments: dict[str, InstrumentSettings]) -> BackendSettings:
    """An oscilloscope's several response channels name the outputs (``scope.ch2``, control first)."""
    scope = instruments.get(backend.force) if backend.kind == "instruments" else None
    if scope is None or len(scope.channel_roles.get("response", ())) < 2:
        return backend
    return replace(backend, channel_outputs=tuple(f"{scope.name}.ch{c}" for c in scope.response_channels(backend.control_output)))


def parse_procedure_text(text: str, source: str = "<procedure>") -> Procedure:
    """Parse and validate procedure TOML text (stored in :attr:`Procedure.source_text`).

    Raises
    ------
    ProcedureError
        For TOML syntax errors (with the line) and every validation problem.
    """
    if not isinstance(text, str):
        raise ProcedureError(source, "", f"expected text, found {type(text).__name__}")
    try:
        doc = parse_toml_text(text, source)
    except ProcedureError:
        raise
    except InputFormatError as exc:
        raise ProcedureError(exc.source, exc.location, exc.problem) from None
    except (ValueError, TypeError, RecursionError) as exc:  # tomllib edge cases (e.g. deep nesting)
        raise ProcedureError(source, "", f"invalid TOML: {exc}") from None
    return parse_procedure_mapping(doc, source, text)


def load_procedure(path: str | os.PathLike) -> Procedure:
    """Read and validate a procedure file; messages name ``path`` as given.

    Raises
    ------
    ProcedureError
        If the file cannot be read, is not valid TOML or does not validate.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ProcedureError(str(path), "", f"cannot read: {exc}") from None
    proc = parse_procedure_text(text, str(path))
    return replace(proc, source_path=str(p))
