"""Command-line entry point ``setmem-hil``.

Subcommands live one per module in :mod:`setmem_hil.cli.commands` and are discovered here.
Exit codes (public contract): 0 success; 2 malformed input (the message names file, line or
key); 3 data inconsistent with the prior (the message names the frequencies); 4 device fault
(the exciter was commanded to zero); 130 interrupted (Ctrl-C; commands that drive a device zero the exciter and close the journal);
1 any other failure.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from setmem_hil import __version__
from setmem_hil.errors import DeviceError, InconsistentDataError, InputFormatError, SafetyLimitError

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_BAD_INPUT = 2
EXIT_INCONSISTENT = 3
EXIT_DEVICE = 4
EXIT_INTERRUPTED = 130


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="setmem-hil", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"setmem-hil {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    import setmem_hil.cli.commands as commands

    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"setmem_hil.cli.commands.{info.name}")
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_BAD_INPUT
    try:
        return int(args.func(args) or 0)
    except InconsistentDataError as exc:
        print(f"setmem-hil: data inconsistent with the prior: {exc}", file=sys.stderr)
        return EXIT_INCONSISTENT
    except (InputFormatError, SafetyLimitError) as exc:
        print(f"setmem-hil: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except DeviceError as exc:
        print(f"setmem-hil: device fault: {exc} (exciter commanded to zero)", file=sys.stderr)
        return EXIT_DEVICE
    except KeyboardInterrupt:
        # commands that drive a device or write a journal say themselves what they left safe
        print("setmem-hil: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
