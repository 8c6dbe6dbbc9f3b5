"""The reference firmware (issue 45): it compiles with -Werror, its core computes what
scipy.signal.sosfilt computes, its line protocol keeps its state rules, and the host's driver
(written from the protocol's documentation) works against the firmware itself running as a
process behind a pseudo-terminal (a real serial line). Truth: scipy's sosfilt, zlib's CRC-32,
the documented states and replies."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.signal

from setmem_hil.firmware import BOARD_SOURCES, CORE_SOURCES, SOURCE_DIR
from setmem_hil.sim_backends.firmware_core import CFLAGS, FirmwareCore, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler (cc or $CC) to build the reference firmware")

FS = 2000.0


def lightly_damped_sections(seed: int = 3) -> np.ndarray:
    """A compensator like the campaign's: lightly damped poles and zeros, order 8, Tustin at FS
    in product form (as the export makes them, robust.controller_forms)."""
    rng = np.random.default_rng(seed)
    poles, zeros = [], []
    for w in (40.0, 170.0, 520.0, 1300.0):
        poles += [w * (-0.01 + 1j * np.sqrt(1 - 1e-4)), w * (-0.01 - 1j * np.sqrt(1 - 1e-4))]
        wz = w * rng.uniform(0.8, 1.2)
        zeros += [wz * (-0.02 + 1j * np.sqrt(1 - 4e-4)), wz * (-0.02 - 1j * np.sqrt(1 - 4e-4))]
    z, p, k = scipy.signal.bilinear_zpk(np.array(zeros), np.array(poles), 3.0, FS)
    return scipy.signal.zpk2sos(z, p, k, pairing="nearest")


def loaded_core(sos, delay=0) -> FirmwareCore:
    core = FirmwareCore(FS, delay)
    assert core.command(f"LOAD {len(sos)}") == "OK"
    for i, row in enumerate(sos):
        assert core.command(f"SOS {i} " + " ".join(repr(float(v)) for v in row[[0, 1, 2, 4, 5]])) == "OK"
    return core


def test_the_firmware_compiles_without_a_warning_for_a_board_and_for_the_pc_port(tmp_path):
    cc = compiler()
    board = [str(SOURCE_DIR / name) for name in BOARD_SOURCES]
    for extra, out in (([str(SOURCE_DIR / "host" / "hal_host.c")], "host"), ([], "core.o")):
        flags = [f for f in CFLAGS if f not in ("-shared", "-fPIC")]
        cmd = [cc, *flags, *(board + extra if extra else ["-c", str(SOURCE_DIR / CORE_SOURCES[0])]), "-o", str(tmp_path / out)]
        if extra:
            cmd.append("-lm")
        done = subprocess.run(cmd, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    # a board with a force channel: main.c with -DSETMEM_HAL_FORCE needs hal_read_force (compiled, not linked)
    flags = [f for f in CFLAGS if f not in ("-shared", "-fPIC")]
    done = subprocess.run([cc, *flags, "-DSETMEM_HAL_FORCE", "-c", str(SOURCE_DIR / "main.c"), "-o", str(tmp_path / "main.o")],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_the_core_computes_what_sosfilt_computes_on_2000_samples():
    sos = lightly_damped_sections()
    x = np.random.default_rng(7).standard_normal(2000)
    core = loaded_core(sos)
    mine = np.array([core.filter(v) for v in x])
    truth = scipy.signal.sosfilt(sos, x)
    assert np.max(np.abs(mine - truth)) <= 1e-12 * max(1.0, np.max(np.abs(truth)))


def test_an_engaged_target_drives_gain_times_the_compensator_delayed_by_its_samples():
    sos = lightly_damped_sections()
    x = np.random.default_rng(8).standard_normal(400)
    for delay in (0, 1, 3):
        core = loaded_core(sos, delay)
        core.command("LIMIT 1e9")
        assert core.command("ENGAGE 0.5") == "OK" and core.command("STATE?") == "ENGAGED 0.5"
        drive = np.array([core.tick(v) for v in x])
        truth = 0.5 * scipy.signal.sosfilt(sos, x)
        expected = np.concatenate([np.zeros(delay), truth[: len(x) - delay]])
        assert np.allclose(drive, expected, rtol=0, atol=1e-12 * np.max(np.abs(truth))), delay


def test_the_checksum_is_crc32_of_the_coefficients_bits_as_documented():
    import struct
    import zlib

    sos = lightly_damped_sections()
    core = loaded_core(sos)
    assert core.command("SOSGAIN 1.5") == "OK"
    payload = struct.pack("<I", len(sos)) + b"".join(struct.pack("<5d", *row[[0, 1, 2, 4, 5]]) for row in sos) + struct.pack("<d", 1.5)
    assert core.command("CHECKSUM?") == f"CHECKSUM {zlib.crc32(payload):08X}"


def test_the_protocol_refuses_what_its_state_forbids():
    core = FirmwareCore(FS, 1)
    assert core.command("ENGAGE 1").startswith("ERR no compensator")
    assert core.command("CHECKSUM?").startswith("ERR not loaded")
    core.command("LOAD 2")
    core.command("SOS 0 1 0 0 0 0")
    assert core.command("ENGAGE 1").startswith("ERR no compensator")  # one section of two
    assert core.command("SOS 2 1 0 0 0 0").startswith("ERR SOS index")
    assert core.command("SOS 1 1 0 0 0").startswith("ERR SOS needs")  # four coefficients
    core.command("SOS 1 1 0 0 0 0")
    assert core.command("ENGAGE 3").startswith("ERR ENGAGE needs a gain")
    assert core.command("ENGAGE 1") == "OK"
    for refused in ("LOAD 1", "SOS 0 1 0 0 0 0", "LIMIT 2", "SOSGAIN 2"):
        assert core.command(refused).startswith("ERR engaged"), refused
    assert core.command("FROB").startswith("ERR unknown command")
    assert core.command("BYPASS") == "OK" and core.command("STATE?") == "BYPASS"
    assert core.command("LIMIT 2") == "OK" and core.command("LIMIT?") == "2"


def test_a_drive_past_its_limit_trips_the_target_to_zero_until_bypassed():
    core = loaded_core(np.array([[2.0, 0, 0, 1, 0, 0]]))
    core.command("LIMIT 1")
    core.command("ENGAGE 1")
    assert core.tick(0.25) == 0.5
    assert core.tick(0.75) == 0.0 and core.command("STATE?") == "TRIPPED drive_limit"
    assert core.tick(0.1) == 0.0 and core.command("ENGAGE 1").startswith("ERR tripped")
    assert core.command("BYPASS") == "OK" and core.command("STATE?") == "BYPASS"


def test_a_silent_host_trips_the_watchdog():
    core = loaded_core(np.array([[1.0, 0, 0, 1, 0, 0]]))
    core.command("WATCHDOG 0.01")  # 20 samples at 2 kHz
    core.command("ENGAGE 1")
    for _ in range(20):
        core.tick(0.1)
    assert core.command("STATE?").startswith("ENGAGED")  # the query itself feeds the watchdog
    for _ in range(21):
        core.tick(0.1)
    assert core.command("STATE?") == "TRIPPED watchdog"


def test_the_injection_is_a_sine_at_the_summing_junction():
    core = FirmwareCore(FS, 1)
    assert core.command("INJECT 0.2 300") == "OK"
    drive = np.array([core.tick(0.0) for _ in range(100)])  # bypassed: the drive is the injection alone
    assert np.allclose(drive, 0.2 * np.sin(300 * np.arange(100) / FS), atol=1e-15)


# -- the host's driver against the firmware running as a process on a pseudo-terminal ---------
@pytest.fixture
def firmware_on_a_pty(tmp_path):
    """The firmware's PC port (firmware/host/hal_host.c) on the controller side of a
    pseudo-terminal; the test opens the device side as a serial port, as it would a board's."""
    if not sys.platform.startswith("linux"):
        pytest.skip("pseudo-terminals as serial ports: Linux")
    import tty

    binary = tmp_path / "target"
    sources = [str(SOURCE_DIR / name) for name in BOARD_SOURCES] + [str(SOURCE_DIR / "host" / "hal_host.c")]
    flags = [f for f in CFLAGS if f not in ("-shared", "-fPIC")]
    subprocess.run([compiler(), *flags, "-DSETMEM_DELAY_SAMPLES=2", *sources, "-o", str(binary), "-lm"], check=True)
    controller_fd, device_fd = os.openpty()
    tty.setraw(controller_fd)
    process = subprocess.Popen([str(binary)], stdin=controller_fd, stdout=controller_fd)
    yield os.ttyname(device_fd)
    process.kill()
    process.wait()
    os.close(controller_fd)
    os.close(device_fd)


