"""Issue 40 item 3: a rig PC runs Windows. What is OS-specific lives in
:mod:`setmem_hil.os_support`; everything else uses what every OS has.

CI has no Windows, so the tests take away the POSIX-only names the code once relied on
(``socket.MSG_DONTWAIT``, the ``fcntl`` module, ``signal.SIGKILL``) in a fresh interpreter and
run what used them: an emulated instrument campaign through PyVISA sockets, the run lock
between two processes, the sweep's kill of its workers.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# run first in each child: the names Windows lacks are gone, as on a Windows interpreter
WITHOUT_POSIX_NAMES = textwrap.dedent("""
    import signal, socket, sys
    import serial  # pyserial's POSIX backend needs fcntl (on Windows pyserial loads its win32 backend instead)
    sys.modules["fcntl"] = None  # import fcntl -> ImportError
    for module, name in ((socket, "MSG_DONTWAIT"), (signal, "SIGKILL")):
        if hasattr(module, name):
            delattr(module, name)
""")


def _child(code: str, *args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", WITHOUT_POSIX_NAMES + textwrap.dedent(code), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, stdin=subprocess.PIPE, text=True, **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize("procedure", ["instruments_emulated.toml", "instruments_scope_emulated.toml"])
def test_an_emulated_instrument_campaign_runs_without_the_posix_only_names(tmp_path, procedure):
    """33500B + SR830 + SR860, and 33500B + DS1104Z (binary records, its channel match measured
    on the emulated tee first), over PyVISA sockets (every query peeks for a closed peer and for
    stale bytes), the run lock held throughout: exit 0, the goal reached."""
    import shutil

    shutil.copy(REPO / "procedures" / procedure, tmp_path / procedure)  # a channel match is measured beside it
    child = _child("""
        from setmem_hil.cli.main import main
        sys.exit(main(["run", sys.argv[1], "--out", sys.argv[2], "--quiet"]))
    """, str(tmp_path / procedure), str(tmp_path / "run"))
    out, err = child.communicate(timeout=600)
    assert child.returncode == 0, err[-2000:]
    import json

    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["reached_goal"]


LOCK_HOLDER = """
    import sys
    from pathlib import Path
    from setmem_hil import os_support
    with os_support.directory_lock(Path(sys.argv[1]), ".run.lock"):
        print("held", flush=True)
        sys.stdin.readline()  # hold until told (or killed)
"""
LOCK_TAKER = """
    import sys
    from pathlib import Path
    from setmem_hil import os_support
    try:
        with os_support.directory_lock(Path(sys.argv[1]), ".run.lock"):
            print("taken")
    except os_support.DirectoryBusy:
        print("busy")
"""


@pytest.mark.parametrize("posix_names", [True, False], ids=["fcntl", "no-fcntl"])
def test_the_run_lock_refuses_a_second_process_and_frees_with_its_holders_death(tmp_path, posix_names):
    """Two processes, one directory: the second is refused while the first lives, also where
    ``fcntl`` is missing (Windows); a holder killed outright leaves no lock behind."""
    prelude = "" if posix_names else WITHOUT_POSIX_NAMES

    def spawn(code):
        return subprocess.Popen([sys.executable, "-c", prelude + textwrap.dedent(code), str(tmp_path)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, stdin=subprocess.PIPE, text=True)

    holder = spawn(LOCK_HOLDER)
    try:
        assert holder.stdout.readline().strip() == "held", holder.stderr.read()
        taker = spawn(LOCK_TAKER)
        assert taker.communicate(timeout=60)[0].strip() == "busy"
    finally:
        holder.kill()
        holder.wait(timeout=30)
    taker = spawn(LOCK_TAKER)
    assert taker.communicate(timeout=60)[0].strip() == "taken"


def test_a_process_is_killed_where_there_is_no_sigkill():
    child = _child("""
        import os, time
        from setmem_hil.os_support import kill_process
        sleeper = __import__("subprocess").Popen([sys.executable, "-c", "import time; time.sleep(60)"])
        kill_process(sleeper.pid)
        start = time.monotonic()
        sleeper.wait(timeout=30)
        print("ended" if time.monotonic() - start < 10 else "late")
    """)
    out, err = child.communicate(timeout=60)
    assert out.strip() == "ended", err


def test_tcp_nodelay_through_the_visa_attribute_and_the_socket_where_it_is_not_honoured(monkeypatch):
    """Issue 40, item 7: VI_ATTR_TCPIP_NODELAY first; a library that refuses it still gets the
    socket option (what pyvisa-py's INSTR sessions would need)."""
    import socket

    import pyvisa

    from setmem_hil.drivers.instruments.visa_link import VisaLink
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.instrument_bench import EmulatedBench
    from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, InstrumentServer

    server = InstrumentServer(GeneratorEmulator(EmulatedBench(beam_parameters()), "33500B"))
    try:
        link = VisaLink("fgen", server.resource)
        assert link._inst.get_visa_attribute(pyvisa.constants.VI_ATTR_TCPIP_NODELAY) == pyvisa.constants.VI_TRUE
        link.close()
        refused = []
        honoured = pyvisa.resources.Resource.set_visa_attribute

        def refuse(self, attribute, state):
            if attribute != pyvisa.constants.VI_ATTR_TCPIP_NODELAY:
                return honoured(self, attribute, state)
            refused.append(attribute)
            raise pyvisa.errors.VisaIOError(pyvisa.constants.StatusCode.error_nonsupported_attribute)

        monkeypatch.setattr(pyvisa.resources.Resource, "set_visa_attribute", refuse)
        original = socket.socket.setsockopt
        calls = []
        monkeypatch.setattr(socket.socket, "setsockopt", lambda self, *a: calls.append(a) or original(self, *a))
        link = VisaLink("fgen", server.resource)
        assert refused == [pyvisa.constants.VI_ATTR_TCPIP_NODELAY]
        assert (socket.IPPROTO_TCP, socket.TCP_NODELAY, 1) in calls
        assert link.query("OUTP1?") == "0"
        link.close()
    finally:
        server.close()
