"""``setmem-hil view DIR``: the live view of a run going on in another process, or finished (read-only)."""

from __future__ import annotations

import argparse
import threading

from setmem_hil.errors import InputFormatError

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("view", help="watch a run (going on elsewhere, or finished) in the browser, read-only",
                              description="Serve the live view of the run in DIR from its journal, read-only: the page "
                              "follows a campaign another setmem-hil process runs, or shows a finished one. Ctrl-C stops serving.")
    p.add_argument("run_dir", metavar="DIR", help="run directory (holds journal.sqlite)")
    p.add_argument("--port", type=int, default=0, metavar="N", help="port (default: a free one)")
    p.add_argument("--host", default="127.0.0.1", metavar="HOST", help="address to bind to (default 127.0.0.1)")
    p.set_defaults(func=run, interrupted="view stopped")


def run(args: argparse.Namespace) -> int:
    from setmem_hil.io.journal import journal_path
    from setmem_hil.live.server import LiveServer

    if not journal_path(args.run_dir).is_file():
        raise InputFormatError(str(args.run_dir), "", "no journal here (expected a run directory holding journal.sqlite)")
    from setmem_hil.io.journal import read_snapshot

    read_snapshot(args.run_dir)  # a damaged or foreign journal is refused here, not served as "starting" forever
    with LiveServer(args.run_dir, None, host=args.host, port=args.port) as server:
        print(f"live view: {server.url}", flush=True)
        print("read-only view; Ctrl-C stops serving", flush=True)
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            return 0
    return 0
