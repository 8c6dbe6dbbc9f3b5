"""Procedure files: what a technician runs (schema as dataclasses; defaults = thesis 6.3.2).

A procedure gathers everything a campaign needs: the backend and its transport settings, the
safety limits, the prior (``[[mode]]`` tables, same keys as PRIOR.toml), the noise model of the
simulated backend, the initial frequencies, the goal and experiment budget, input-design
settings, and the control weights W1, W2. Every key is documented in README.

Loading and validation (messages naming file, table and key) live in
:mod:`setmem_hil.io.procedure_file`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping


from setmem_hil.model.prior import ModePrior, Prior
from setmem_hil.model.weights import THESIS_WEIGHTS, Weights

LOOPBACK_BACKENDS = ("serial-loopback", "can-virtual", "modbus-loopback")  # the project's own wire formats, fake devices only
IN_PROCESS_BACKENDS = ("time-domain",)  # the fake shaker + DAQ called directly, no wire format
BACKENDS = ("sim", *LOOPBACK_BACKENDS, *IN_PROCESS_BACKENDS, "instruments")
DWELL_SIGNALS = ("sine", "multisine")  # one frequency per dwell, or several in one record
MULTISINE_BACKENDS = ("sim", *IN_PROCESS_BACKENDS)  # exciters that can play a sum of sines
SENSOR_QUANTITIES = ("force", "displacement", "velocity", "acceleration")
UNMODELLED_BOUNDS = ("w1", "none")
STRATEGIES = ("mu", "log-sweep", "random", "max-reduction")
DESIGN_METHODS = ("robust", "h2")  # the compensator: tuned to the mixed-mu bound (issue 38), or the thesis's H2
RANKINGS = ("thesis", "per_rig_second")
NOISE_PROFILES = ("fully_damped", "snr10", "resonance", "none")


@dataclass(frozen=True)
class SafetyLimits:
    """Enforced in the driver layer before any command is sent."""

    max_amplitude_n: float = 1.0
    omega_min_rad_s: float = 0.05
    omega_max_rad_s: float = 2000.0
    max_dwell_s: float = 3600.0
    max_response: float | None = None  # abort limit on the measured response amplitude (instrument backends)


@dataclass(frozen=True)
class SimulationSettings:
    """Simulated structure behind every backend (the fake devices simulate it too)."""

    noise_profile: str = "fully_damped"
    noise_scale: float = 1.0
    unmodelled_dynamics: bool = True
    first_mode_rad_s: float = 1.0  # the beam's first natural frequency; modes and residues scale with it
    sensors: tuple[float, ...] = (1.0,)  # displacement sensors along the cantilever (fraction of its length; issue 25)
    actuator: float = 1.0  # where the force acts (the thesis: the tip)
    control_output: int = 1  # which sensor (from 1) the robust analysis and the H2 design use
    truth: str = ""  # a truth file (relative to the procedure file) replacing the beam (issue 47)
    truth_modes: tuple = ()  # its modes, ((omega_rad_s, zeta, b0, b1), ...) sorted by frequency

    def sensor_names(self) -> tuple[str, ...]:
        """``x=0.4`` etc., in the order of ``sensors``."""
        return tuple(f"x={x:g}" for x in self.sensors)

    def output_order(self) -> tuple[str, ...]:
        """The outputs as a measurement carries them: the control sensor, then the others in order."""
        names = self.sensor_names()
        c = self.control_output - 1
        return (names[c],) + tuple(n for i, n in enumerate(names) if i != c)


@dataclass(frozen=True)
class InstrumentSettings:
    """One ``[instruments.<name>]`` table: which profile, where, and its calibration."""

    name: str
    profile: str  # a shipped profile name or a path (relative to the procedure file)
    resource: str  # PyVISA resource string, or tcp://HOST:PORT / rtu:///dev/X?baudrate=... for Modbus
    channel: int = 1
    newton_per_volt: float | None = None  # exciters: nominal force per volt of drive (planning only)
    max_drive_v: float | None = None
    load_ohms: float | None = None  # generator output load; None: high impedance
    volt_per_unit: float | None = None  # sensors: sensitivity
    calibration_uncertainty: float = 0.0
    quantity: str | None = None  # sensors: None -> force for the force role, displacement for the response role
    visa_library: str = "@py"
    timeout_s: float | None = None  # the link's reply timeout (None: the profile's); not a file key: emulation sets it
    # an NI-DAQmx channel's sensor power and input coupling (issue 40): IEPE current excitation
    # in amperes (0: none) and "AC" | "DC" (None: AC with IEPE, else the device's default, DC)
    iepe_current_a: float = 0.0
    coupling: str | None = None
    # an oscilloscope (issue 26): {"force": (1,), "response": (2, 3)} as the file lists them;
    # each channel's sensor in channel_sensors
    channel_roles: Mapping[str, tuple[int, ...]] = field(default_factory=dict)
    trigger_channel: int | None = None
    channel_match: str | None = None  # an oscilloscope's channel-match file (relative to the procedure file)
    channel_sensors: Mapping[int, "ChannelSensor"] = field(default_factory=dict)

    def response_channels(self, control_output: int = 1) -> tuple[int, ...]:
        """An oscilloscope's response channels in measurement order: the control output first."""
        channels = tuple(self.channel_roles.get("response", ()))
        if len(channels) < 2:
            return channels
        c = control_output - 1
        return (channels[c],) + tuple(ch for i, ch in enumerate(channels) if i != c)


