"""The experiment protocol: what the campaign loop needs from a rig, real or simulated.

Optional capabilities are declared protocols too (checked with ``isinstance``, never probed
with ``getattr``): :class:`ResumableExperiment`, :class:`ModelAwareExperiment`,
:class:`BoundPredictingExperiment`, :class:`CountingExperiment`, :class:`PlanningExperiment`,
:class:`IdentifiedExperiment`, :class:`MultisineExperiment`, :class:`OutputConfirmingExperiment`,
:class:`OutputModelsAwareExperiment`, :class:`CalibrationScaledExperiment`,
:class:`RawRecordingExperiment`.

One call applies a unit-amplitude sinusoid at ``omega_rad_s`` and returns the steady-state
complex response ``G(j omega)`` with an absolute bound on its total error (noise, estimation
error and unmodelled dynamics), exactly the four columns of the data CSV. The loop depends on
this protocol only (devices and procedures apart, as in Bluesky/ophyd): the simulated beam,
the sine-dwell measurement over serial/CAN/Modbus and test doubles all implement it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class Measurement:
    """One frequency-response measurement: a row of the data CSV, plus the rig time it cost.

    ``rig_s`` is the device time of the dwell (settling, excitation and acquisition, failed
    attempts included): the shaker time a real rig spends on this point. 0 where unknown. It is
    what the point cost, not part of what was measured: equality compares the measurement only.
    """

    omega_rad_s: float
    response: complex
    bound: float
    rig_s: float = field(default=0.0, compare=False)
    others: tuple[tuple[complex, float], ...] = ()
    """The other sensors of the same dwell (issue 25), ``(response, bound)`` each, in the
    procedure's sensor order without the control output, which is ``response``/``bound``."""


@runtime_checkable
class Experiment(Protocol):
    """Anything that can measure the structure's frequency response at one frequency."""

    def measure(self, omega_rad_s: float) -> Measurement:
        """Apply a unit sinusoid at ``omega_rad_s``, wait for steady state, return the response.

        Must leave the actuator at zero output when it returns or raises.
        """
        ...

    def close(self) -> None:
        """Command the actuator to zero and release the device (idempotent)."""
        ...


@runtime_checkable
class ResumableExperiment(Protocol):
    """Counts its measurements; a resumed campaign sets ``n_measured`` to the stored count so the
    (simulated) noise continues exactly where the stopped run left it."""

    n_measured: int


@runtime_checkable
class MultisineExperiment(Protocol):
    """Measures several frequencies in one record (a multisine dwell, ``[dwell] signal = "multisine"``).

    Returns one measurement per frequency, in order; ``n_measured`` (if any) advances by their
    number. The actuator is at zero when it returns or raises.
    """

    def measure_multisine(self, omegas_rad_s) -> list[Measurement]: ...


@runtime_checkable
class ModelAwareExperiment(Protocol):
    """Uses the current interval model (e.g. to fit transients with the identified poles)."""

    def update_model(self, model: Any) -> None: ...


@runtime_checkable
class OutputModelsAwareExperiment(Protocol):
    """Reads several sensors and uses every output's own interval model (issue 25; control
    output first), e.g. for each output's free-response allowance."""

    def update_output_models(self, models: Any) -> None: ...


@runtime_checkable
class CalibrationScaledExperiment(Protocol):
    """Measures every output's ratio in its sensors' calibration scale: ``calibration_scales``
    holds, per output (control first), the interval ``(c_lo, c_hi)`` of measured over true ratio,
    common to all its points and left out of their bounds; the campaign identifies the model as
    measured and widens the residues by it
    (:mod:`setmem_hil.identification.calibration_scale`)."""

    @property
    def calibration_scales(self) -> tuple[tuple[float, float], ...]: ...


@runtime_checkable
class BoundPredictingExperiment(Protocol):
    """Knows the total error bound ``R(omega)`` a measurement at ``omega`` will report."""

    def total_bound(self, omega_rad_s: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class CountingExperiment(Protocol):
    """Counts faults, retries and discarded dwells (journaled as events by an observer)."""

    counters: Mapping[str, int]


@runtime_checkable
class PlanningExperiment(Protocol):
    """Can say beforehand how long a dwell at ``omega`` will take (``plan(w).skip_s + .window_s``)."""

    def plan(self, omega_rad_s: float) -> Any: ...


@runtime_checkable
class IdentifiedExperiment(Protocol):
    """Knows which instruments it drives: ``{name: identity answer}`` (journaled with the run,
    so the data say which serial numbers measured them)."""

    identities: Mapping[str, str]


@runtime_checkable
class OutputConfirmingExperiment(Protocol):
    """Drives an exciter whose output state can be read back: ``output_confirmed_off`` is True
    only after an output-off was read back from the instrument (False from the moment the output
    is switched on, and after a switch-off that could not be confirmed). ``exciter`` names the
    instrument in messages; ``confirm_output_off()`` switches the output off and reads it back
    (a fresh connection if the link failed), raising when it cannot be confirmed."""

    output_confirmed_off: bool
    exciter: str

    def confirm_output_off(self) -> None: ...


@runtime_checkable
class CampaignControl(Protocol):
    """Steers a running campaign between dwells (the live view's Pause/Resume/Abort).

    ``checkpoint(make_safe)`` is called before every new dwell: it returns at once to go on,
    blocks while paused (calling ``make_safe()`` first, which confirms every exciter output off),
    or raises :class:`setmem_hil.errors.CampaignAborted` to stop (journal closed, resumable)."""

    def checkpoint(self, make_safe=None) -> None: ...


@dataclass(frozen=True)
class RawRecord:
    """What one dwell's points were computed from (issue 39): stored in ``RUN_DIR/raw.h5``
    before the points are committed, and recomputed from by ``setmem-hil reprocess``.

    ``kind`` names the estimator that turns it into points
    (:mod:`setmem_hil.estimation.raw_reprocessing`); ``datasets`` are arrays (samples, readings,
    times: as read, never rounded); ``attrs`` are numbers, strings or JSON-able structures (the
    stored settings, instrument identities). ``positions``: which of the call's measurements
    (0-based, in the order returned) it produced; None for all of them (a multisine record split
    into several records names its lines)."""

    kind: str
    datasets: Mapping[str, np.ndarray]
    attrs: Mapping[str, Any] = field(default_factory=dict)
    positions: tuple[int, ...] | None = None


@runtime_checkable
class RawRecordingExperiment(Protocol):
    """Keeps what each dwell was computed from: ``take_raw_records()`` returns (and forgets) the
    records of the measurements made since the last call, in order."""

    def take_raw_records(self) -> list[RawRecord]: ...
