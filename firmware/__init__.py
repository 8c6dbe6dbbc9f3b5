"""The reference firmware's C99 sources (``setmem_hil.firmware``): a real-time target for the
exported compensator, its line protocol and a three-function hardware layer
(docs/real-time-target.md). Python code here only names the files; the emulated target
(:mod:`setmem_hil.sim_backends.firmware_core`) compiles the core and runs it."""

from __future__ import annotations

from pathlib import Path

SOURCE_DIR = Path(__file__).resolve().parent
CORE_SOURCES = ("target_core.c", "protocol.c")
"""What a host links to run the target's core (no hardware layer, no main loop)."""
BOARD_SOURCES = ("main.c", *CORE_SOURCES)
"""What a board port compiles with its own ``hal.c`` (``host/hal_host.c``: the PC port)."""

__all__ = ["SOURCE_DIR", "CORE_SOURCES", "BOARD_SOURCES"]
