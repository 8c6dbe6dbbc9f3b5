"""The reference firmware's own C core, compiled on this machine and run from Python
(software in the loop).

:func:`firmware_library` compiles ``firmware/target_core.c`` and ``firmware/protocol.c`` (the
sources the board runs, :mod:`setmem_hil.firmware`) into a shared library with the system's C
compiler (``$CC``, else ``cc``), once per source content: the library is cached under the user's
cache directory by the hash of the sources and the flags. The same library holds
``sim_backends/sil_loop.c`` (simulation code, not firmware: the closed loop of a sampled
structure and the core, many samples per call, for :mod:`setmem_hil.sim_backends.emulated_target`). :class:`FirmwareCore` holds one
target's state (allocated opaquely: its size comes from the library, so no C struct is mirrored
here) and offers the two things a board does with it: a sample (:meth:`FirmwareCore.tick`) and a
command line (:meth:`FirmwareCore.command`). Nothing here changes what the C code computes.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from setmem_hil.errors import SetmemError
from setmem_hil.firmware import CORE_SOURCES, SOURCE_DIR

__all__ = ["FirmwareBuildError", "FirmwareCore", "firmware_library", "compiler", "CFLAGS"]

CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2", "-fPIC", "-shared")
"""The firmware must compile without a warning (the issue's ``-Werror``); ``-O2`` as a board build
would; no ``-ffast-math``: the sections must compute what ``scipy.signal.sosfilt`` computes."""

REPLY_CAPACITY = 256
SIL_SOURCE = Path(__file__).resolve().parent / "sil_loop.c"


class FirmwareBuildError(SetmemError):
    """The firmware's core could not be compiled here (no C compiler, or it failed)."""


def compiler() -> str | None:
    """The C compiler to use: ``$CC``, else ``cc`` on the path; None when there is none."""
    name = os.environ.get("CC", "cc")
    return shutil.which(name)


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "setmem-hil" / "firmware"


@lru_cache(maxsize=None)
def firmware_library() -> Path:
    """The compiled core (a shared library), built on first use and cached by content.

    Raises :class:`FirmwareBuildError` naming the compiler's first error line, or that there is
    no compiler (the emulated target needs one: install a C compiler, e.g. ``gcc``)."""
    cc = compiler()
    if cc is None:
        raise FirmwareBuildError(str(SOURCE_DIR), "", "no C compiler (cc, or $CC) to build the firmware's core; install one (e.g. gcc)")
    sources = [SOURCE_DIR / name for name in CORE_SOURCES] + [SIL_SOURCE]
    digest = hashlib.sha256()
    for path in [*sorted(SOURCE_DIR.glob("*.[ch]")), SIL_SOURCE]:
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    digest.update(" ".join(CFLAGS).encode() + sys.platform.encode())
    target = _cache_dir() / f"setmem_target_{digest.hexdigest()[:16]}.so"
    if target.is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:  # built beside, renamed into place: no half library
        built = Path(tmp) / target.name
        done = subprocess.run([cc, *CFLAGS, f"-I{SOURCE_DIR}", *map(str, sources), "-o", str(built), "-lm"], capture_output=True,
                              text=True)
        if done.returncode != 0:
            first = next((line for line in done.stderr.splitlines() if "error" in line), done.stderr.strip()[:200])
            raise FirmwareBuildError(str(SOURCE_DIR), "", f"the firmware's core did not compile: {first}")
        os.replace(built, target)
    return target


@lru_cache(maxsize=None)
def _library() -> ctypes.CDLL:
    lib = ctypes.CDLL(str(firmware_library()))
    lib.setmem_target_sizeof.restype = ctypes.c_size_t
    lib.setmem_target_init.argtypes = (ctypes.c_void_p, ctypes.c_double, ctypes.c_uint)
    lib.setmem_target_tick.argtypes = (ctypes.c_void_p, ctypes.c_double)
    lib.setmem_target_tick.restype = ctypes.c_double
    lib.setmem_target_force_sample.argtypes = (ctypes.c_void_p, ctypes.c_double)
    lib.setmem_target_force_sample.restype = None
    lib.setmem_target_filter.argtypes = (ctypes.c_void_p, ctypes.c_double)
    lib.setmem_target_filter.restype = ctypes.c_double
    lib.setmem_protocol_handle.argtypes = (ctypes.c_void_p, ctypes.c_char_p, ctypes.c_char_p, ctypes.c_size_t)
    lib.setmem_protocol_handle.restype = ctypes.c_size_t
    double_p = ctypes.POINTER(ctypes.c_double)
    lib.sil_run.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_size_t, double_p, double_p, double_p, ctypes.c_int, double_p,
                            double_p, double_p, ctypes.c_double, ctypes.c_size_t, double_p, ctypes.c_int, double_p, double_p, double_p, double_p)
    lib.sil_run.restype = ctypes.c_int
    return lib


