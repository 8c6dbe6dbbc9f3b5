"""Safety in the driver layer: limits checked before sending, output to zero on every abort path.

:func:`check_sine_command` raises :class:`setmem_hil.errors.SafetyLimitError` for a command
outside the procedure's :class:`setmem_hil.io.procedure.SafetyLimits` *before* anything is sent.
:class:`SafeExciter` wraps any :class:`~setmem_hil.drivers.protocols.Exciter` so that every
``set_sine`` is checked first. :func:`output_guard` is the context manager that commands zero
output when its block raises anything (device errors, timeouts, ``KeyboardInterrupt``) and on
normal exit; a failing ``stop`` during an abort never hides the original exception.
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import Iterator

from setmem_hil.drivers.protocols import Exciter, RecordedMultisineExciter
from setmem_hil.errors import SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits

log = logging.getLogger(__name__)


def _prefix(where: str) -> str:
    return f"{where}: " if where else ""


def check_sine_command(limits: SafetyLimits, omega_rad_s: float, amplitude_n: float, where: str = "") -> None:
    """Raise SafetyLimitError unless ``omega`` and ``amplitude`` are inside the limits.

    One rule for every transport and instrument; ``where`` (e.g. the transport) prefixes the
    message.

    Parameters
    ----------
    limits : SafetyLimits
    omega_rad_s : float
        Must be finite and in ``[omega_min_rad_s, omega_max_rad_s]``.
    amplitude_n : float
        Must be finite and in ``[0, max_amplitude_n]``.
    where : str, optional
        Names the device or transport in the message.
    """
    w, a = float(omega_rad_s), float(amplitude_n)
    if not math.isfinite(w) or not limits.omega_min_rad_s <= w <= limits.omega_max_rad_s:
        raise SafetyLimitError(
            f"{_prefix(where)}sine command: omega {w!r} rad/s outside the procedure's safety limits "
            f"[{limits.omega_min_rad_s:g}, {limits.omega_max_rad_s:g}] rad/s; nothing was sent"
        )
    if not math.isfinite(a) or not 0.0 <= a <= limits.max_amplitude_n:
        raise SafetyLimitError(
            f"{_prefix(where)}sine command: amplitude {a!r} N outside the procedure's safety limit "
            f"[0, {limits.max_amplitude_n:g}] N; nothing was sent"
        )


def check_dwell(limits: SafetyLimits, dwell_s: float, where: str = "") -> None:
    """Raise SafetyLimitError unless ``0 < dwell_s <= max_dwell_s`` (the one duration rule).

    Used for planned dwells and for every acquisition a transport is asked for, before anything
    is sent; ``where`` names the device or transport in the message.
    """
    d = float(dwell_s)
    if not math.isfinite(d) or d <= 0 or d > limits.max_dwell_s:
        raise SafetyLimitError(
            f"{_prefix(where)}dwell of {d!r} s outside (0, {limits.max_dwell_s:g}] s (the procedure's max_dwell_s); nothing sent"
        )


def safe_stop(exciter: Exciter) -> BaseException | None:
    """Command zero output; never raises (returns the exception a failing stop raised)."""
    try:
        exciter.stop()
    except BaseException as exc:  # noqa: BLE001 - a failing stop must not mask the abort cause
        log.error("commanding the exciter to zero failed: %r", exc)
        return exc
    return None


class SafeExciter:
    """An exciter whose commands are checked against the safety limits before sending.

    Parameters
    ----------
    exciter : Exciter
        The transport's exciter.
    limits : SafetyLimits
    """

    def __init__(self, exciter: Exciter, limits: SafetyLimits):
        self.inner = exciter
        self.limits = limits

    def set_sine(self, omega_rad_s: float, amplitude_n: float) -> None:
        check_sine_command(self.limits, omega_rad_s, amplitude_n)
        self.inner.set_sine(omega_rad_s, amplitude_n)

    def set_multisine(self, multisine, duration_s: float) -> None:
        """Play a :class:`setmem_hil.estimation.multisine.Multisine` for at most ``duration_s``.

        Every line must be inside the frequency limits and the *peak of the sum* over the
        record (its guaranteed bound) within ``max_amplitude_n``; nothing is sent otherwise.
        """
        for w in multisine.omegas_rad_s:
            check_sine_command(self.limits, w, 0.0)
        peak = multisine.peak_bound(duration_s)
        if not peak <= self.limits.max_amplitude_n * (1 + 1e-9):
            raise SafetyLimitError(
                f"multisine command: peak force {peak:.4g} N over {duration_s:.4g} s above the procedure's safety limit "
                f"{self.limits.max_amplitude_n:g} N; nothing was sent"
            )
        if isinstance(self.inner, RecordedMultisineExciter):  # the whole record as one waveform
            self.inner.set_multisine_record(multisine, duration_s)
            return
        self.inner.set_multisine(multisine.omegas_rad_s, multisine.amplitudes_n, multisine.phases_rad)

    def stop(self) -> None:
        self.inner.stop()


@contextlib.contextmanager
def output_guard(exciter: Exciter) -> Iterator[Exciter]:
    """Context manager: zero output when the block ends, however it ends.

    On an exception (including ``KeyboardInterrupt``) the exciter is stopped and the exception
    re-raised; a failing stop is logged and does not replace it. On normal exit the exciter is
    stopped and a failing stop propagates.
    """
    try:
        yield exciter
    except BaseException:
        safe_stop(exciter)
        raise
    exciter.stop()