def test_the_driver_loads_engages_and_bypasses_the_firmware_with_everything_read_back(firmware_on_a_pty):
    from setmem_hil.drivers.real_time_target import RealTimeTarget, compensator_checksum
    from setmem_hil.errors import DeviceRejectedError

    from setmem_hil.drivers.real_time_target import SerialLineChannel

    target = RealTimeTarget(SerialLineChannel(firmware_on_a_pty, timeout_s=5.0), firmware_on_a_pty)
    identity = target.identity()
    assert identity.fs_hz == 2000.0 and identity.delay_samples == 2 and identity.version == "1.1"
    sos = lightly_damped_sections()
    assert target.load(sos, 1.0) == compensator_checksum(sos, 1.0)
    target.set_drive_limit(5.0)
    assert target.engage(0.25).gain == 0.25 and target.engage(0.5).gain == 0.5
    with pytest.raises(DeviceRejectedError, match="LOAD refused: engaged"):
        target.load(sos)
    assert target.bypass().mode == "BYPASS"
    target.close()


def test_a_coefficient_the_target_parses_differently_fails_the_read_back():
    from setmem_hil.drivers.real_time_target import RealTimeTarget
    from setmem_hil.errors import DeviceRejectedError

    core = FirmwareCore(FS, 1)

    class Rounding:  # a line that loses digits (a 32-bit float parser on a board, say)
        def exchange(self, line):
            if line.startswith("SOS "):
                line = " ".join([*line.split()[:2], *(f"{float(v):.7g}" for v in line.split()[2:])])
            return core.command(line)

        def close(self):
            pass

    with pytest.raises(DeviceRejectedError, match="checksum"):
        RealTimeTarget(Rounding(), "rounding target").load(lightly_damped_sections())


