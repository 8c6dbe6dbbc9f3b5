"""Issue 13, end to end: full campaigns through ``kind = "instruments"`` against the emulated
33500B + SR830 + SR860, and with a Modbus controller as exciter.

Truth is the emulated beam (8 modes, exact time-domain physics behind the lock-in filters). The
emulated amplifier's gain is 10 % above the declared ``newton_per_volt``; the measured force must
still never exceed ``max_amplitude_n`` by more than 5 %. Also: Ctrl-C leaves every output off,
an identity mismatch, a misspelt key and an unreachable resource each stop the run before any
output is switched on, with their exit codes.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.campaign.session import start_run
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.identification.algorithm import identify
from setmem_hil.io.journal import read_snapshot
from setmem_hil.io.procedure_file import load_procedure, parse_procedure_text
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.modal_model import ModalParameters
from setmem_hil.sim_backends.beam import BEAM_DAMPING_RATIO, BEAM_RESIDUE, beam_natural_frequencies
from setmem_hil.sim_backends.instrument_emulators import free_port

REPO = Path(__file__).resolve().parents[1]
PROCEDURES = {
    "33500B+SR830+SR860": REPO / "procedures" / "instruments_emulated.toml",
    "Modbus+SR830+SR860": REPO / "procedures" / "instruments_modbus_emulated.toml",
}


def _run(procedure, run_dir):
    """A full campaign through the CLI's own session, keeping the experiment for inspection."""
    opened = []

    def opener(p, seed):
        exp = open_experiment(p, seed)
        opened.append(exp)
        return exp

    outcome = start_run(procedure, run_dir, opener=opener, quiet_report_hint=True)
    return outcome, opened[0]


