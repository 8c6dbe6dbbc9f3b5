"""Issue 24: the real-instrument path against the faults a lab meets on its first day.

Each test reproduces one finding against the emulated instruments (emulators of the 33500B,
Siglent SDG, SR830/SR860/SR865A written from their programming manuals, on 127.0.0.1 sockets
opened through PyVISA and pyvisa-py), and checks the behaviour against the emulated truth: the
output state *inside the emulated generator*, not what the driver believes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from setmem_hil.campaign.session import start_run, unconfirmed_output_off
from setmem_hil.cli.main import exit_code_and_message, main
from setmem_hil.errors import CampaignAborted, DeviceDisconnectedError, DeviceError, DeviceRejectedError, OutputNotConfirmedOffError
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure_file import load_procedure, parse_procedure_text
from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, LockInEmulator

REPO = Path(__file__).resolve().parents[1]
EMULATED = REPO / "procedures" / "instruments_emulated.toml"


def _procedure(**emulation):
    p = load_procedure(EMULATED)
    return dataclasses.replace(p, backend=dataclasses.replace(
        p.backend, emulation=dataclasses.replace(p.backend.emulation, **emulation)))


def _server(exp, kind):
    return next(s for s in exp.owned if isinstance(s.emulator, kind))


# -- finding 1: a dropped link leaves the shaker running ----------------------------------------

def test_a_dropped_link_is_reconnected_and_the_output_switched_off_for_real():
    exp = open_experiment(_procedure(), seed=1)
    try:
        gen = _server(exp, GeneratorEmulator)
        original = exp.source.set_amplitude_v

        def drop_after_output_on(volts):  # the link drops while the output is on
            if exp.bench.output_on:
                gen.drop_link(after=0)
            original(volts)

        exp.source.set_amplitude_v = drop_after_output_on
        with pytest.raises(DeviceDisconnectedError, match="fgen .*closed the connection|fgen .*connection was lost"):
            exp.measure(0.95)
        assert exp.bench.output_on is False  # the emulated generator's relay, not our belief
        assert exp.output_confirmed_off and exp.counters["reconnects"] >= 1
    finally:
        exp.close()


def test_a_link_that_stays_down_is_reported_as_such_never_as_commanded_to_zero(tmp_path):
    opened = []

    def opener(p, seed):
        exp = open_experiment(p, seed)
        opened.append(exp)
        original = exp.source.set_amplitude_v

        def drop_for_good(volts):
            if exp.bench.output_on:
                _server(exp, GeneratorEmulator).drop_link(after=0, reconnectable=False)
            original(volts)

        exp.source.set_amplitude_v = drop_for_good
        return exp

    with pytest.raises(DeviceError) as info:
        start_run(_procedure(), tmp_path / "run", opener=opener, quiet_report_hint=True)
    assert opened[0].bench.output_on  # the emulated shaker still drives: the message must say so
    code, message = exit_code_and_message(info.value)
    assert code == 4
    assert "fgen" in message and "switch it off at the instrument" in message
    assert "commanded to zero" not in message and "at zero" not in message
    assert f"run --resume {tmp_path / 'run'}" in message
    # the first fault leads the line, not the failed clean-up, and no resource string is blamed
    assert message.index("closed the connection") < message.index("could not be confirmed off")
    assert "resource string" not in message
    j = Journal.open(tmp_path / "run")
    try:
        assert unconfirmed_output_off(j) is not None
        assert any(e["kind"] == "output-off" and e["message"].startswith("NOT confirmed") for e in j.events())
    finally:
        j.close()


@pytest.mark.slow
def test_resume_after_sigkill_switches_the_output_off_first_and_says_so(tmp_path):
    run_dir = tmp_path / "killed"
    child = subprocess.Popen([sys.executable, "-m", "setmem_hil.cli.main", "run", str(EMULATED), "--out", str(run_dir), "--quiet"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # kill it once a dwell has been journaled
            if (run_dir / "journal.sqlite").exists():
                j = Journal.open(run_dir)
                n = j.n_measurements()
                j.close()
                if n >= 1:
                    break
            time.sleep(0.05)
        os.kill(child.pid, signal.SIGKILL)
        child.wait(timeout=30)
    finally:
        if child.poll() is None:
            child.kill()
    j = Journal.open(run_dir)
    assert unconfirmed_output_off(j) is not None  # armed, never confirmed off
    j.close()
    resumed = subprocess.run([sys.executable, "-m", "setmem_hil.cli.main", "run", "--resume", str(run_dir)],
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    lines = resumed.stdout.splitlines()
    off = next(i for i, line in enumerate(lines) if "output switched off" in line)
    first_dwell = next((i for i, line in enumerate(lines) if "rad/s" in line and "measur" in line.lower()), len(lines))
    assert off < first_dwell
    j = Journal.open(run_dir)
    try:
        assert unconfirmed_output_off(j) is None and j.run_info()["finished"]
    finally:
        j.close()


# -- finding 2: a momentary reference unlock ends the campaign ----------------------------------

def test_a_lockin_that_relocks_after_each_frequency_step_is_waited_for():
    with open_experiment(_procedure(relock_s=0.05), seed=1) as exp:
        for w in (5.95, 6.2):  # two steps, each followed by 50 ms of "unlocked"
            m = exp.measure(w)
            assert abs(m.response - exp.bench.true_response(w)) <= m.bound


def test_a_reference_that_never_locks_is_a_device_fault_naming_the_lockin():
    with open_experiment(_procedure(), seed=1) as exp:
        exp.bench.settings = dataclasses.replace(exp.bench.settings, relock_s=1e6)  # the sync cable is not plugged in
        with pytest.raises(DeviceRejectedError, match=r"lia_force .*reference not locked .*sync output"):
            exp.measure(5.95)
        assert not exp.bench.output_on
    assert exit_code_and_message(DeviceRejectedError("unlocked", "x"))[0] == 4


# -- finding 7: one garbled reply ends the campaign; a closed connection is a "timeout" ----------

def test_one_garbled_reply_is_asked_again_two_are_a_device_fault():
    with open_experiment(_procedure(), seed=1) as exp:
        lia = _server(exp, LockInEmulator)
        lia.garble_replies(1)
        m = exp.measure(5.95)
        assert abs(m.response - exp.bench.true_response(5.95)) <= m.bound
        assert exp.force.garbled_replies + exp.response.garbled_replies == 1
        lia.garble_replies(2)
        with pytest.raises(DeviceRejectedError, match=r"twice in a form that does not parse") as info:
            exp.measure(6.2)
        assert info.value.args[0].startswith(("lia_force", "lia_response"))
        assert not exp.bench.output_on


def test_a_connection_closed_by_the_instrument_is_reported_as_closed_at_once():
    with open_experiment(_procedure(), seed=1) as exp:
        response = next(s for s in exp.owned if isinstance(s.emulator, LockInEmulator) and s.emulator.signal == "response")
        response.drop_link(after=5, reconnectable=False)
        start = time.monotonic()
        with pytest.raises(DeviceDisconnectedError, match=r"lia_response .*closed the connection") as info:
            exp.measure(5.95)
        assert "within" not in str(info.value)
        assert time.monotonic() - start < 1.5  # not the 2 s timeout
        assert not exp.bench.output_on


# -- finding 3: "paused" while the shaker still drives -----------------------------------------

def test_pause_is_pausing_until_the_dwell_has_finished_and_the_output_is_confirmed_off():
    from setmem_hil.live.control import LiveControl

    control = LiveControl()
    dwell_running, release = threading.Event(), threading.Event()
    output = {"on": False, "confirmed_off_calls": 0, "measured": 0}

    def dwell():  # the runner's loop: checkpoint, then a dwell that drives the shaker
        with contextlib.suppress(CampaignAborted):
            _dwells()

    def _dwells():
        for _ in range(3):
            control.checkpoint(make_safe=lambda: output.__setitem__("confirmed_off_calls", output["confirmed_off_calls"] + 1))
            output["on"] = True
            dwell_running.set()
            release.wait(10)
            output["on"] = False
            output["measured"] += 1
            release.clear()

    runner = threading.Thread(target=dwell, daemon=True)
    runner.start()
    assert dwell_running.wait(5)
    control.pause()
    assert control.status == "pausing" and output["on"]  # the shaker drives: not "paused"
    release.set()
    deadline = time.monotonic() + 5
    while control.status != "paused" and time.monotonic() < deadline:
        time.sleep(0.01)
    assert control.status == "paused" and not output["on"] and output["confirmed_off_calls"] == 1
    measured = output["measured"]
    time.sleep(0.5)
    assert output["measured"] == measured  # nothing is measured while paused
    control.abort()
    runner.join(5)


# -- finding 4: an instrument the project does not ship cannot be read back ----------------------

def _sdg_sr865a_procedure(**emulation) -> str:
    text = EMULATED.read_text()
    text = text.replace('profile = "keysight-33500b"', 'profile = "siglent-sdg2000x"').replace('profile = "srs-sr860"', 'profile = "srs-sr865a"')
    extra = "".join(f"{k} = {v}\n" for k, v in emulation.items())
    return text.replace("noise_v_per_rthz = 2e-6\n", "noise_v_per_rthz = 2e-6\n" + extra, 1)


def test_siglent_compound_replies_are_read_back_on_either_channel():
    from setmem_hil.drivers.instruments.profile import load_profile
    from setmem_hil.drivers.instruments.scpi_generator import ScpiGenerator
    from setmem_hil.drivers.instruments.visa_link import VisaLink
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.instrument_bench import EmulatedBench
    from setmem_hil.sim_backends.instrument_emulators import InstrumentServer, SiglentGeneratorEmulator

    profile = load_profile("siglent-sdg2000x")
    emulator = SiglentGeneratorEmulator(EmulatedBench(beam_parameters()), "SDG2000X", channel=2)
    server = InstrumentServer(emulator)
    try:
        gen = ScpiGenerator("sdg", profile, VisaLink("sdg", server.resource, timeout_s=2.0), channel=2)
        assert "SDG2042X" in gen.check_identity()
        gen.initialise()
        assert emulator.channels[2]["LOAD"] == "HZ" and emulator.channels[2]["SYNC"]  # high_z, and the sync for the lock-ins
        gen.set_frequency_hz(0.1432394488)  # 1 uHz resolution: read back 0.143239 Hz, within it
        assert emulator.channels[2]["FRQ"] == pytest.approx(0.143239, abs=1e-12)
        gen.set_amplitude_v(0.25)
        assert emulator.channels[2]["AMP"] == pytest.approx(0.5)  # Vpp
        gen.set_output(True)
        assert emulator.channels[2]["OUTP"] and not emulator.channels[1]["OUTP"]
        gen.set_output(False)
        assert not emulator.channels[2]["OUTP"]
        gen.close()
    finally:
        server.close()


@pytest.mark.slow
def test_campaign_through_sdg2042x_sr830_sr865a_reads_back_and_contains_the_truth(tmp_path):
    import numpy as np

    from setmem_hil.io.journal import read_snapshot

    procedure = parse_procedure_text(_sdg_sr865a_procedure(relock_s=0.005), str(tmp_path / "p.toml"))
    opened = []

    def opener(p, seed):
        opened.append(open_experiment(p, seed))
        return opened[-1]

    outcome = start_run(procedure, tmp_path / "run", opener=opener, quiet_report_hint=True)
    assert outcome.summary["reached_goal"]
    exp = opened[0]
    transcript = exp.source.link.transcript
    assert any(c.startswith("C1:BSWV FRQ,") for c in transcript) and "C1:BSWV?" in transcript and "C1:OUTP?" in transcript
    assert exp.identities["lia_response"].startswith("Stanford_Research_Systems,SR865A")
    measured = read_snapshot(tmp_path / "run").measurements
    errors = np.array([abs(m.response - exp.bench.true_response(m.omega_rad_s)) for m in measured])
    assert np.all(errors <= np.array([m.bound for m in measured]))
    assert not exp.bench.output_on


def _profile_file(tmp_path, name, text):
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def test_profile_extends_reply_expect_with_ch_and_model_optional(tmp_path):
    from setmem_hil.drivers.instruments.profile import load_profile, profile_warnings

    sr865 = load_profile("srs-sr865a")
    sr860 = load_profile("srs-sr860")
    assert sr865.identity_expect != sr860.identity_expect and sr865.time_constants_s == sr860.time_constants_s
    own = _profile_file(tmp_path, "my-sr865", 'extends = "srs-sr865a"\n[time_constant]\nquery = ""\n')
    p = load_profile(str(own))
    assert p.model == "my-sr865" or p.model == "Stanford Research Systems SR865A"
    assert any("[time_constant]" in w and "no read-back" in w for w in profile_warnings(p))
    base = (REPO / "drivers/instruments/profiles/keysight-33500b.toml").read_text().replace('model = "Keysight/Agilent 33500B series"\n', "")
    assert load_profile(str(_profile_file(tmp_path, "gen-without-model", base))).model == "gen-without-model"
    loop = _profile_file(tmp_path, "loop", 'extends = "loop.toml"\n')
    with pytest.raises(Exception, match="extends"):
        load_profile(str(loop))


# -- finding 5: a Modbus profile written to the published contract is refused -------------------

def test_modbus_profile_with_only_the_published_keys_is_accepted(tmp_path):
    from setmem_hil.drivers.instruments.profile import load_profile

    text = """kind = "modbus"
