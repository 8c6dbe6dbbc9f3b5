"""A lock-in dwell's raw record (kind ``lock-in-readings``) and :func:`lock_in_points`, which
computes its points: the phasor dwell
(:class:`setmem_hil.drivers.instruments.phasor_dwell.PhasorDwellExperiment`) computes every point
through :func:`output_point`, so ``setmem-hil reprocess`` runs the same code on the stored
readings.

Datasets: ``times_s`` (clock time of each reading), ``force_v`` (every force reading, X + jY in
V RMS), ``response_v`` (every output's readings, one row each, control output first). Attributes:
``omega_rad_s``, ``window`` (the last readings the point is the mean of), ``confidence``, the force
sensor's ``force_volt_per_unit`` and ``force_calibration``, per output its sensor's
``volt_per_unit``, ``calibration``, ``quantity`` and the model-based terms of that dwell
(``allowance``: the modes' free response, receptance units; stored, not recomputed, since it
depends on the drive's history), ``extra_bound`` (``|W1|`` or 0), and the lock-ins' settings
(time constant, ranges) as read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from setmem_hil.estimation.instrument_terms import to_receptance
from setmem_hil.estimation.phasor_estimate import PhasorPoint, exponential_gap, phasor_point
from setmem_hil.model.experiment import Measurement, RawRecord

__all__ = ["OutputPoint", "OutputSensor", "lock_in_points", "output_point", "reading_ratios", "receptance_scale"]

LOCK_IN_READINGS = "lock-in-readings"
"""Raw-record kind of lock-in X, Y readings with their times (recomputed by :func:`lock_in_points`)."""


@dataclass(frozen=True)
class OutputSensor:
    """What the point computation needs of a sensor: its scale, calibration and quantity."""

    volt_per_unit: float
    calibration: float
    quantity: str


@dataclass(frozen=True)
class OutputPoint:
    """One output's receptance and bound, the window's phasor point and the readings' trend gap."""

    response: complex
    bound: float
    point: PhasorPoint
    trend: float


def receptance_scale(omega_rad_s: float, quantity: str) -> float:
    return {"displacement": 1.0, "velocity": 1.0 / omega_rad_s, "acceleration": 1.0 / omega_rad_s**2}[quantity]


def reading_ratios(force_v, response_v, force: OutputSensor, sensor: OutputSensor) -> np.ndarray:
    """Each reading's response per force, in the sensors' units."""
    return (np.asarray(response_v) / sensor.volt_per_unit) / (np.asarray(force_v) / force.volt_per_unit)


def trend_gap(force_v: np.ndarray, response_v: np.ndarray, times: np.ndarray, window: int, force: OutputSensor,
              sensor: OutputSensor, confidence: float) -> float:
    """The exponential trend of every reading of the dwell (:func:`exponential_gap`), in the
    ratio's units: what a transient slower than the window may still hide."""
    ratio = reading_ratios(force_v, response_v, force, sensor)
    return exponential_gap(times, ratio, complex(ratio[-window:].mean()), confidence)


def output_point(omega_rad_s: float, force_v: np.ndarray, response_v: np.ndarray, times: np.ndarray, window: int,
                 force: OutputSensor, sensor: OutputSensor, confidence: float, allowance: float,
                 extra: float) -> OutputPoint:
    """One output's receptance and its bound from every reading of the dwell: the window's
    point (:func:`phasor_point`) and the trend gap in the sensor's quantity, the free-response
    ``allowance`` (receptance) and ``extra`` (``|W1|``: the unmodelled modes at every sensor)."""
    trend = trend_gap(force_v, response_v, times, window, force, sensor, confidence)
    point = phasor_point(force_v[-window:], response_v[-window:], force.volt_per_unit, sensor.volt_per_unit, force.calibration,
                         sensor.calibration, confidence)
    g = to_receptance(point.response, omega_rad_s, sensor.quantity)
    bound = (point.bound + trend) * receptance_scale(omega_rad_s, sensor.quantity)
    bound += allowance * receptance_scale(omega_rad_s, "displacement")
    if extra:
        bound += extra
    return OutputPoint(complex(g), float(bound), point, trend)


def lock_in_record(omega_rad_s: float, force_v: np.ndarray, response_v: np.ndarray, times: np.ndarray, window: int,
                   force: OutputSensor, sensors: list[OutputSensor], confidence: float, allowances: list[float], extra: float,
                   settings: dict) -> RawRecord:
    """The raw record of one lock-in dwell (see the module docstring)."""
    outputs = [{"volt_per_unit": s.volt_per_unit, "calibration": s.calibration, "quantity": s.quantity, "allowance": float(a)}
               for s, a in zip(sensors, allowances)]
    return RawRecord(LOCK_IN_READINGS, {"times_s": np.asarray(times, dtype=float), "force_v": np.asarray(force_v, dtype=complex),
                                        "response_v": np.asarray(response_v, dtype=complex)},
                     {"omega_rad_s": float(omega_rad_s), "window": int(window), "confidence": float(confidence),
                      "force_volt_per_unit": force.volt_per_unit, "force_calibration": force.calibration, "outputs": outputs,
                      "extra_bound": float(extra), "lock_in_settings": settings})


def lock_in_points(record: RawRecord) -> list[Measurement]:
    """The point of a ``lock-in-readings`` record, every output's (control output first)."""
    d, a = record.datasets, record.attrs
    force = OutputSensor(float(a["force_volt_per_unit"]), float(a["force_calibration"]), "force")
    w = float(a["omega_rad_s"])
    force_v, times = np.asarray(d["force_v"]), np.asarray(d["times_s"])
    outputs = [output_point(w, force_v, np.asarray(r), times, int(a["window"]), force,
                            OutputSensor(float(o["volt_per_unit"]), float(o["calibration"]), o["quantity"]), float(a["confidence"]),
                            float(o["allowance"]), float(a["extra_bound"]))
               for r, o in zip(np.asarray(d["response_v"]), a["outputs"])]
    others = tuple((o.response, o.bound) for o in outputs[1:])
    return [Measurement(w, outputs[0].response, outputs[0].bound, others=others)]
