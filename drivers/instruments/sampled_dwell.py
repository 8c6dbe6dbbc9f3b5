"""The sine dwell on a generator and a sampling instrument (an oscilloscope or a DAQ), as the
campaign sees it: the instruments' identities journaled with the run, and the generator's output
confirmed off by read-back (:class:`~setmem_hil.model.experiment.OutputConfirmingExperiment`,
like the lock-in rig): a pause waits for it, the journal records it at the end of every session."""

from __future__ import annotations

from setmem_hil.drivers.sine_dwell import SineDwellExperiment

__all__ = ["SampledDwellExperiment"]


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
    def output_confirmed_off(self) -> bool:
        return bool(self.rig.exciter.confirmed_off)

    def confirm_output_off(self) -> None:
        """Output off, read back (a fresh connection if the link failed); raises
        :class:`~setmem_hil.errors.OutputNotConfirmedOffError` when it cannot be confirmed."""
        self.rig.exciter.stop()