device_id = 1
identity = { table = "input", address = 0, type = "uint16", expect = 21320 }
frequency_hz = { table = "holding", address = 10, type = "float32" }
amplitude_v = { table = "holding", address = 12, type = "float32" }
output = { table = "coil", address = 0 }
"""
    p = load_profile(str(_profile_file(tmp_path, "published-keys", text)))
    assert p.model == "published-keys" and p.device_id == 1


def test_an_init_error_names_the_command_and_run_check_warns_without_read_back(tmp_path, capsys):
    gen = (REPO / "drivers/instruments/profiles/keysight-33500b.toml").read_text()
    gen = gen.replace('"SOUR{ch}:VOLT:OFFS 0",', '"SOUR{ch}:VOLT:OFFS 0",\n    "SOUR{ch}:BOGUS 1",')
    gen = gen.replace('amplitude = { set = "SOUR{ch}:VOLT {value:.5g}", query = "SOUR{ch}:VOLT?",', 'amplitude = { set = "SOUR{ch}:VOLT {value:.5g}",')
    _profile_file(tmp_path, "gen", gen)
    text = EMULATED.read_text().replace('profile = "keysight-33500b"', 'profile = "gen.toml"')
    path = _profile_file(tmp_path, "proc", text)
    assert main(["run", "--check", str(path)]) == 0
    out = capsys.readouterr()
    assert "warning" in (out.out + out.err) and "no read-back" in (out.out + out.err) and "amplitude" in (out.out + out.err)
    code = main(["run", str(path), "--out", str(tmp_path / "r"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 4 and "SOUR1:BOGUS 1" in err and "fgen" in err


def test_probe_switches_a_left_on_output_off_and_says_so(tmp_path, capsys):
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.instrument_bench import EmulatedBench
    from setmem_hil.sim_backends.instrument_emulators import InstrumentServer

    bench = EmulatedBench(beam_parameters())
    gen = GeneratorEmulator(bench, "33500B")
    servers = [InstrumentServer(gen), InstrumentServer(LockInEmulator(bench, "force", "SR830")),
               InstrumentServer(LockInEmulator(bench, "response", "SR860"))]
    gen.handle_line("OUTP1 ON")  # what a killed run leaves behind
    assert bench.output_on
    try:
        text = EMULATED.read_text().replace("[backend.emulation]\n", "[unused_emulation]\n")
        text = text.replace("[unused_emulation]\ndrive_gain_ratio = 1.1        # the real amplifier gain is 10 % above the nominal one\nnoise_v_per_rthz = 2e-6\n", "")
        for old, server in zip(('profile = "keysight-33500b"', 'profile = "srs-sr830"', 'profile = "srs-sr860"'), servers):
            text = text.replace(f'{old}\nresource = "TCPIP::127.0.0.1::0::SOCKET"', f'{old}\nresource = "{server.resource}"')
        path = _profile_file(tmp_path, "rig", text)
        assert main(["probe", str(path)]) == 0
        out = capsys.readouterr().out
        assert "output switched off" in out
        assert not bench.output_on
        assert [c for c in gen.commands if not c.endswith("?")] == ["OUTP1 ON", "OUTP1 OFF"]  # nothing else is set
    finally:
        for s in servers:
            s.close()


def test_every_example_in_the_profile_docs_is_valid_and_realistic():
    import re

    import tomllib

    from setmem_hil.drivers.instruments.profile import PROFILE_KEYS, load_profile, parse_profile

    text = (REPO / "docs" / "instrument-profiles.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert len(blocks) >= 5
    for block in blocks:
        doc = tomllib.loads(block)  # valid TOML: no "..." inside arrays
        if doc.get("kind") in PROFILE_KEYS and doc.get("kind") != "dbc":
            profile = parse_profile(block, "docs/instrument-profiles.md")
            for setting in (getattr(profile, "frequency", None),):
                if setting is not None:  # a frequency read-back tolerance no tighter than 1 uHz steps allow
                    assert setting.resolution >= 1e-6 or setting.tolerance_rel >= 1e-5
            if doc["kind"] == "scpi-generator":
                assert any("SYNC" in c.upper() for c in profile.init), "the lock-ins need the generator's sync output"
    shipped = load_profile("siglent-sdg2000x")
    documented = next(parse_profile(b, "doc") for b in blocks if "SDG2000X" in b and "kind" in b)
    assert documented.frequency == shipped.frequency and documented.output_on == shipped.output_on and documented.init == shipped.init