# -- the target's own analyser (ANALYSE, ANALYSIS?, SUMS?) ----------------------------------------
def test_the_analyser_refuses_what_its_state_forbids():
    core = loaded_core(np.array([[2.0, 0, 0, 1, 0, 0]]))
    assert core.command("ANALYSE 0 100").startswith("ERR ANALYSE needs an injection")
    assert core.command("ANALYSIS?") == "IDLE" and core.command("SUMS? Y").startswith("ERR no analysis")
    assert core.command("INJECT 0.1 50") == "OK"
    assert core.command("ANALYSE 0 0").startswith("ERR ANALYSE needs whole numbers")
    assert core.command("ANALYSE 1.5 10").startswith("ERR ANALYSE needs whole numbers")
    assert core.command("ANALYSE 3 10") == "OK"
    for _ in range(3):
        core.tick(0.0)
    assert core.command("ANALYSIS?").startswith("SUMMING 0 10 ")
    for _ in range(10):
        core.tick(0.0)
    assert core.command("ANALYSIS?").startswith("DONE 3 10 ")  # the injection's sample 3 is the first summed
    assert core.command("SUMS? Q").startswith("ERR SUMS? needs")
    assert len(core.command("SUMS? REF").split()) == 5 and len(core.command("SUMS? u").split()) == 4
    assert core.command("INJECT 0.1 60") == "OK" and core.command("ANALYSIS?") == "IDLE"  # sums of another injection
    core.command("ANALYSE 0 1000")
    core.command("LIMIT 0.05")
    core.command("ENGAGE 1")
    core.tick(0.0)
    core.tick(1.0)  # drive 2 > 0.05: tripped, the analysis dropped
    assert core.command("STATE?") == "TRIPPED drive_limit" and core.command("ANALYSIS?") == "IDLE"
    assert core.command("ANALYSE 0 10").startswith("ERR tripped")


def test_the_force_channels_sums_are_the_sums_of_the_force_samples_and_a_board_without_one_says_so():
    """Issue 63 item 1: a board with a second ADC on the force transducer calls
    setmem_target_force_sample before each tick; SUMS? F is the sums of those samples against the
    injection's phase (written out here in numpy from the samples fed). A board that never fed one
    refuses SUMS? F by name."""
    core = loaded_core(np.array([[0.0, 0, 0, 1, 0, 0]]))
    assert core.command("INJECT 0.1 50") == "OK" and core.command("ANALYSE 2 40") == "OK"
    for _ in range(42):
        core.tick(0.0)
    assert core.command("ANALYSIS?").startswith("DONE") and core.command("SUMS? F") == "ERR no force channel on this board"

    core = loaded_core(np.array([[0.0, 0, 0, 1, 0, 0]]))
    fs, w = FS, 50.0
    assert core.command("INJECT 0.1 50") == "OK" and core.command("ANALYSE 5 300") == "OK"
    rng = np.random.default_rng(7)
    force = 0.3 * np.sin(w * np.arange(400) / fs + 0.4) + 0.02 * rng.standard_normal(400) + 0.05
    for f in force:
        core.force_sample(f)
        core.tick(0.0)
    first = int(core.command("ANALYSIS?").split()[1])
    n = np.arange(first, first + 300)
    summed = force[n]  # the injection's sample n is the n-th tick here (INJECT before the first tick)
    expected = [np.sum(summed * np.sin(w * n / fs)), np.sum(summed * np.cos(w * n / fs)), np.sum(summed), np.sum(summed ** 2)]
    got = [float(v) for v in core.command("SUMS? F").split()]
    assert got == pytest.approx(expected, rel=1e-12, abs=1e-12)

