"""``setmem-hil calibrate-channels PROCEDURE.toml``: measure the oscilloscope's channel match.

Before it: disconnect the shaker amplifier's input and the sensors from the oscilloscope, and
wire the generator's output through BNC tees to every channel the procedure uses (force and
responses; a sync wired to ``trigger_channel`` stays). The command plays a 1 kHz sine at most
``max_drive_v``, records it at every vertical scale the generator can fill and writes each
channel's gain at each scale relative to the force channel, with its guaranteed bound, to the
procedure's ``channel_match`` file (or ``--out``). Campaigns then divide every ratio by its
channels' gain ratio (docs/technician-guide.md section 10). The output is off at the end, read
back. Exit 0 written, 2 malformed procedure, 4 device fault (output off), 130 interrupted. With
``[backend.emulation]`` the emulated scope's channels are on a tee.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.console import Console
from rich.markup import escape

from setmem_hil.cli.campaign_options import SAFE_STOP


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("calibrate-channels", help="measure the oscilloscope's channel gains (generator on a tee to every channel)",
                              description="Measure each oscilloscope channel's gain at each V/div relative to the force channel, "
                              "with the generator's output wired to every channel used through a tee (amplifier and sensors "
                              "disconnected). Writes the procedure's channel_match file (or --out).")
    p.add_argument("procedure", metavar="PROCEDURE.toml", help="procedure file with an oscilloscope as force and response")
    p.add_argument("--out", metavar="FILE.json", help="where to write (default: the procedure's channel_match key)")
    p.add_argument("--seed", type=int, default=None, help="emulation only: the emulated unit (default: the procedure's seed)")
    p.set_defaults(func=run, interrupted=SAFE_STOP)


def run(args: argparse.Namespace) -> int:
    from setmem_hil.drivers.instruments.instrument_set import calibrate_scope_channels, channel_match_path
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.channel_match_file import write_channel_match
    from setmem_hil.io.procedure_file import load_procedure

    procedure = load_procedure(args.procedure)
    if procedure.backend.kind != "instruments":
        raise ProcedureError(args.procedure, "[backend] key 'kind'", f"calibrate-channels needs kind = \"instruments\", found {procedure.backend.kind!r}")
    scope = procedure.instruments[procedure.backend.force]
    out = Path(args.out) if args.out else channel_match_path(procedure, scope)
    if out is None:
        raise ProcedureError(args.procedure, f"[instruments.{scope.name}] key 'channel_match'", "missing: give it (or --out FILE.json)")
    console = Console(stderr=True, highlight=False)

    def progress(done: int, total: int) -> None:
        if console.is_terminal:  # a line that rewrites itself; nothing in a log
            console.print(f"  record {done}/{total}", end="\r" if done < total else "\n")

    if procedure.backend.emulation is not None:
        from setmem_hil.loopback.instrument_emulation import calibrate_emulated_channels

        match = calibrate_emulated_channels(procedure, procedure.seed if args.seed is None else args.seed, progress)
    else:
        match = calibrate_scope_channels(procedure, progress=progress)
    write_channel_match(match, out)
    table = Console(soft_wrap=True, highlight=False)
    table.print(escape(f"channel match of {match.identity} at {match.frequency_hz:g} Hz, relative to channel {match.reference[0]} "
                       f"at {match.reference[1]:g} V/div:"))
    for ch in sorted({g.channel for g in match.gains}):
        cells = [f"{g.scale_v:g} V/div {g.gain:.4f} +-{g.bound:.2%}" for g in match.gains if g.channel == ch]
        table.print(escape(f"  channel {ch}: " + "; ".join(cells)))
    table.print(escape(f"written to {out}; the generator's output is off. Reconnect the amplifier and the sensors before a campaign."))
    return 0
