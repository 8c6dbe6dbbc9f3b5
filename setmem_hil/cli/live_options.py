"""``--live``, ``--live-port``, ``--live-host`` of ``run`` and ``demo``: the live view beside a campaign."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path
from typing import Iterator

__all__ = ["add_live_options", "live_view"]


def add_live_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--live", action="store_true", help="serve a live view of the campaign (prints its URL with a token)")
    p.add_argument("--live-port", type=int, default=0, metavar="N", help="port of the live view (default: a free one)")
    p.add_argument("--live-host", default="127.0.0.1", metavar="HOST",
                   help="address to bind the live view to (default 127.0.0.1: this computer only)")


@contextlib.contextmanager
def live_view(args: argparse.Namespace, run_dir: Path) -> Iterator[dict]:
    """Keyword arguments for the session (``control``, ``observers``): empty without ``--live``."""
    if not getattr(args, "live", False):
        yield {}
        return
    from setmem_hil.live.control import LiveControl
    from setmem_hil.live.server import LiveServer

    control = LiveControl()
    with LiveServer(run_dir, control, host=args.live_host, port=args.live_port) as server:
        print(f"live view: {server.url}", flush=True)
        yield {"control": control, "observers": [server.observe]}