@dataclass(frozen=True)
class ChannelSensor:
    """One ``[instruments.<name>.channel.N]`` table: the sensor wired to an oscilloscope channel."""

    volt_per_unit: float
    calibration_uncertainty: float = 0.0
    quantity: str | None = None


@dataclass(frozen=True)
class EmulationSettings:
    """``[backend.emulation]``: run the instrument backend against the emulated instruments."""

    drive_gain_ratio: float = 1.0  # true drive gain / the declared newton_per_volt
    noise_v_per_rthz: float = 2e-6  # lock-in input noise density
    damping: float | None = None  # damping ratio of every emulated mode (None: the beam's 0.01)
    relock_s: float = 0.0  # the emulated lock-ins relock this long after every frequency step
    sensors: tuple[float, ...] = (1.0,)  # emulated sensor position per response instrument, in [backend] response's order
    actuator: float = 1.0  # where the emulated force acts
    first_mode_rad_s: float = 1.0  # the emulated beam's first natural frequency (every mode scales with it, as in simulation)


@dataclass(frozen=True)
class BackendSettings:
    kind: str = "sim"
    simulation: SimulationSettings = SimulationSettings()
    transport: Mapping[str, Any] = field(default_factory=dict)  # per-transport options (url, channel, ...)
    faults: Mapping[str, Any] = field(default_factory=dict)  # fault injection of fake devices
    exciter: str = ""  # kind = "instruments": names of [instruments.<name>] tables
    force: str = ""
    response: str = ""  # the control output's response instrument
    emulation: EmulationSettings | None = None
    responses: tuple[str, ...] = ()  # several response instruments (issue 25), as the file lists them
    control_output: int = 1  # index from 1 into responses (or into one oscilloscope's response channels)
    channel_outputs: tuple[str, ...] = ()  # one oscilloscope's response channels as outputs ("scope.ch2", ...), control first

    def response_instruments(self) -> tuple[str, ...]:
        """Every response instrument as a measurement carries them: the control output, then the
        others in the file's order (one name when ``response`` is a string)."""
        names = self.responses or ((self.response,) if self.response else ())
        if len(names) <= 1:
            return names
        c = self.control_output - 1
        return (names[c],) + tuple(n for i, n in enumerate(names) if i != c)

    def output_order(self) -> tuple[str, ...]:
        """The outputs' names in measurement order: response instruments (kind = "instruments"),
        else the simulated sensors (``x=<position>``)."""
        if self.kind == "instruments" and len(self.channel_outputs) > 1:
            return self.channel_outputs
        if self.kind == "instruments" and len(self.responses) > 1:
            return self.response_instruments()
        return self.simulation.output_order()


@dataclass(frozen=True)
class Goal:
    mu_target: float = 1.0
    max_experiments: int = 30


@dataclass(frozen=True)
class InputDesignSettings:
    strategy: str = "mu"
    candidates_base: int = 500  # 500 + 25 k candidates at iteration k (section 6.3.2)
    candidates_per_iteration: int = 25
    candidate_omega_min_rad_s: float | None = None  # None: 0.1 x the reference frequency
    candidate_omega_max_rad_s: float | None = None  # None: 1000 x the reference frequency
    exact_resolve_top: int = 5  # candidates re-identified exactly before choosing
    per_iteration: int = 1  # frequencies added per iteration (batch design)
    ranking: str = "thesis"  # or "per_rig_second": expected improvement per second of rig time

    def resolved(self, reference_rad_s: float = 1.0, safety: "SafetyLimits | None" = None) -> "InputDesignSettings":
        """These settings with a concrete candidate band: the given one, or ``[0.1, 1000] x
        reference_rad_s`` (the weights' reference frequency,
        :meth:`setmem_hil.model.weights.Weights.reference_frequency_rad_s`; 0.1-1000 rad/s for the
        thesis weights, section 6.3.2) clipped to the safety range, so the candidates follow the
        structure's frequency scale."""
        lo, hi = self.candidate_omega_min_rad_s, self.candidate_omega_max_rad_s
        if lo is not None and hi is not None:
            return self
        r = float(reference_rad_s)
        lo_d, hi_d = 0.1 * r, 1000.0 * r
        if safety is not None:
            lo_d, hi_d = max(lo_d, safety.omega_min_rad_s), min(hi_d, safety.omega_max_rad_s)
        return replace(self, candidate_omega_min_rad_s=lo_d if lo is None else lo,
                       candidate_omega_max_rad_s=hi_d if hi is None else hi)


