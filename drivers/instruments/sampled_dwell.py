"""The sine dwell on a generator and a sampling instrument (an oscilloscope or a DAQ), as the
campaign sees it: the instruments' identities journaled with the run, and the generator's output
confirmed off by read-back (:class:`~setmem_hil.model.experiment.OutputConfirmingExperiment`,
like the lock-in rig): a pause waits for it, the journal records it at the end of every session."""

from __future__ import annotations

from setmem_hil.drivers.sine_dwell import SineDwellExperiment
from setmem_hil.estimation.instrument_terms import scale_structure_terms, with_instrument_terms  # noqa: F401 - re-exported
from setmem_hil.identification.calibration_scale import ratio_scale

__all__ = ["SampledDwellExperiment", "with_instrument_terms", "scale_structure_terms", "calibration_scales"]


def calibration_scales(force, responses) -> tuple[tuple[float, float], ...]:
    """Each output's calibration scale (control output first) from its sensors' channels (their
    ``calibration_uncertainty``): one unknown factor on all its points, which the campaign puts
    on the model (:mod:`~setmem_hil.identification.calibration_scale`), not in each bound."""
    return tuple(ratio_scale(force.calibration_uncertainty, ch.calibration_uncertainty) for ch in responses)


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