def test_the_analysers_sums_give_the_fit_the_samples_give():
    """Second formulation: the beam in closed loop with the core (the emulated rig), the target's
    own injection and analyser on; the same run's samples fitted by fit_sine (IEEE 1057) must give
    the point the sums give, to rounding."""
    from setmem_hil.estimation.analyser_sums import AnalyserSums, closed_loop_point_from_sums
    from setmem_hil.estimation.closed_loop_point import closed_loop_point
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.emulated_target import EmulatedClosedLoop

    loop = EmulatedClosedLoop(beam_parameters().truncated(3), 1000.0, 1, noise_rms=1e-4, seed=3)
    core = loop.core
    for line in ("LOAD 1", "SOS 0 0.3 0 0 0 0", "LIMIT 5", "WATCHDOG 0", "ENGAGE 0.5", "INJECT 0.05 4.0", "ANALYSE 700 9000"):
        assert core.command(line) == "OK", line
    record = loop.run(9700)
    reply = core.command("ANALYSIS?").split()
    assert reply[:3] == ["DONE", "700", "9000"]
    rows = [tuple(float(v) for v in core.command(f"SUMS? {name}").split()) for name in ("R", "U", "Y", "REF")]
    sums = AnalyserSums(4.0, 1000.0, 700, 9000, *rows, float(reply[3]), float(reply[4]))
    n = np.arange(700, 9700)
    r = 0.05 * np.sin(4.0 * n / 1000.0)  # the target's own injection, as the protocol documents it
    from_samples = closed_loop_point(n / 1000.0, r, record.u[700:], record.y[700:], 4.0)
    from_sums = closed_loop_point_from_sums(sums)
    assert abs(from_sums.S - from_samples.S) < 1e-10 * abs(from_samples.S)
    assert abs(from_sums.G - from_samples.G) < 1e-9 * abs(from_samples.G)
    assert from_sums.S_bound == pytest.approx(from_samples.S_bound, rel=1e-6)
    assert from_sums.G_bound == pytest.approx(from_samples.G_bound, rel=1e-6)
    assert from_sums.free_response_rms == pytest.approx(from_samples.free_response_rms, rel=1e-6)
    assert sums.peak_drive == pytest.approx(np.max(np.abs(record.u)), rel=1e-12)
    assert sums.peak_response == pytest.approx(np.max(np.abs(record.y)), rel=1e-12)


def test_a_silent_board_is_a_timeout_naming_the_command_not_a_lost_link():
    """Issue 63 item 4: our own timeout is an OSError too; it used to be re-raised as "link lost"."""
    import os

    from setmem_hil.drivers.real_time_target import SerialLineChannel
    from setmem_hil.errors import DeviceTimeoutError

    master, slave = os.openpty()  # a port that exists and never answers
    try:
        channel = SerialLineChannel(os.ttyname(slave), timeout_s=0.2)
        with pytest.raises(DeviceTimeoutError, match=r"no reply to ANALYSIS\? within 0.2 s"):
            channel.exchange("ANALYSIS?")
        channel.close()
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("reason, says, never", [
    ("amplifier_fault", "a fault the board reports (amplifier_fault), not the loop", "the loop grew"),
    ("drive_limit", "the drive reached the board's limit: the loop grew", "not the loop"),
    ("watchdog", "the host fell silent", "the loop grew"),
])
def test_a_trip_is_reported_by_its_reason(reason, says, never):
    """Issue 63 item 4: a hardware trip is not blamed on the loop; the firmware's own reasons
    (docs/real-time-target.md) are said as what they mean. The service bypasses before saying so."""
    from setmem_hil.drivers.real_time_target import TRIPPED, TargetState
    from setmem_hil.verify.messages import InjectAndRecord
    from setmem_hil.verify.target_service import LoopFault, TargetService

    class TrippedBoard:
        where = "board under test"
        bypassed = False

        def state(self):
            return TargetState(TRIPPED, reason=reason)

        def inject(self, amplitude, omega):
            pass

        def bypass(self):
            self.bypassed = True

    board = TrippedBoard()
    service = TargetService(board, None, fs_hz=1000.0, delay_samples=0, drive_limit=1.0, watchdog_s=1.0,
                            response_limit=None, measure="analyser", wait=lambda s: None)
    request = InjectAndRecord(omega_rad_s=17.5, amplitude=0.1, settle_s=1.0, record_s=1.0)
    with pytest.raises(LoopFault) as caught:
        service._check(request, 0.0, 0.0)
    assert says in str(caught.value) and never not in str(caught.value) and board.bypassed