@dataclass(frozen=True)
class Procedure:
    name: str
    prior: Prior
    initial_omegas_rad_s: tuple[float, ...]
    seed: int = 1
    backend: BackendSettings = BackendSettings()
    safety: SafetyLimits = SafetyLimits()
    goal: Goal = Goal()
    input_design: InputDesignSettings = InputDesignSettings()
    weights: Weights = THESIS_WEIGHTS
    discrepancy_check: bool = False
    instruments: Mapping[str, InstrumentSettings] = field(default_factory=dict)
    unmodelled_bound: str | None = None  # "w1" | "none"; None: the backend's default (see procedure_file)
    dwell_signal: str = "sine"  # "multisine": initial points and each iteration's batch in one record
    design_method: str = "robust"  # [design] method: "robust" (issue 38) or "h2" (thesis 6.3.1)
    description: str = ""
    source_text: str = ""  # the file's text, stored in the journal with the run
    source_path: str = ""

    @property
    def max_measurements(self) -> int:
        """The most measurements a campaign of this procedure takes: its initial frequencies and the
        goal's budget of added experiments (the progress display's total)."""
        return len(self.initial_omegas_rad_s) + int(self.goal.max_experiments)

    def time_scaled(self, factor: float) -> "Procedure":
        """The same campaign for the structure with every frequency times ``factor`` (issue 18's
        rescaling rule): prior bands, initial frequencies, safety frequency limits, an explicit
        candidate band and the simulated (or emulated) beam's first mode times ``factor``, the weights
        time-scaled (``W(s) -> W(s / factor)``). Noise and amplitudes are unchanged."""
        f = float(factor)
        d = self.input_design
        design = replace(d, **{k: getattr(d, k) * f for k in ("candidate_omega_min_rad_s", "candidate_omega_max_rad_s")
                               if getattr(d, k) is not None})
        sim = self.backend.simulation
        if self.backend.kind == "sim":  # the other backends simulate the beam at 1 rad/s (the parser refuses the key there)
            sim = replace(sim, first_mode_rad_s=sim.first_mode_rad_s * f)
        emulation = self.backend.emulation
        if emulation is not None:
            emulation = replace(emulation, first_mode_rad_s=emulation.first_mode_rad_s * f)
        return replace(
            self,
            prior=self.prior.time_scaled(f),
            initial_omegas_rad_s=tuple(w * f for w in self.initial_omegas_rad_s),
            backend=replace(self.backend, simulation=sim, emulation=emulation),
            safety=replace(self.safety, omega_min_rad_s=self.safety.omega_min_rad_s * f, omega_max_rad_s=self.safety.omega_max_rad_s * f),
            input_design=design,
            weights=self.weights.time_scaled(f),
            source_text="",
        )


def thesis_beam_prior(b1_fixed: bool = True, b1_limit: float = 1.0) -> Prior:
    """Section 6.1 prior: omega_n bounds of the first three modes, zeta <= 0.5; b1 = 0 (6.2.2).

    With ``b1_fixed=False`` (section 6.2.1) ``b1`` is bounded by ``+-b1_limit``: a guaranteed
    start needs some bound on it (the thesis started from an "engineering judgment" constant,
    section 3.2.1); 1.0 is seven times wider than the thesis's final b1 intervals (Table 6-2).
    """
    bounds = ((0.884, 1.125), (5.41, 7.34), (16.35, 19.81))
    extra = {"b1_min": 0.0, "b1_max": 0.0} if b1_fixed else {"b1_min": -b1_limit, "b1_max": b1_limit}
    return Prior(tuple(ModePrior(lo, hi, 0.5, **extra) for lo, hi in bounds))


def thesis_6_3_2_initial_omegas() -> tuple[float, ...]:
    """15 initial points, 5 around each of the first three modes but not at the peaks.

    The thesis (figure 6-8) shows them only as a plot. We place them at ratios
    0.80, 0.90, 0.95, 1.06, 1.15 of the prior's mid natural frequency of each mode, i.e. well
    outside each half-power band (+-1%), covering the band of a priori frequency uncertainty.
    """
    ratios = (0.80, 0.90, 0.95, 1.06, 1.15)
    centres = (1.0, 6.267, 17.547)  # the true natural frequencies the prior bands surround
    return tuple(float(round(c * r, 4)) for c in centres for r in ratios)


def default_procedure() -> Procedure:
    """The section 6.3.2 campaign on the simulated beam (used by ``setmem-hil demo``)."""
    return Procedure(
        name="beam-6.3.2",
        description="Thesis section 6.3.2: simulated cantilever, fully damped noise bound plus W1, b1 = 0.",
        prior=thesis_beam_prior(),
        initial_omegas_rad_s=thesis_6_3_2_initial_omegas(),
        # the thesis's candidate band (section 6.3.2), stated explicitly as in beam_6_3_2.toml
        input_design=InputDesignSettings(candidate_omega_min_rad_s=0.1, candidate_omega_max_rad_s=1000.0),
    )
