"""How fast the command line answers (issue 46): ``--help``, ``--version``, ``sweep --help``,
``run --check`` and the time until a run's journal exists, each the median of five fresh
processes (the interpreter's own start measured alone for comparison). Goals: ``--help`` under
0.5 s; ``--version`` and ``run --check`` well under a second; the journal within a second.

    .venv/bin/python benchmarks/cli_startup.py
"""

from __future__ import annotations

import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).with_name("setmem-hil")
PROCEDURE = REPO / "setmem_hil" / "procedures" / "beam_6_3_2.toml"


def timed(argv: list[str], repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(argv, capture_output=True, check=False)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def journal_after(repeats: int = 3) -> float:
    """Seconds from the start of ``setmem-hil run`` until its journal exists (the run is then stopped)."""
    times = []
    for _ in range(repeats):
        out = Path(tempfile.mkdtemp()) / "run"
        t0 = time.perf_counter()
        child = subprocess.Popen([str(EXE), "run", str(PROCEDURE), "--out", str(out), "--quiet"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        while not (out / "journal.sqlite").exists() and child.poll() is None:
            time.sleep(0.005)
        times.append(time.perf_counter() - t0)
        child.terminate()
        child.wait()
        shutil.rmtree(out.parent, ignore_errors=True)
    return statistics.median(times)


def main() -> None:
    rows = [
        ("python -c pass (the interpreter alone)", timed([sys.executable, "-c", "pass"])),
        ("setmem-hil --help", timed([str(EXE), "--help"])),
        ("setmem-hil --version", timed([str(EXE), "--version"])),
        ("setmem-hil sweep --help", timed([str(EXE), "sweep", "--help"])),
        ("setmem-hil run --check beam_6_3_2.toml", timed([str(EXE), "run", "--check", str(PROCEDURE)])),
        ("setmem-hil run: until journal.sqlite exists", journal_after()),
    ]
    for name, seconds in rows:
        print(f"{name:48s} {seconds:6.3f} s")


if __name__ == "__main__":
    main()
