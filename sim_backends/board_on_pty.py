"""The reference firmware as a board on a serial port, with a simulated structure as its rig.

:class:`BoardOnPty` compiles the firmware as a board would (``main.c``, the core, the protocol)
with its PC port (``firmware/host/hal_host.c``, ``-DSETMEM_HOST_EXTERNAL_RIG``) and
``sim_backends/structure_hal.c`` as the sensor and drive: the structure (all its modes,
discretised for the held drive) in closed loop with the firmware, sampled on the wall clock
sped up ``speedup`` times. The process sits on the controller side of a pseudo-terminal; the
host opens the device side (:attr:`BoardOnPty.port`) as it would a board's serial port
(``[target] kind = "serial"``, measured by the target's own analyser). For tests and for trying
the serial path without a board (Linux).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from setmem_hil.errors import SetmemError
from setmem_hil.firmware import BOARD_SOURCES, SOURCE_DIR
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.emulated_target import held_discretisation
from setmem_hil.sim_backends.firmware_core import CFLAGS, FirmwareBuildError, compiler

__all__ = ["BoardOnPty"]

STRUCTURE_HAL = Path(__file__).resolve().parent / "structure_hal.c"


class BoardOnPty:
    """The firmware at ``fs_hz`` with ``delay_samples`` on a pseudo-terminal, its rig ``structure``
    (sensor noise ``noise_rms``); a context manager: the process is killed on exit."""

    def __init__(self, structure: ModalParameters, fs_hz: float, delay_samples: int, *, speedup: float = 1.0,
                 noise_rms: float = 0.0, seed: int = 1):
        if not sys.platform.startswith("linux"):
            raise SetmemError("a board on a pseudo-terminal: Linux only")
        self._folder = tempfile.TemporaryDirectory(prefix="setmem-board-")
        folder = Path(self._folder.name)
        binary = self._build(folder, fs_hz, delay_samples)
        plant = folder / "plant.txt"
        Ad, Bd, C, _ = held_discretisation(structure, fs_hz, None)
        plant.write_text(" ".join(map(repr, [Ad.shape[0], float(noise_rms), int(seed)])) + "\n"
                         + " ".join(repr(float(v)) for v in np.concatenate([Ad.ravel(), Bd.ravel(), C[0].ravel()])) + "\n")
        import tty

        self._controller, self._device = os.openpty()
        tty.setraw(self._controller)
        env = {**os.environ, "SETMEM_HOST_PLANT": str(plant), "SETMEM_HOST_SPEEDUP": repr(float(speedup))}
        self._process = subprocess.Popen([str(binary)], stdin=self._controller, stdout=self._controller, env=env)
        self.port = os.ttyname(self._device)

    @staticmethod
    def _build(folder: Path, fs_hz: float, delay_samples: int) -> Path:
        cc = compiler()
        if cc is None:
            raise FirmwareBuildError(str(SOURCE_DIR), "", "no C compiler (cc, or $CC) to build the firmware; install one (e.g. gcc)")
        binary = folder / "board"
        flags = [f for f in CFLAGS if f not in ("-shared", "-fPIC")]
        sources = [str(SOURCE_DIR / name) for name in BOARD_SOURCES] + [str(SOURCE_DIR / "host" / "hal_host.c"), str(STRUCTURE_HAL)]
        done = subprocess.run([cc, *flags, f"-I{SOURCE_DIR}", f"-DSETMEM_FS_HZ={float(fs_hz)!r}", f"-DSETMEM_DELAY_SAMPLES={int(delay_samples)}",
                               "-DSETMEM_HOST_EXTERNAL_RIG", *sources, "-o", str(binary), "-lm"], capture_output=True, text=True)
        if done.returncode != 0:
            first = next((line for line in done.stderr.splitlines() if "error" in line), done.stderr.strip()[:200])
            raise FirmwareBuildError(str(SOURCE_DIR), "", f"the board build failed: {first}")
        return binary

    def kill(self) -> None:
        """The board loses power: the process ends, the line goes silent."""
        if self._process.poll() is None:
            self._process.kill()
            self._process.wait()

    def __enter__(self) -> "BoardOnPty":
        return self

    def __exit__(self, *exc) -> None:
        self.kill()
        for fd in (self._controller, self._device):
            try:
                os.close(fd)
            except OSError:
                pass
        self._folder.cleanup()
