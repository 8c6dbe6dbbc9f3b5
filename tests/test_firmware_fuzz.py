"""Issue 63 item 3: a firmware that refuses what it cannot do.

The protocol is fed random and adversarial lines by ``tests/fuzz/firmware_protocol_fuzz.c``, built
with AddressSanitizer and UndefinedBehaviorSanitizer (float-cast-overflow included) that abort on
the first report; the harness checks the board's invariants after every line and sample (its
header lists them). Before the fix ``WATCHDOG 1e13`` at 2 kHz converted 2e16 to a ``uint32_t``
(undefined; on x86 a wrapped, silently short or absent watchdog) and the sanitizer stopped the run
at protocol.c's conversion. The named lines are also checked one by one through the compiled core.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from setmem_hil.firmware import SOURCE_DIR
from setmem_hil.sim_backends.firmware_core import FirmwareCore, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler (cc or $CC) to build the reference firmware")

HARNESS = Path(__file__).resolve().parent / "fuzz" / "firmware_protocol_fuzz.c"
SANITIZERS = ("-fsanitize=address,undefined,float-cast-overflow", "-fno-sanitize-recover=all")


@pytest.fixture(scope="module")
def fuzzer(tmp_path_factory):
    out = tmp_path_factory.mktemp("fuzz") / "firmware_protocol_fuzz"
    sources = [str(HARNESS), str(SOURCE_DIR / "protocol.c"), str(SOURCE_DIR / "target_core.c")]
    built = subprocess.run([compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-g", "-O1", *SANITIZERS,
                            f"-I{SOURCE_DIR}", *sources, "-lm", "-o", str(out)], capture_output=True, text=True)
    if built.returncode != 0 and "sanitize" in built.stderr and "cannot find" in built.stderr:
        pytest.skip(f"the C compiler has no sanitizer runtime here: {built.stderr.strip().splitlines()[-1]}")
    assert built.returncode == 0, built.stderr
    return out


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5, 6])
def test_random_and_adversarial_lines_keep_every_invariant_under_the_sanitizers(fuzzer, seed):
    run = subprocess.run([str(fuzzer), str(seed), "20000"], capture_output=True, text=True, timeout=120,
                         env={"ASAN_OPTIONS": "detect_leaks=1", "UBSAN_OPTIONS": "print_stacktrace=1"})
    assert run.returncode == 0, run.stdout + run.stderr
    assert "runtime error" not in run.stderr and "Sanitizer" not in run.stderr, run.stderr
    summary = run.stdout.strip().splitlines()[-1]
    assert "every invariant held" in summary
    # the run reached the states the invariants are about, not only refusals
    counts = [int(word) for word in summary.replace("(", " ").replace(")", " ").replace(",", " ").split() if word.isdigit()]
    lines, refused, samples, engaged, trips = counts
    assert lines == 20000 and 0 < refused < lines and engaged > 1000 and trips > 10


@pytest.mark.parametrize("line", ["WATCHDOG inf", "WATCHDOG nan", "WATCHDOG 4294967.296", "WATCHDOG 1e13", "WATCHDOG -1",
                                  "WATCHDOG 0.0001", "LOAD nan", "LOAD inf", "LOAD 1e309", "SOS 0 nan 0 0 0 0",
                                  "SOS nan 1 0 0 0 0", "SOS 0 1 0 0 inf 0", "LIMIT inf", "LIMIT nan", "SOSGAIN nan",
                                  "SOSGAIN -inf", "INJECT inf 1", "INJECT 0.1 nan", "ENGAGE nan", "ANALYSE nan 10"])
def test_non_finite_and_out_of_range_arguments_are_refused_and_change_nothing(line):
    core = FirmwareCore(2000.0, 0)
    assert core.command("LOAD 1") == "OK" and core.command("SOS 0 0.5 0 0 0 0") == "OK"
    before = [core.command(q) for q in ("STATE?", "LIMIT?", "CHECKSUM?")]
    reply = core.command(line)
    assert reply.startswith("ERR "), f"{line!r} -> {reply!r}"
    assert [core.command(q) for q in ("STATE?", "LIMIT?", "CHECKSUM?")] == before


def test_the_longest_watchdog_is_kept_and_still_trips():
    """The longest watchdog the ticks hold is accepted (no wrap to a short one); a short one trips
    an engaged board silent for longer than it, counted in the target's own samples."""
    core = FirmwareCore(2000.0, 0)
    assert core.command(f"WATCHDOG {4294967295 / 2000.0!r}") == "OK"
    assert core.command("WATCHDOG 0.01") == "OK"
    assert core.command("LOAD 1") == "OK" and core.command("SOS 0 0.1 0 0 0 0") == "OK"
    assert core.command("ENGAGE 1") == "OK"
    for _ in range(20):
        core.tick(0.0)
    assert core.command("STATE?").startswith("ENGAGED")  # the command itself fed the watchdog
    for _ in range(21):
        core.tick(0.0)
    assert core.command("STATE?") == "TRIPPED watchdog"
