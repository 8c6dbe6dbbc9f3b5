"""Command-line entry point of setmem-hil.

Subcommands live one per module in :mod:`setmem_hil.cli.commands` and are discovered here.

Exit codes (public contract): 0 success; 2 malformed input (the message names file, line or
key); 3 data inconsistent with the prior (the message names the frequencies); 4 device fault
(the message says whether the exciter's output was confirmed off, and when it could not be:
"switch it off at the instrument"); 130 interrupted or aborted (the exciter is at zero and
the journal closed); 1 any other failure. Every failure is reported as one line
``setmem-hil: ...`` on stderr; ``--debug`` adds the Python traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from setmem_hil import __version__
from setmem_hil.errors import (
    CampaignAborted,
    CampaignReplayError,
    DeviceError,
    InconsistentDataError,
    InputFormatError,
    JournalError,
    RunInterrupted,
    MeasuredLimitError,
    SafetyLimitError,
    SetmemError,
    SolverError,
)

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_BAD_INPUT = 2
EXIT_INCONSISTENT = 3
EXIT_DEVICE = 4
EXIT_INTERRUPTED = 130

DESCRIPTION = (
    "setmem-hil: drive a flexible structure with sinusoids, identify a modal model with guaranteed "
    "parameter intervals, design an H2 compensator, measure robust performance with mixed mu, and choose "
    "the next excitation frequency until mu-bar < 1."
)


from setmem_hil.cli.campaign_options import SAFE_STOP  # noqa: E402 (re-exported: commands name it)


def exit_code_and_message(exc: BaseException, interrupted: str = "interrupted") -> tuple[int, str]:
    """The exit code and the one-line message for an exception reaching the CLI.

    ``interrupted`` is the command's own account of what it left safe (``SAFE_STOP`` for the
    commands that drive an exciter; commands register it with ``set_defaults(interrupted=...)``).
    """
    if isinstance(exc, InconsistentDataError):
        return EXIT_INCONSISTENT, f"data inconsistent with the prior: {exc}"
    if isinstance(exc, MeasuredLimitError):  # the output was on: a rig fault (exit 4), with what the clean-up confirmed
        safety = getattr(exc, "safety_note", "")
        return EXIT_DEVICE, "; ".join(part for part in (f"safety stop: {exc}", safety) if part)
    if isinstance(exc, (InputFormatError, SafetyLimitError)):
        return EXIT_BAD_INPUT, str(exc)
    if isinstance(exc, DeviceError):
        # what the clean-up achieved, as the session established it (never claimed when unknown)
        safety = getattr(exc, "safety_note", "")
        hint = getattr(exc, "resume_hint", "")
        return EXIT_DEVICE, "; ".join(part for part in (f"device fault: {exc}", safety, hint) if part)
    if isinstance(exc, (RunInterrupted, CampaignAborted)) and exc.args:
        return EXIT_INTERRUPTED, str(exc)
    if isinstance(exc, (KeyboardInterrupt, CampaignAborted)):
        return EXIT_INTERRUPTED, interrupted
    if isinstance(exc, CampaignReplayError):
        return EXIT_FAILURE, f"cannot replay the stored run: {exc}"
    if isinstance(exc, SolverError):
        return EXIT_FAILURE, f"numerical failure: {exc}"
    if isinstance(exc, JournalError):
        return EXIT_FAILURE, f"journal: {exc}"
    if isinstance(exc, SetmemError):
        return EXIT_FAILURE, str(exc)
    if isinstance(exc, OSError):
        where = f" {exc.filename}" if getattr(exc, "filename", None) else ""
        return EXIT_FAILURE, f"cannot access{where}: {exc.strerror or exc}"
    return EXIT_FAILURE, f"internal error ({type(exc).__name__}: {exc}); rerun with --debug for the traceback"


def one_line(text: str) -> str:
    return " ".join(str(text).split())


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the command ``argv`` asks for is imported (the others are listed by name
    and help, :data:`setmem_hil.cli.commands.COMMANDS`), so ``--help`` answers at once."""
    parser = argparse.ArgumentParser(
        prog="setmem-hil", description=DESCRIPTION,
        epilog="run 'setmem-hil COMMAND --help' for a command's options; exit codes: 0 ok, 2 malformed input, "
        "3 data inconsistent with the prior, 4 device fault, 130 interrupted, 1 other",
    )
    parser.add_argument("--version", action="version", version=f"setmem-hil {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the Python traceback of a failure")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    from setmem_hil.cli.commands import COMMANDS

    wanted = next((a for a in (argv or []) if not a.startswith("-")), None)
    for name, (module, summary) in sorted(COMMANDS.items()):
        if name == wanted or argv is None:
            importlib.import_module(f"setmem_hil.cli.commands.{module}").register(subparsers)
        else:
            subparsers.add_parser(name, help=summary)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv  # also honoured after the command name
    if debug:
        argv = [a for a in argv if a != "--debug"]
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args) or 0)
    except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 - every failure becomes one line and an exit code
        code, message = exit_code_and_message(exc, getattr(args, "interrupted", "interrupted"))
        hint = getattr(exc, "resume_hint", "")
        if hint and hint not in message:  # what a stopped run left safe, and how to go on
            message = f"{message}; {hint}"
        if debug:
            traceback.print_exc()
        line = one_line(message)
        # a message naming its command ("setmem-hil controller: ...") keeps one prefix:
        # "setmem-hil: controller: ..." (issue 40: it printed "setmem-hil: setmem-hil controller: ...")
        print(f"setmem-hil: {line.removeprefix('setmem-hil ')}", file=sys.stderr)
        return code


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
