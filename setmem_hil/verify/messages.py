"""The verification plan's requests to the run engine (its commands: :mod:`setmem_hil.verify.target_service`).

=========================  ===================================================  =================
request                    what the engine does                                 reply
=========================  ===================================================  =================
:class:`IdentifyTarget`    ``*IDN?``, checked against the procedure's rate       ``TargetIdentity``
:class:`LoadCompensator`   drive limit, watchdog, sections; checksum read back  the checksum
:class:`Engage`            engage at a gain, confirmed by ``STATE?``             ``TargetState``
:class:`InjectAndRecord`   generator on at the summing junction, settle while   ``LoopRecord``
                           watching the target, record
:class:`Bypass`            generator off, bypass, both confirmed                 ``TargetState``
=========================  ===================================================  =================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["IdentifyTarget", "LoadCompensator", "Engage", "InjectAndRecord", "Bypass"]


@dataclass(frozen=True)
class IdentifyTarget:
    pass


@dataclass(frozen=True)
class LoadCompensator:
    sos: np.ndarray
    gain: float


@dataclass(frozen=True)
class Engage:
    gain: float


@dataclass(frozen=True)
class InjectAndRecord:
    omega_rad_s: float
    amplitude: float
    settle_s: float
    record_s: float
    label: str = ""  # a record that is not a point ("baseline"): kept under this name, not numbered


@dataclass(frozen=True)
class Bypass:
    reason: str = ""
