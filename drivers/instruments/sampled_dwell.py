"""The sine dwell on a generator and a sampling instrument (an oscilloscope or a DAQ), as the
campaign sees it: the instruments' identities journaled with the run, and the generator's output
confirmed off by read-back (:class:`~setmem_hil.model.experiment.OutputConfirmingExperiment`,
like the lock-in rig): a pause waits for it, the journal records it at the end of every session."""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

from setmem_hil.drivers.instruments.phasor_dwell import to_receptance
from setmem_hil.drivers.sine_dwell import SineDwellExperiment
from setmem_hil.errors import DataQualityError
from setmem_hil.estimation.channel_errors import ChannelError, ratio_error_bound
from setmem_hil.identification.calibration_scale import ratio_scale
from setmem_hil.model.experiment import Measurement

__all__ = ["SampledDwellExperiment", "with_instrument_terms", "scale_structure_terms", "calibration_scales"]


def calibration_scales(force, responses) -> tuple[tuple[float, float], ...]:
    """Each output's calibration scale (control output first) from its sensors' channels (their
    ``calibration_uncertainty``): one unknown factor on all its points, which the campaign puts
    on the model (:mod:`~setmem_hil.identification.calibration_scale`), not in each bound."""
    return tuple(ratio_scale(force.calibration_uncertainty, ch.calibration_uncertainty) for ch in responses)


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


class SampledDwellExperiment(SineDwellExperiment):
    """A :class:`SineDwellExperiment` on a rig whose ``exciter`` is a
    :class:`~setmem_hil.drivers.instruments.drive_level.LevelledExciter`."""

    def __init__(self, rig, limits, settings=None, model=None, extra_bound=None, identities=None):
        super().__init__(rig, limits, settings, model, extra_bound)
        self.identities = dict(identities or {})

    @property
    def exciter(self) -> str:  # the generator's name, in messages (the dwell commands self.safe_exciter)
        return self.rig.exciter.source.name

    @property
    def calibration_scales(self) -> tuple[tuple[float, float], ...]:
        """Each output's calibration scale (the sensor's; see
        :class:`~setmem_hil.model.experiment.CalibrationScaledExperiment`)."""
        return self.rig.sensor.calibration_scales

    @property
    def output_confirmed_off(self) -> bool:
        return bool(self.rig.exciter.confirmed_off)

    def confirm_output_off(self) -> None:
        """Output off, read back (a fresh connection if the link failed); raises
        :class:`~setmem_hil.errors.OutputNotConfirmedOffError` when it cannot be confirmed."""
        self.rig.exciter.stop()
