"""A sampled instrument's terms on a measured point, as data (issue 39: so a raw record can
carry them and ``reprocess`` apply them again): the calibration scale of each output, each
output's channel error discs and the force channel's, the channel match's gain ratio where it
covers both channels, and the sensor's quantity (the point is converted to receptance).

:func:`apply_instrument_terms` is what the scope and DAQ sensors apply to every point
(``corrected``); the terms are evaluated by the sensor right after the record, at the point's
frequency.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Sequence

from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.channel_errors import ChannelError, ratio_error_bound
from setmem_hil.model.experiment import Measurement

__all__ = ["InstrumentTerms", "OutputTerms", "apply_instrument_terms", "scale_structure_terms", "to_receptance",
           "with_instrument_terms"]


def to_receptance(value: complex, omega_rad_s: float, quantity: str) -> complex:
    """Response per force in the sensor's quantity to displacement per force (receptance)."""
    jw = 1j * omega_rad_s
    return {"displacement": value, "velocity": value / jw, "acceleration": value / (jw * jw)}[quantity]


@dataclass(frozen=True)
class OutputTerms:
    """One output's terms: its channel's error and the force channel's (as the ratio sees them),
    its sensor's quantity, and with a channel match the output's gain over the force channel's
    (``gain_ratio``) and the force channel's gain (``force_gain``)."""

    force_error: ChannelError
    output_error: ChannelError
    quantity: str
    gain_ratio: float | None = None
    force_gain: float | None = None


@dataclass(frozen=True)
class InstrumentTerms:
    """Every output's terms (control output first), the outputs' calibration scales and where
    the point was measured (for messages)."""

    scales: tuple[tuple[float, float], ...]
    outputs: tuple[OutputTerms, ...]
    where: str

    def to_document(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_document(cls, doc: dict) -> "InstrumentTerms":
        outputs = tuple(OutputTerms(ChannelError(**o["force_error"]), ChannelError(**o["output_error"]), o["quantity"],
                                    o["gain_ratio"], o["force_gain"]) for o in doc["outputs"])
        return cls(tuple((float(lo), float(hi)) for lo, hi in doc["scales"]), outputs, doc["where"])


def scale_structure_terms(m: Measurement, scales: Sequence[tuple[float, float]]) -> Measurement:
    """``m`` with each output's bound times the largest of its calibration scale: the ratio is
    measured in that scale, and the bound's terms in the structure's units (``|W1|`` for the
    unmodelled modes) are too."""
    (first, rest) = scales[0], scales[1:]
    return dataclasses.replace(m, bound=m.bound * first[1],
                               others=tuple((g, b * scale[1]) for (g, b), scale in zip(m.others, rest)))


def with_instrument_terms(m: Measurement, force_amplitude_n: float, force: ChannelError,
                          outputs: Sequence[tuple[ChannelError, str]], where: str) -> Measurement:
    """``m`` with every output's instrument terms added to its bound
    (:func:`~setmem_hil.estimation.channel_errors.ratio_error_bound` with the force channel's
    ``force`` and each output's error, control output first), then converted to receptance
    where the output's sensor measures velocity or acceleration (its quantity)."""
    w = m.omega_rad_s

    def one(g: complex, bound: float, error: ChannelError, quantity: str) -> tuple[complex, float]:
        total = bound + ratio_error_bound(g, force_amplitude_n, force, error)
        if not math.isfinite(total):
            raise DataQualityError(f"{where}: the force at {w:g} rad/s ({force_amplitude_n:.3g} N) is not larger than its "
                                   f"channel's error ({force.absolute:.3g} N)")
        return to_receptance(g, w, quantity), total * abs(to_receptance(1.0, w, quantity))

    (first_error, first_quantity), rest = outputs[0], outputs[1:]
    response, bound = one(m.response, m.bound, first_error, first_quantity)
    others = tuple(one(g, b, error, quantity) for (g, b), (error, quantity) in zip(m.others, rest))
    return dataclasses.replace(m, response=response, bound=bound, others=others)


def apply_instrument_terms(m: Measurement, force_amplitude_n: float, terms: InstrumentTerms) -> Measurement:
    """``m`` (the ratio as the channels measured it) in its calibration scale, each output's
    ratio divided by the matched gain ratio where the match covers it (the bound never shrinks:
    it also holds ``|W1|``, in the structure's units), its instrument terms added, converted
    to receptance."""
    m = scale_structure_terms(m, terms.scales)
    points = []
    for (g, bound), out in zip([(m.response, m.bound), *m.others], terms.outputs):
        force_n = force_amplitude_n
        if out.gain_ratio is not None:
            g, bound, force_n = g / out.gain_ratio, bound / min(out.gain_ratio, 1.0), force_amplitude_n / out.force_gain
        one = with_instrument_terms(dataclasses.replace(m, response=g, bound=bound, others=()), force_n, out.force_error,
                                    [(out.output_error, out.quantity)], terms.where)
        points.append((one.response, one.bound))
    return dataclasses.replace(m, response=points[0][0], bound=points[0][1], others=tuple(points[1:]))
