"""Typed exceptions of setmem-hil.

Every error subclasses a built-in (``ValueError``, ``RuntimeError``, ``TimeoutError``) so callers
may catch either. Messages say what was wrong and where (file, line or key, frequency).
The CLI maps them to exit codes (see ``setmem_hil.cli.main``): 2 for malformed input,
3 for data inconsistent with the prior, 4 for device faults, 130 for an interrupted or aborted
campaign, 1 for anything else. Every error class of the package lives in this module.
"""

from __future__ import annotations

from typing import Sequence


class SetmemError(Exception):
    """Base class of all setmem-hil errors."""


class InputFormatError(SetmemError, ValueError):
    """A malformed input file or argument.

    Parameters
    ----------
    source : str
        File name (or argument name) the problem is in.
    location : str
        Where in it: ``"line 7"``, ``"[[mode]] 2"``, ``"key 'gamma'"``; may be empty.
    problem : str
        What rule was broken and what was found.
    """

    def __init__(self, source: str, location: str, problem: str):
        self.source = source
        self.location = location
        self.problem = problem
        where = f"{source}: {location}: " if location else f"{source}: "
        super().__init__(where + problem)


class ProcedureError(InputFormatError):
    """A procedure file that does not validate (names file, table and key)."""


class InconsistentDataError(SetmemError, ValueError):
    """No parameters fit the data and the prior: names the conflicting frequencies.

    Attributes
    ----------
    omegas_rad_s : tuple of float
        Frequencies of the data points involved in the conflict.
    mode_index : int or None
        Mode (0-based) whose one-mode problem became infeasible, if known.
    suspects_rad_s : tuple of float
        Points whose removal alone restores consistency of that mode's problem.
    """

    def __init__(self, message: str, omegas_rad_s: Sequence[float] = (), mode_index: int | None = None,
                 suspects_rad_s: Sequence[float] = ()):
        self.omegas_rad_s = tuple(float(w) for w in omegas_rad_s)
        self.mode_index = mode_index
        self.suspects_rad_s = tuple(float(w) for w in suspects_rad_s)
        super().__init__(message)


class SolverError(SetmemError, RuntimeError):
    """The conic solver failed for a reason other than infeasibility."""


class DeviceError(SetmemError, RuntimeError):
    """A device or transport fault (the exciter has been commanded to zero)."""


class DeviceDisconnectedError(DeviceError):
    """The connection to a device or bus was lost (the device's watchdog zeroes its output).

    Transports do not retry on the same connection; the rig's ``reconnect()`` opens a new one.
    """


class DeviceRejectedError(DeviceError):
    """A device refused a request: outside its limits, wrong state, or a protocol exception.

    Parameters
    ----------
    code : str or int
        Machine-readable reason as the device gave it (``"range"``, a Modbus exception code).
    message : str
        The full human-readable message.
    retryable : bool
        Whether repeating the same request may succeed (e.g. Modbus SERVER DEVICE BUSY).
    seq : int, optional
        Sequence number of the rejected request, where the wire format has one.
    """

    def __init__(self, code, message: str, *, retryable: bool = False, seq: int | None = None):
        self.code = code
        self.retryable = retryable
        self.seq = seq
        super().__init__(message)


class ModbusExceptionError(DeviceRejectedError):
    """A Modbus exception response (``code`` as in the Modbus application protocol spec)."""

    RETRYABLE = (0x05, 0x06)  # ACKNOWLEDGE (processing), SERVER DEVICE BUSY

    def __init__(self, function_code: int, code: int, where: str = "Modbus"):
        self.function_code = function_code
        super().__init__(code, f"{where}: exception response to function {function_code} with code {code}",
                         retryable=code in self.RETRYABLE)


class OutputNotConfirmedOffError(DeviceError):
    """Switching an exciter's output off could not be confirmed, on the open link nor on a fresh
    one: the output may still be on. The message says to switch it off at the instrument."""

    def __init__(self, instrument: str, message: str):
        self.instrument = instrument
        super().__init__(message)


class DeviceIdentityError(DeviceError):
    """An instrument answered its identity query with something other than what the profile expects."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """A device stopped answering within its timeout."""


class FrameError(DeviceError, ValueError):
    """A garbled, truncated or otherwise undecodable frame on a transport."""


class SafetyLimitError(SetmemError, ValueError):
    """A command that would exceed the procedure's amplitude or frequency limits (never sent)."""


class MeasuredLimitError(SafetyLimitError):
    """A measurement exceeded a safety limit while the output was on (a force sensor declared 10x
    too sensitive, a response over ``[safety] max_response``): the output was switched off. A rig
    fault, not malformed input: the CLI exits 4, as for a device fault (issue 63)."""


class DataQualityError(SetmemError, RuntimeError):
    """A dwell whose samples are unusable (clipped, NaN, timestamp jumps); it is discarded."""


class JournalError(SetmemError, RuntimeError):
    """The journal cannot be opened, is locked by another run, or holds inconsistent records."""


class ReplayError(SetmemError, RuntimeError):
    """A stopped run whose stored record does not match what its plan does now (a resumed
    campaign's journal: a measurement at another frequency, an iteration choosing differently).

    Not malformed input: the stored run and the procedure (or software) disagree. Exit 1; the
    message names the journal and the measurement.
    """

    def __init__(self, source: str, location: str, problem: str):
        self.source, self.location, self.problem = source, location, problem
        super().__init__(f"{source}: {location}: {problem}")


CampaignReplayError = ReplayError
"""The campaign's name for :class:`ReplayError` (the same class)."""


class RunAborted(SetmemError, RuntimeError):
    """A run stopped on request (an operator's Abort); the run engine's ``stop`` document says ``abort``."""


class CampaignAborted(RunAborted):
    """A campaign stopped on request (live-view Abort): exciter off, journal closed, exit 130."""


class RunInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped a campaign after it made the rig safe; the message says what was
    kept and how to resume (exit 130). A ``KeyboardInterrupt``, so code that handles Ctrl-C sees it."""