class FirmwareCore:
    """One target of the firmware's core at ``fs_hz`` with ``delay_samples`` of computation delay."""

    def __init__(self, fs_hz: float, delay_samples: int):
        self._lib = _library()
        self._state = ctypes.create_string_buffer(int(self._lib.setmem_target_sizeof()))
        self._lib.setmem_target_init(self._state, float(fs_hz), int(delay_samples))
        self._reply = ctypes.create_string_buffer(REPLY_CAPACITY)

    def tick(self, y: float) -> float:
        """One sample: the sensor sample in, the drive sample out (``setmem_target_tick``)."""
        return self._lib.setmem_target_tick(self._state, float(y))

    def force_sample(self, f: float) -> None:
        """The force channel's sample, before the next tick (``setmem_target_force_sample``)."""
        self._lib.setmem_target_force_sample(self._state, float(f))

    def filter(self, y: float) -> float:
        """The compensator alone, one sample (``setmem_target_filter``)."""
        return self._lib.setmem_target_filter(self._state, float(y))

    def run_loop(self, n: int, Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, lagged: bool, x: np.ndarray, r: np.ndarray,
                 noise: np.ndarray, dac_gain: float, pipeline: np.ndarray, held_force: np.ndarray | None = None,
                 force_noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``n`` samples of the closed loop in C (``sim_backends/sil_loop.c``); ``x`` and
        ``pipeline`` are updated in place; returns ``(u, y)``. ``held_force`` (one element,
        updated in place): the board has a force channel, which reads the drive held since the
        previous sample (None: no force channel), plus ``force_noise`` (its ADC's noise, per sample)."""
        def ptr(a: np.ndarray):
            return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))

        Ad, Bd, C = (np.ascontiguousarray(a, dtype=float) for a in (Ad, Bd, C))
        r, noise = np.ascontiguousarray(r, dtype=float), np.ascontiguousarray(noise, dtype=float)
        u, y = np.empty(n), np.empty(n)
        force_noise = np.zeros(n) if force_noise is None else np.ascontiguousarray(force_noise, dtype=float)
        status = self._lib.sil_run(self._state, n, x.size, ptr(Ad), ptr(Bd), ptr(C), int(lagged), ptr(x), ptr(r), ptr(noise),
                                   float(dac_gain), pipeline.size, ptr(pipeline), int(held_force is not None),
                                   ptr(held_force if held_force is not None else np.zeros(1)), ptr(force_noise), ptr(u), ptr(y))
        if status != 0:
            raise ValueError(f"the loop harness holds at most 128 states and 65 samples of extra delay (got {x.size}, {pipeline.size})")
        return u, y

    def command(self, line: str) -> str:
        """One protocol line in, its reply out (``setmem_protocol_handle``)."""
        n = self._lib.setmem_protocol_handle(self._state, line.encode("ascii"), self._reply, REPLY_CAPACITY)
        return self._reply.raw[:n].decode("ascii")