def _reprocessed_and_every_reading_kept(run_dir, n_points: int) -> bool:
    """Issue 39: ``reprocess`` agrees with the journal, and each lock-in record holds every reading
    of its dwell (more than the window the point is the mean of), with their times."""
    import h5py

    from setmem_hil.cli.main import main

    with h5py.File(run_dir / "raw.h5", "r") as f:
        records = [f["measurements"][name] for name in f["measurements"]]
        kinds = {r.attrs["kind"] for r in records}
        readings = [(r["times_s"].size, r["force_v"].size, r.attrs["window"]) for r in records if r.attrs["kind"] == "lock-in-readings"]
        del records
    assert all(t == n >= w for t, n, w in readings) and (kinds != {"lock-in-readings"} or len(readings) == n_points)
    return main(["reprocess", str(run_dir)]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("rig", list(PROCEDURES))
def test_full_campaign_through_the_instrument_path(rig, tmp_path):
    procedure = load_procedure(PROCEDURES[rig])
    assert procedure.backend.emulation.drive_gain_ratio == pytest.approx(1.1)  # the real gain 10 % above nominal
    outcome, exp = _run(procedure, tmp_path / "run")
    bench = exp.bench
    assert outcome.summary["reached_goal"], outcome.summary

    snapshot = read_snapshot(tmp_path / "run")
    measured = snapshot.measurements
    truth = np.array([bench.true_response(m.omega_rad_s) for m in measured])
    inside = np.abs(np.array([m.response for m in measured]) - truth) <= np.array([m.bound for m in measured])
    assert inside.mean() >= 0.95, f"{inside.sum()} of {inside.size} points contain the emulated truth"

    data = FrequencyData(np.array([m.omega_rad_s for m in measured]), np.array([m.response for m in measured]),
                         np.array([m.bound for m in measured]))
    model = identify(data, procedure.prior).model
    modelled_truth = ModalParameters.from_modal(beam_natural_frequencies(3), BEAM_DAMPING_RATIO, BEAM_RESIDUE, 0.0)
    assert model.contains(modelled_truth).all()

    # safety: the actual force never above the limit by more than 5 %, outputs off at the end
    assert bench.peak_force_n <= 1.05 * procedure.safety.max_amplitude_n
    assert bench.peak_force_n >= 0.9 * procedure.safety.max_amplitude_n / 1.01  # closed loop reached the level
    assert not bench.output_on and bench.force_amplitude_n == 0.0
    assert _reprocessed_and_every_reading_kept(tmp_path / "run", len(measured))
    assert exp.closed


def _emulated(text_changes: dict[str, str], base: Path = PROCEDURES["33500B+SR830+SR860"]) -> str:
    text = base.read_text()
    for old, new in text_changes.items():
        assert old in text, old
        text = text.replace(old, new)
    return text


def test_ctrl_c_during_a_dwell_leaves_the_output_off(tmp_path):
    procedure = load_procedure(PROCEDURES["33500B+SR830+SR860"])
    exp = open_experiment(procedure, seed=1)
    clock = exp.clock
    sleeps = {"n": 0}
    real_sleep = clock.sleep

    def interrupting_sleep(s):
        sleeps["n"] += 1
        if sleeps["n"] == 6:  # in the middle of the level ramp of the second dwell
            raise KeyboardInterrupt
        real_sleep(s)

    clock.sleep = interrupting_sleep
    with pytest.raises(KeyboardInterrupt):
        with exp:
            exp.measure(3.0)
            exp.measure(5.0)
    assert sleeps["n"] == 6
    assert not exp.bench.output_on and exp.bench.force_amplitude_n == 0.0


def test_ctrl_c_in_a_cli_run_exits_130_with_the_output_off(tmp_path, monkeypatch, capsys):
    import setmem_hil.drivers.instruments.phasor_dwell as phasor_dwell

    benches = []
    original = phasor_dwell.PhasorDwellExperiment.measure

    def measure(self, omega):
        benches.append(self.bench)
        if self.n_measured == 3:
            self.source.set_output(True)  # as if interrupted mid-dwell with the drive on
            raise KeyboardInterrupt
        return original(self, omega)

    monkeypatch.setattr(phasor_dwell.PhasorDwellExperiment, "measure", measure)
    code = main(["run", str(PROCEDURES["33500B+SR830+SR860"]), "--out", str(tmp_path / "r"), "--quiet"])
    assert code == 130
    assert benches and not benches[-1].output_on


def test_identity_mismatch_stops_before_any_output(tmp_path, capsys):
    # the procedure says Rigol DG800, the emulator at that address is a 33500B
    text = _emulated({'profile = "keysight-33500b"': 'profile = "rigol-dg800"'})
    path = tmp_path / "p.toml"
    path.write_text(text)
    procedure = load_procedure(path)
    from setmem_hil.loopback.instrument_emulation import start_emulators

    # start the emulators as the 33500B the lab actually owns
    real = dataclasses.replace(procedure, instruments={**procedure.instruments, "fgen": dataclasses.replace(
        procedure.instruments["fgen"], profile="keysight-33500b")})
    wired, bench, servers = start_emulators(real, 1)
    try:
        wrong = dataclasses.replace(wired, instruments={**wired.instruments, "fgen": dataclasses.replace(
            wired.instruments["fgen"], profile="rigol-dg800")}, backend=dataclasses.replace(wired.backend, emulation=None))
        from setmem_hil.errors import DeviceIdentityError
        from setmem_hil.drivers.instruments.instrument_set import open_instrument_experiment

        with pytest.raises(DeviceIdentityError, match=r"fgen .*expected a Rigol DG800.*Keysight Technologies,33522B"):
            open_instrument_experiment(wrong)
        generator = servers[0].emulator
        assert not any(re.match(r":?OUTP\d? (ON|1)", c, re.I) for c in generator.commands)
        assert generator.commands == ["*IDN?"]  # nothing but the identity query reached it
        assert not bench.output_on
    finally:
        for s in servers:
            s.close()


def test_identity_mismatch_from_the_cli_exits_4_naming_instrument_and_answer(tmp_path, capsys):
    from setmem_hil.sim_backends.instrument_bench import EmulatedBench
    from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, InstrumentServer, LockInEmulator
    from setmem_hil.sim_backends.beam import beam_parameters

    bench = EmulatedBench(beam_parameters())
    servers = [InstrumentServer(GeneratorEmulator(bench, "33500B")), InstrumentServer(LockInEmulator(bench, "force", "SR830")),
               InstrumentServer(LockInEmulator(bench, "response", "SR860"))]
    try:
        text = _emulated({
            '[backend.emulation]\ndrive_gain_ratio = 1.1        # the real amplifier gain is 10 % above the nominal one\nnoise_v_per_rthz = 2e-6\n': "",
            'profile = "keysight-33500b"\nresource = "TCPIP::127.0.0.1::0::SOCKET"': f'profile = "rigol-dg800"\nresource = "{servers[0].resource}"',
            'profile = "srs-sr830"\nresource = "TCPIP::127.0.0.1::0::SOCKET"': f'profile = "srs-sr830"\nresource = "{servers[1].resource}"',
            'profile = "srs-sr860"\nresource = "TCPIP::127.0.0.1::0::SOCKET"': f'profile = "srs-sr860"\nresource = "{servers[2].resource}"',
        })
        path = tmp_path / "rig.toml"
        path.write_text(text)
        assert main(["probe", str(path)]) == 4
        out = capsys.readouterr().out
        assert "FAILED" in out and "Keysight Technologies,33522B" in out
        code = main(["run", str(path), "--out", str(tmp_path / "r"), "--quiet"])
        err = capsys.readouterr().err
        assert code == 4
        assert "fgen" in err and "Keysight Technologies,33522B" in err and "nothing was switched on" in err
        assert servers[0].emulator.commands == ["*IDN?"] * 2  # the probe's and the run's identity queries, nothing else
        assert not bench.output_on
    finally:
        for s in servers:
            s.close()


def test_misspelt_instrument_key_exits_2_naming_it(tmp_path, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_emulated({"volt_per_unit = 0.0225": "volts_per_unit = 0.0225"}))
    assert main(["run", str(path), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "[instruments.lia_force]" in err and "volts_per_unit" in err and "did you mean 'volt_per_unit'" in err
    assert not (tmp_path / "r").exists() or not list((tmp_path / "r").iterdir())


def test_unknown_profile_and_wrong_role_are_input_errors(tmp_path, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_emulated({'profile = "srs-sr830"': 'profile = "srs-sr8300"'}))
    assert main(["run", "--check", str(path)]) == 2
    assert "did you mean 'srs-sr830'" in capsys.readouterr().err
    path.write_text(_emulated({'profile = "keysight-33500b"': 'profile = "srs-sr830"'}))
    assert main(["run", "--check", str(path)]) == 2
    assert "is a scpi-lockin (Stanford Research Systems SR830); the exciter needs a scpi-generator, modbus or dbc profile" in capsys.readouterr().err


def test_unreachable_resource_exits_4_with_nothing_switched_on(tmp_path, capsys):
    port = free_port()  # nothing listens there
    text = _emulated({
        '[backend.emulation]\ndrive_gain_ratio = 1.1        # the real amplifier gain is 10 % above the nominal one\nnoise_v_per_rthz = 2e-6\n': "",
        'profile = "keysight-33500b"\nresource = "TCPIP::127.0.0.1::0::SOCKET"': f'profile = "keysight-33500b"\nresource = "TCPIP::127.0.0.1::{port}::SOCKET"',
    })
    path = tmp_path / "p.toml"
    path.write_text(text)
    code = main(["run", str(path), "--out", str(tmp_path / "r"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 4
    assert f"fgen: cannot reach 'TCPIP::127.0.0.1::{port}::SOCKET'" in err and "refused" in err
    assert main(["probe", str(path)]) == 4


def test_url_in_backend_transport_is_refused_not_ignored(tmp_path, capsys):
    text = (REPO / "procedures" / "serial_loopback.toml").read_text()
    text = text.replace("[backend.transport]", '[backend.transport]\nurl = "/dev/ttyUSB0"') if "[backend.transport]" in text \
        else text.replace('kind = "serial-loopback"', 'kind = "serial-loopback"\n\n[backend.transport]\nurl = "/dev/ttyUSB0"')
    with pytest.raises(Exception, match="unknown key 'url'"):
        parse_procedure_text(text, "p.toml")


def test_sigterm_during_a_run_exits_130_with_the_output_off(tmp_path, monkeypatch):
    """``kill PID`` (SIGTERM) is handled like Ctrl-C: output off, journal closed, exit 130."""
    import os
    import signal

    import setmem_hil.drivers.instruments.phasor_dwell as phasor_dwell

    benches = []
    original = phasor_dwell.PhasorDwellExperiment.measure

    def measure(self, omega):
        benches.append(self.bench)
        if self.n_measured == 2:
            real_sleep = self.clock.sleep

            def sleep_then_term(s):  # SIGTERM arrives in the middle of the third dwell's ramp
                self.clock.sleep = real_sleep
                os.kill(os.getpid(), signal.SIGTERM)
                real_sleep(s)

            self.clock.sleep = sleep_then_term
        return original(self, omega)

    monkeypatch.setattr(phasor_dwell.PhasorDwellExperiment, "measure", measure)
    code = main(["run", str(PROCEDURES["33500B+SR830+SR860"]), "--out", str(tmp_path / "r"), "--quiet"])
    assert code == 130
    assert benches and not benches[-1].output_on and benches[-1].force_amplitude_n == 0.0
    assert len(read_snapshot(tmp_path / "r").measurements) == 2  # the two finished dwells are kept


@pytest.mark.slow
def test_the_journal_records_which_instruments_measured(tmp_path):
    procedure = load_procedure(PROCEDURES["Modbus+SR830+SR860"])
    procedure = dataclasses.replace(procedure, goal=dataclasses.replace(procedure.goal, max_experiments=0))
    start_run(procedure, tmp_path / "run", opener=open_experiment, quiet_report_hint=True)
    events = [e for e in read_snapshot(tmp_path / "run").events if e["kind"] == "instruments"]
    assert len(events) == 1
    message = events[0]["message"]
    assert "shaker_plc: Generic Modbus shaker controller" in message
    assert "lia_force: Stanford_Research_Systems,SR830,s/n86021" in message and "lia_response: Stanford_Research_Systems,SR860,004512" in message


def test_transport_settings_with_instruments_are_refused_not_ignored(tmp_path, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_emulated({'\n[backend.emulation]\n': '\n[backend.transport]\nurl = "/dev/ttyUSB0"\n\n[backend.emulation]\n'}))
    assert main(["run", "--check", str(path)]) == 2
    err = capsys.readouterr().err
    assert "[backend.transport]" in err and "[instruments.<name>]" in err


def test_multisine_on_lock_ins_exits_2_naming_the_instrument_and_the_key(tmp_path, capsys):
    """Issue 26's contract: lock-ins demodulate one frequency, so `[dwell] signal = "multisine"`
    on them is exit 2 naming the instrument and the key, before any instrument is touched."""
    text = (Path(__file__).resolve().parents[1] / "procedures" / "instruments_emulated.toml").read_text()
    proc = tmp_path / "multisine.toml"
    proc.write_text(text + '\n[dwell]\nsignal = "multisine"\n', encoding="utf-8")
    assert main(["run", str(proc), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "[dwell] key 'signal'" in err[0] and "[instruments.lia_force]" in err[0] and "lock-in" in err[0]
