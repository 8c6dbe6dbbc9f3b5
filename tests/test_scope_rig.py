"""Issue 26: a generator and one oscilloscope as the force and three response roles of a rig.

Truth is independent of the drivers: each output's receptance is the cantilever's at its
sensor position (``beam_parameters_at``, mode shapes checked in ``test_beam``), reached only
through the emulated bench's exact time-domain record behind the scope emulator (written from the
DS1000Z and InfiniiVision programming guides, with a gain error on every input within the
datasheets' figures) and our drivers over PyVISA.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.drivers.instruments import scope_rig
from setmem_hil.errors import ProcedureError
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure_file import parse_procedure_text
from setmem_hil.sim_backends.beam import beam_parameters_at

REPO = Path(__file__).resolve().parents[1]
SCOPE_PROCEDURE = REPO / "procedures" / "instruments_scope_emulated.toml"
POSITIONS = (1.0, 0.7, 0.4)  # channels 2, 3, 4 in the shipped procedure
# the shipped procedure without its channel match: every point carries the datasheet's gain accuracy
DATASHEET_TEXT = re.sub(r"\nchannel_match = [^\n]*", "", SCOPE_PROCEDURE.read_text())


def _truth(x: float, omega: float) -> complex:
    return complex(np.ravel(beam_parameters_at(x, 1.0).frequency_response(np.array([omega])))[0])


def _procedure(text: str | None = None):
    return parse_procedure_text(text or DATASHEET_TEXT, str(SCOPE_PROCEDURE))


def test_one_scope_holds_the_force_and_three_response_roles():
    p = _procedure()
    scope = p.instruments["scope"]
    assert p.backend.force == p.backend.response == "scope"
    assert scope.channel_roles == {"force": (1,), "response": (2, 3, 4)}
    assert p.backend.output_order() == ("scope.ch2", "scope.ch3", "scope.ch4")
    q = _procedure(DATASHEET_TEXT.replace('response = "scope"', 'response = "scope"\ncontrol_output = 3'))
    assert q.backend.output_order() == ("scope.ch4", "scope.ch2", "scope.ch3")


@pytest.mark.parametrize("change, where", [
    ("[instruments.scope.channel.4]\nvolt_per_unit = 0.04\ncalibration_uncertainty = 0.01\n", r"\[instruments.scope.channel.4\].*missing"),
    ('channels = { force = 1, response = [2, 3, 4] }', r"key 'trigger_channel'.*response channel"),
    ('sensors = [1.0, 0.7, 0.4]', r"\[backend.emulation\] key 'sensors'.*one position per response channel"),
])
def test_a_scope_table_that_cannot_work_names_the_key(change, where):
    text = DATASHEET_TEXT
    if change.startswith("[instruments.scope.channel.4]"):
        text = text.replace(change, "")
    elif change.startswith("channels"):
        text = text.replace(change, change + "\ntrigger_channel = 3")
    else:
        text = text.replace(change, "sensors = [1.0, 0.7]")
    with pytest.raises(ProcedureError, match=where):
        _procedure(text)


@pytest.fixture(scope="module")
def dwells():
    """Four dwells through the emulated 33500B + DS1104Z (drive gain 10 % above nominal)."""
    out = []
    with open_experiment(_procedure(), 3) as exp:
        # downwards: no resonance's ringing under the next point; 0.1 rad/s plans a window longer than the
        # DS1000Z's longest record (600 s): fitted on what the scope holds
        for omega in (55.0, 17.5, 5.9, 0.97, 0.1):
            out.append(exp.measure(omega))
        bench, counters = exp.bench, dict(exp.rig.sensor.counters)
    return out, bench, counters


@pytest.mark.slow
def test_every_channel_holds_its_sensors_truth(dwells):
    measurements, _, _ = dwells
    for m in measurements:
        points = [(m.response, m.bound), *m.others]
        assert len(points) == 3
        for x, (g, bound) in zip(POSITIONS, points):
            assert abs(g - _truth(x, m.omega_rad_s)) <= bound, (x, m.omega_rad_s)
    # mode 2 has a node near x = 0.78: the sensor at 0.7 sees far less of it than the tip
    m = measurements[2]
    assert abs(m.response - m.others[0][0]) > m.bound + m.others[0][1]


def test_the_bound_carries_the_scopes_gain_accuracy(dwells):
    # 3 % of full scale on each of the two channels of a ratio: a 4 % gain error each (module
    # channel_errors), so at least 8 % of the ratio
    measurements, _, _ = dwells
    for m in measurements:
        assert m.bound >= 0.08 * abs(m.response)


def test_closed_loop_level_keeps_the_force_within_the_limit_and_the_output_off_after(dwells):
    measurements, bench, counters = dwells
    assert bench.settings.drive_gain_ratio == pytest.approx(1.1)
    assert bench.peak_force_n <= 1.05 * 1.0
    assert bench.peak_force_n >= 0.8  # the level was closed on the measured force, not left low
    assert not bench.output_on
    assert counters["level_steps"] >= len(measurements)
    assert all(m.rig_s > 0 for m in measurements)


def test_ctrl_c_during_a_record_leaves_the_output_off(monkeypatch):
    calls = []

    def interrupted(self, duration_s, *args):
        calls.append(duration_s)
        if len(calls) == 3:  # inside the first dwell's main record, the output on
            raise KeyboardInterrupt
        return original(self, duration_s, *args)

    original = scope_rig.ScopeSensor._record
    monkeypatch.setattr(scope_rig.ScopeSensor, "_record", interrupted)
    exp = open_experiment(_procedure(), 3)
    try:
        with pytest.raises(KeyboardInterrupt):
            exp.measure(5.9)
        assert not exp.bench.output_on
    finally:
        exp.close()
    assert not exp.bench.output_on


def test_a_keysight_triggers_on_its_ext_input():
    text = DATASHEET_TEXT.replace('profile = "rigol-ds1000z"', 'profile = "keysight-infiniivision"')
    with open_experiment(_procedure(text), 5) as exp:
        assert exp.rig.scope.trigger_source == "ext"
        m = exp.measure(17.5)
        for x, (g, bound) in zip(POSITIONS, [(m.response, m.bound), *m.others]):
            assert abs(g - _truth(x, 17.5)) <= bound


MULTISINE_TEXT = DATASHEET_TEXT.replace("[safety]", '[dwell]\nsignal = "multisine"\n\n[safety]', 1)


@pytest.mark.slow
@pytest.mark.parametrize("generator", ["keysight-33500b", "rigol-dg800", "siglent-sdg2000x"])
def test_a_multisine_record_through_the_arbitrary_waveform_holds_every_lines_truth(generator):
    """The generator plays the record as an arbitrary waveform (held points: the 33500B's ASCII
    floats, the DG800's 14-bit codes in CON/END packages, the SDG's 16-bit TrueArb codes), the
    DS1104Z samples force and three responses; every line of every output holds its truth; the
    level is closed on the force (drive gain 10 % high); a sine after it is the generator's own
    again."""
    text = MULTISINE_TEXT.replace('profile = "keysight-33500b"', f'profile = "{generator}"')
    with open_experiment(_procedure(text), 3) as exp:
        lines = [5.0, 6.0, 17.0, 18.5]
        measurements = exp.measure_multisine(lines)
        assert [m.omega_rad_s for m in measurements] == lines
        for m in measurements:
            for x, (g, bound) in zip(POSITIONS, [(m.response, m.bound), *m.others]):
                assert abs(g - _truth(x, m.omega_rad_s)) <= bound, (x, m.omega_rad_s)
        assert exp.bench.peak_force_n <= 1.0  # the waveform's peak, levelled with room for the channel's error
        assert exp.bench.peak_force_n >= 0.85
        assert not exp.bench.output_on
        m = exp.measure(6.2)
        assert exp.bench.arb_points is None  # the generator's own sine again
        assert abs(m.response - _truth(1.0, 6.2)) <= m.bound
    assert not exp.bench.output_on


@pytest.mark.slow
def test_the_first_record_through_the_sdg_holds_every_points_truth_on_seed_105(tmp_path):
    """Found by the rig-time benchmark: in seed 105's first record through the SDG2000X the tip
    channel's search for an unmodelled transient refined its pole into the line at 0.9 rad/s
    (undamped, 0.9000 rad/s), the scan's own exclusion, and the line came out at 3x its truth
    under a bound a thirtieth of the error. Every point of the first record holds its truth.
    (As the benchmark runs it: the channel match measured on the emulated tee.)"""
    text = SCOPE_PROCEDURE.read_text().replace("[safety]", '[dwell]\nsignal = "multisine"\n\n[safety]', 1)
    text = text.replace('profile = "keysight-33500b"', 'profile = "siglent-sdg2000x"').replace("\nseed = 1\n", "\nseed = 105\n")
    procedure = parse_procedure_text(text, str(tmp_path / "scope.toml"))  # no match file there: measured first
    with open_experiment(procedure, 105) as exp:
        measurements = exp.measure_multisine(list(procedure.initial_omegas_rad_s))
    for m in measurements:
        for x, (g, bound) in zip(POSITIONS, [(m.response, m.bound), *m.others]):
            assert abs(g - _truth(x, m.omega_rad_s)) <= bound, (x, m.omega_rad_s)


def test_multisine_without_an_arbitrary_waveform_generator_names_the_exciter(tmp_path):
    """A generator profile without an [arbitrary] table (here the DG800's with it cut off)."""
    shipped = (REPO / "drivers" / "instruments" / "profiles" / "rigol-dg800.toml").read_text()
    cut = tmp_path / "dg800-sine-only.toml"
    cut.write_text(shipped[: shipped.index("\n# Arbitrary waveforms")])
    text = MULTISINE_TEXT.replace('profile = "keysight-33500b"', f'profile = "{cut}"')
    from setmem_hil.drivers.instruments.instrument_set import check_instruments

    with pytest.raises(ProcedureError, match=r"\[dwell\] key 'signal'.*\[instruments.fgen\].*\[arbitrary\]"):
        check_instruments(_procedure(text))
    for generator in ("keysight-33500b", "rigol-dg800", "siglent-sdg2000x", "siglent-sdg1000x"):  # the shipped ones: accepted
        check_instruments(_procedure(MULTISINE_TEXT.replace('profile = "keysight-33500b"', f'profile = "{generator}"')))


def _faulty_run(tmp_path, monkeypatch, capsys, fault):
    """`setmem-hil run` on the shipped scope procedure (without its channel match) with ``fault``
    applied to every scope emulator; returns the exit code, stderr's lines and the bench."""
    from setmem_hil.cli.main import main
    from setmem_hil.loopback import instrument_emulation
    from setmem_hil.sim_backends.scope_emulators import RigolScopeEmulator

    benches = []
    start = instrument_emulation.start_emulators

    def capturing(procedure, seed, tee=False):
        wired, bench, servers = start(procedure, seed, tee)
        benches.append(bench)
        return wired, bench, servers

    monkeypatch.setattr(instrument_emulation, "start_emulators", capturing)
    fault(RigolScopeEmulator, monkeypatch)
    (tmp_path / "scope.toml").write_text(DATASHEET_TEXT)
    code = main(["run", str(tmp_path / "scope.toml"), "--out", str(tmp_path / "run"), "--quiet"])
    return code, capsys.readouterr().err.strip().splitlines(), benches[0]


def _clipped(cls, mp):  # the tip's channel at the ADC's top rail at every range
    original = cls._adc
    mp.setattr(cls, "_adc", lambda self, ch, v: np.full(v.size, 255) if ch == 2 else original(self, ch, v))


def _no_trigger(cls, mp):
    mp.setattr(cls, "_trigger_can_fire", lambda self: False)


def _bad_header(cls, mp):
    mp.setattr(cls, "_block", lambda self, payload, digits: b"#X" + payload)


def _short(cls, mp):  # every data transfer loses its last 5 points (the emulator's hook, made permanent)
    original = cls._data
    mp.setattr(cls, "_data", lambda self: (setattr(self, "short_by", 5), original(self))[1])


@pytest.mark.parametrize("fault, words", [(_clipped, "channel 2"), (_no_trigger, "no trigger"), (_bad_header, "scope"),
                                          (_short, "the preamble announced")])
def test_a_scope_fault_is_exit_4_one_line_naming_the_scope_with_the_output_off(tmp_path, monkeypatch, capsys, fault, words):
    code, err, bench = _faulty_run(tmp_path, monkeypatch, capsys, fault)
    assert code == 4
    assert len(err) == 1 and "scope" in err[0] and words in err[0], err
    assert not bench.output_on


@pytest.mark.slow
@pytest.mark.parametrize("signal", ["sine", "multisine"])
def test_a_campaign_through_the_matched_scope_reaches_the_goal_with_every_truth_inside(tmp_path, signal):
    """The shipped 33500B + DS1104Z procedure as a technician runs it: `calibrate-channels` (the
    generator on a tee to the four channels), then `run` (single sines; the multisine run finds
    no match file and, emulated, measures it on the emulated tee first), single sines and multisine records:
    mu-bar < 1 certified, every output's truth inside its bound at every point, the force never
    above 1.05 x max_amplitude_n (drive gain 10 % high), the output off at the end, the outputs
    exported by name."""
    from setmem_hil.campaign.session import start_run
    from setmem_hil.cli.main import main
    from setmem_hil.io.journal import read_snapshot
    from setmem_hil.io.procedure_file import load_procedure

    text = SCOPE_PROCEDURE.read_text()
    if signal == "multisine":
        text = text.replace("[safety]", '[dwell]\nsignal = "multisine"\n\n[safety]', 1)
    (tmp_path / "scope.toml").write_text(text)
    if signal == "sine":
        assert main(["calibrate-channels", str(tmp_path / "scope.toml")]) == 0
        assert (tmp_path / "instruments_scope_emulated.channel-match.json").exists()
    procedure = load_procedure(tmp_path / "scope.toml")
    opened = []

    def opener(p, seed):
        opened.append(open_experiment(p, seed))
        return opened[-1]

    outcome = start_run(procedure, tmp_path / "run", opener=opener, quiet_report_hint=True)
    assert outcome.summary["reached_goal"] and outcome.summary["final_mu_peak"] < 1.0
    assert outcome.summary["rig_s"] > 0
    measurements = read_snapshot(tmp_path / "run").measurements
    assert len(measurements) == 15 + outcome.summary["experiments_added"]
    ratios = [abs(g - _truth(x, m.omega_rad_s)) / bound
              for m in measurements for x, (g, bound) in zip(POSITIONS, [(m.response, m.bound), *m.others])]
    assert np.mean(np.array(ratios) <= 1.0) >= 0.99, max(ratios)
    bench = opened[0].bench
    assert bench.peak_force_n <= 1.05 * procedure.safety.max_amplitude_n
    assert not bench.output_on
    from setmem_hil.io.journal import Journal

    journal = Journal.open(tmp_path / "run")  # the session armed the generator and read its output back off
    try:
        kinds = [(e["kind"], e["message"]) for e in journal.events()]
    finally:
        journal.close()
    assert any(k == "exciter-armed" and "fgen" in m for k, m in kinds)
    assert any(k == "output-off" and m.startswith("confirmed") and "fgen" in m for k, m in kinds)
    assert any(k == "instruments" and "RIGOL TECHNOLOGIES,DS1104Z" in m and "scope channel match" in m for k, m in kinds)
    assert main(["export", str(tmp_path / "run"), "--csv", str(tmp_path / "csv")]) == 0
    import csv

    rows = list(csv.DictReader((tmp_path / "csv" / "measurements.csv").open()))
    assert {r["output"] for r in rows} == {"scope.ch2", "scope.ch3", "scope.ch4"} and len(rows) == 3 * len(measurements)


def _bare_sensor(noise_div: dict[int, float]):
    """A ScopeSensor's resolution, without instruments: the DS1000Z profile, four channels."""
    from types import SimpleNamespace

    from setmem_hil.drivers.instruments.profile import load_profile
    from setmem_hil.drivers.instruments.scpi_scope import ScpiScope

    sensor = scope_rig.ScopeSensor.__new__(scope_rig.ScopeSensor)
    sensor.scope = SimpleNamespace(profile=load_profile("rigol-ds1000z"), SCREEN_FILL=ScpiScope.SCREEN_FILL)
    sensor.force = scope_rig.ScopeChannel(1, 0.0225, quantity="force")
    sensor.responses = tuple(scope_rig.ScopeChannel(n, 0.04) for n in (2, 3, 4))
    sensor.noise_div = noise_div
    return sensor


@pytest.mark.parametrize("noise_code", [0.0, 0.4, 0.47, 0.6])
def test_the_smallest_line_a_scope_resolves_carries_the_chosen_share_of_quantization_in_its_bound(noise_code):
    """The split criterion against the bound the point then carries: a line at 1 / dynamic_range
    of a record's summed amplitudes (the sum ranged as the scope ranges it) gets, from
    :func:`scope_channel_error` (the per-point term), a quantization term of RESOLUTION_SHARE of
    its amplitude; more dither resolves smaller lines, none leaves a whole code."""
    from setmem_hil.estimation.channel_errors import adc_code, scope_channel_error

    p = _bare_sensor({}).scope.profile
    code_div = adc_code(p.divisions, p.adc_bits)
    sensor = _bare_sensor({ch: noise_code * code_div for ch in (1, 2, 3, 4)} if noise_code else {})
    scale_v = 0.1
    summed_v = sensor.scope.SCREEN_FILL / scope_rig.RANGE_HEADROOM * p.divisions / 2 * scale_v  # what ranging fills
    line_v = summed_v / sensor.dynamic_range
    error = scope_channel_error(gain_accuracy=p.gain_accuracy, full_scale_v=p.divisions * scale_v, adc_bits=p.adc_bits,
                                volt_per_unit=1.0, calibration=0.0, omega_rad_s=1.0, trigger_jitter_s=0.0,
                                noise_v=noise_code * code_div * scale_v)
    assert error.absolute == pytest.approx(scope_rig.RESOLUTION_SHARE * line_v, rel=1e-9)
    if not noise_code:
        assert sensor.dynamic_range < 8  # a whole code of bias: an 8-bit screen resolves little
    # the least dithered channel decides
    mixed = _bare_sensor({1: 0.6 * code_div, 2: 0.6 * code_div, 3: 0.6 * code_div})
    assert mixed.dynamic_range == pytest.approx(_bare_sensor({}).dynamic_range)


def test_before_any_model_the_outputs_other_than_the_control_output_get_room_for_a_mode_growing_from_rest():
    """The first record's ranging: the levelling record's peaks times the level ratio, with
    FIRST_RECORD_ROOM on the non-control outputs while no model can predict the growth; once the
    campaign has models, every channel gets the same room (the model then ranges for growth)."""
    from types import SimpleNamespace

    asked: dict[int, float] = {}
    sensor = _bare_sensor({})
    sensor.scope.range_for = lambda channel, peak_v: asked.__setitem__(channel, peak_v)
    peaks = {1: 0.2, 2: 0.3, 3: 0.3, 4: 0.05}
    record = SimpleNamespace(volts={ch: v * np.sin(np.linspace(0.0, 20.0, 400)) for ch, v in peaks.items()})
    peak_of = {ch: float(np.max(np.abs(record.volts[ch]))) for ch in peaks}

    sensor.response_models = ()
    sensor._range_from(record, 1.0)
    per_unit = {ch: asked[ch] / peak_of[ch] for ch in peaks}
    assert per_unit[1] == pytest.approx(per_unit[2])  # force and control output: the same room
    assert per_unit[3] == pytest.approx(scope_rig.FIRST_RECORD_ROOM * per_unit[2])
    assert per_unit[4] == pytest.approx(scope_rig.FIRST_RECORD_ROOM * per_unit[2])
    assert per_unit[2] >= scope_rig.RANGE_HEADROOM  # never less than the peak with its room

    sensor.response_models = (object(),)
    sensor._range_from(record, 1.0)
    assert {ch: asked[ch] / peak_of[ch] for ch in peaks} == pytest.approx({ch: per_unit[2] for ch in peaks})


def test_a_line_near_a_lightly_damped_mode_driven_from_rest_beats_up_to_twice_its_steady_amplitude():
    """Why FIRST_RECORD_ROOM is 2 (the closed-form response from rest, not our ranging code): a
    line at 0.05 rad/s from a mode with zeta = 0.001 reaches, within a 150 s record, close to
    twice its steady amplitude (the free response started at rest is the forced one's size, up to
    the ratio of the frequencies)."""
    from setmem_hil.estimation.response_growth import zero_state_response
    from setmem_hil.model.modal_model import ModalParameters

    omega_n, zeta, line = 1.0, 0.001, 1.05
    model = ModalParameters.from_modal(omega_n, zeta, 1.0)
    t = np.linspace(0.0, 150.0, 30001)
    y = zero_state_response(model, [line], [1.0], [(0.0, 1.0)], t)
    steady = abs(1.0 / (omega_n**2 - line**2 + 2j * zeta * omega_n * line))
    assert 1.9 * steady < np.max(np.abs(y)) <= (1.0 + line / omega_n) * steady


LATE_TEST_TIMEOUT_S = 3.0


@pytest.mark.slow
def test_a_reply_late_past_its_timeout_mid_campaign_is_retried_with_the_whole_setup_restored(tmp_path, monkeypatch, capsys):
    """Issue 46: one `:TRIG:STAT?` reply arrives after the link gave up on it (the scope emulator
    sends it late, on purpose). The dwell's retry opens a fresh session, sends the scope's whole
    setup again (the profile's init, every channel, the trigger, the waveform format, the time
    base) before it arms, and the campaign finishes: exit 0, every point kept, the fault and
    the reconnect journaled. The truth is the emulator's transcript and the beam."""
    from setmem_hil.cli.main import main
    from setmem_hil.io.journal import Journal
    from setmem_hil.loopback import instrument_emulation

    # 3 s, and the late reply 2.5 times that: at 1 s, a loaded machine made other replies late too
    # (the stop-53 CI run beside other work), and the test measured the machine, not the retry
    monkeypatch.setattr(instrument_emulation, "EMULATED_LINK_TIMEOUT_S", LATE_TEST_TIMEOUT_S)
    servers, armed = [], []
    start = instrument_emulation.start_emulators

    def capturing(procedure, seed, tee=False):
        wired, bench, started = start(procedure, seed, tee)
        servers.extend(s for s in started if type(s.emulator).__name__ == "RigolScopeEmulator")
        return wired, bench, started

    monkeypatch.setattr(instrument_emulation, "start_emulators", capturing)
    from setmem_hil.campaign import journaled_run

    original = journaled_run.run_journaled_campaign

    def with_late_reply(procedure, experiment, journal, **kw):
        def late_on_the_fourth_dwell(event, **info):
            if event == "measure" and info["index"] == 4 and not armed:
                scope = servers[-1]
                armed.append(len(scope.emulator.commands))
                scope.delay_replies(2.5 * LATE_TEST_TIMEOUT_S, count=1, matching=r"TRIG:STAT\?")
        kw["observers"] = [*kw.get("observers", ()), late_on_the_fourth_dwell]
        return original(procedure, experiment, journal, **kw)

    monkeypatch.setattr(journaled_run, "run_journaled_campaign", with_late_reply)
    text = DATASHEET_TEXT.replace("max_experiments = 30", "max_experiments = 0")
    (tmp_path / "scope.toml").write_text(text)
    code = main(["run", str(tmp_path / "scope.toml"), "--out", str(tmp_path / "run"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 0, err
    after = servers[-1].emulator.commands[armed[0]:]
    late = next(i for i, c in enumerate(after) if c.startswith(":TRIG:STAT?"))
    # after the late reply: the init again (its *CLS and :TRIG:SWE SING), channels and trigger before the next :SING
    rest = after[late + 1:]
    restored = rest[: rest.index(":SING")]
    for needed in ("*CLS", ":TRIG:SWE SING", ":CHAN1:DISP ON", ":WAV:MODE RAW", ":TIM:MAIN:SCAL"):
        assert any(c.startswith(needed) for c in restored), (needed, restored)
    journal = Journal.open(tmp_path / "run")
    try:
        kinds = [e["kind"] for e in journal.events()]
        measured = journal.measurements()
    finally:
        journal.close()
    assert "device_error" in kinds and "reconnect" in kinds
    assert len(measured) == 15
    ratios = [abs(m.response - _truth(1.0, m.omega_rad_s)) / m.bound for m in measured]
    assert max(ratios) <= 1.0, max(ratios)
