"""``setmem-hil probe PROCEDURE.toml``: find the instruments before the first campaign.

Connects to every instrument the procedure names (``kind = "instruments"``), checks its
identity against its profile, reads the lock-ins' reference frequency, prints what it found and
never switches an output on: besides queries it sends one command, the exciter's output off (read
back), once the exciter's identity is confirmed; a run killed with the output on leaves it so. Exit 0 when every instrument answers with
its expected identity, 4 otherwise (2 for a malformed procedure or profile). With
``[backend.emulation]`` it probes the emulated instruments.
"""

from __future__ import annotations

import argparse

from rich.console import Console
from rich.markup import escape

EXIT_DEVICE = 4


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("probe", help="connect to the procedure's instruments, check identities; outputs stay off",
                              description="Connect to every instrument of a kind = \"instruments\" procedure, check its identity "
                              "against its profile and print what answered. No output is switched on. Exit 0 if all answer as "
                              "expected, 4 otherwise.")
    p.add_argument("procedure", metavar="PROCEDURE.toml", help="procedure file with [backend] kind = \"instruments\"")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.drivers.instruments.instrument_set import probe_instruments
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.procedure_file import load_procedure

    procedure = load_procedure(args.procedure)
    if procedure.backend.kind != "instruments":
        raise ProcedureError(args.procedure, "[backend] key 'kind'", f"probe needs kind = \"instruments\", found {procedure.backend.kind!r}")
    servers = []
    if procedure.backend.emulation is not None:
        from setmem_hil.loopback.instrument_emulation import start_emulators

        procedure, _, servers = start_emulators(procedure, procedure.seed)
    try:
        results = probe_instruments(procedure)
    finally:
        for server in servers:
            server.close()
    console = Console(soft_wrap=True, highlight=False)
    console.print(escape(f"instruments of {args.procedure}" + (" (emulated)" if servers else "") + ":"))
    for r in results:
        status = "[green]OK    [/]" if r.ok else "[red]FAILED[/]"
        console.print(f"  {status} " + escape(f"{r.name} ({r.role}, {r.model}) at {r.resource}: {r.answer}"))
    bad = [r for r in results if not r.ok]
    console.print(f"{len(results) - len(bad)} of {len(results)} instruments answered as expected; no output was switched on"
                  + ("; exciter output switched off" if any("output switched off" in r.answer for r in results) else ""),
                  highlight=False)
    return EXIT_DEVICE if bad else 0
