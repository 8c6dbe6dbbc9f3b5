"""Issue 26 (part): the oscilloscope driver against emulated Rigol DS1000Z and Keysight InfiniiVision X.

Truth: the emulated bench's exact structure (its ``true_response``, independent of the scope),
sampled and quantised by emulators written from the scopes' programming guides. Independent
reference for the Keysight emulator: PyMeasure's ``KeysightDSOX1102G`` driver reads the same
record (ASCII transfer) and must agree with our driver's binary WORD transfer.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from setmem_hil.drivers.instruments.profile import ScopeProfile, load_profile, parse_profile
from setmem_hil.drivers.instruments.scpi_scope import ClippedChannel, ScpiScope
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceRejectedError, ProcedureError
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.instrument_bench import BenchSettings, EmulatedBench
from setmem_hil.sim_backends.instrument_emulators import InstrumentServer
from setmem_hil.sim_backends.scope_emulators import KeysightScopeEmulator, RigolScopeEmulator

FORCE_V_PER_N, RESPONSE_V_PER_M = 0.0225, 0.004
SCOPES = {"rigol-ds1000z": (RigolScopeEmulator, "ch4"), "keysight-infiniivision": (KeysightScopeEmulator, "ext")}


@pytest.fixture(params=list(SCOPES))
def rig(request):
    """A bench driven at 6 rad/s in steady state, a scope emulator, our driver on it."""
    emulator_class, trigger = SCOPES[request.param]
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    bench.set_generator(frequency_hz=6.0 / (2 * math.pi), amplitude_v=0.25, output_on=True)
    bench.clock.sleep(2000.0)
    # no gain error here: these tests check the transfer and the conversion, exact to the codes
    emulator = emulator_class(bench, {1: "force", 2: "response", 4: "sync"}, {"force": FORCE_V_PER_N, "response": RESPONSE_V_PER_M},
                              gain_error=0.0)
    server = InstrumentServer(emulator)
    profile = load_profile(request.param)
    link = VisaLink("scope", server.resource, termination=profile.termination, timeout_s=profile.timeout_s)
    scope = ScpiScope("scope", profile, link, (1, 2), trigger, 1.0, bench.clock)
    scope.check_identity()
    scope.initialise()
    yield bench, emulator, scope
    link.close()
    server.close()


def _phasor(t, y, omega):
    a = np.column_stack([np.sin(omega * t), np.cos(omega * t), np.ones_like(t)])
    c = np.linalg.lstsq(a, y, rcond=None)[0]
    return complex(c[0], c[1])


def test_a_record_gives_the_structure_response_within_the_quantisation(rig):
    bench, _, scope = rig
    scope.range_for(1, FORCE_V_PER_N * 1.0)
    scope.range_for(2, RESPONSE_V_PER_M * 1.2)
    record = scope.record(20.0)
    assert record.t_s[-1] - record.t_s[0] >= 20.0 * 0.99
    force = _phasor(record.t_s, record.volts[1] / FORCE_V_PER_N, 6.0)
    response = _phasor(record.t_s, record.volts[2] / RESPONSE_V_PER_M, 6.0)
    assert abs(force - 1.0) < 2e-3  # the sync edge is the drive's phase 0: the force is a pure sine there
    truth = bench.true_response(6.0)
    # 8-bit codes on a 2 mV/div screen, thousands of samples: the fit is far better than one code
    assert abs(response / force - truth) < 2e-3 * abs(truth)


def test_a_clipped_channel_is_refused_naming_it_and_ranging_up_recovers(rig):
    _, _, scope = rig
    scope.set_vertical_scale(1, scope.profile.vertical_scales_v[0])  # 1 mV/div: the 22.5 mV force clips
    with pytest.raises(ClippedChannel, match=r"scope \(.*\): channel 1: \d+ samples at the ADC's rails at 0.001 V/div") as info:
        scope.record(5.0)
    assert info.value.channel == 1
    while True:
        try:
            scope.record(5.0)
            break
        except ClippedChannel as exc:
            assert scope.range_up(exc.channel)
    assert scope.scales_v[1] >= 5e-3 * 0.99  # a 22.5 mV peak needs more than 4.4 mV/div on the ADC's 10.24 divisions


def test_no_trigger_is_an_error_naming_the_source(rig):
    bench, _, scope = rig
    bench.set_generator(output_on=False)  # no sync without the output: nothing triggers
    with pytest.raises(DeviceRejectedError, match=r"no trigger on (channel 4|its EXT input) within .* sync output"):
        scope.record(1.0)


def test_a_wrong_block_header_and_a_short_record_are_refused(rig):
    _, emulator, scope = rig
    emulator.bad_header = True
    with pytest.raises(DeviceRejectedError, match=r"scope \(.*\): .*(definite-length block|channel 1: 0 samples read)"):
        scope.record(1.0)
    emulator.short_by = 7
    with pytest.raises(DeviceRejectedError, match=r"channel 1: \d+ samples read, the preamble announced \d+"):
        scope.record(1.0)
    scope.record(1.0)  # the link is clean again afterwards


def test_a_rigol_record_longer_than_one_transfer_is_read_in_pieces(rig):
    bench, emulator, scope = rig
    if not isinstance(emulator, RigolScopeEmulator):
        pytest.skip("the InfiniiVision sends a record in one block")
    emulator.MAX_BYTES = 1000  # an instance limit: the profile's max_transfer_points must follow it
    scope.profile = ScopeProfile(**{**scope.profile.__dict__, "max_transfer_points": 1000})
    record = scope.record(20.0)
    assert record.volts[1].size == 3000
    ranges = [c for c in scope.link.transcript if c.startswith(":WAV:STAR")]
    assert ranges[-3:] == [":WAV:STAR 1", ":WAV:STAR 1001", ":WAV:STAR 2001"]


def test_pymeasure_reads_the_keysight_emulator_as_our_driver_does():
    """PyMeasure's DSOX1102G driver (ASCII transfer, its own preamble parsing) against our
    WORD transfer of the same record."""
    keysight = pytest.importorskip("pymeasure.instruments.keysight")
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    bench.set_generator(frequency_hz=1.0, amplitude_v=0.25, output_on=True)
    bench.clock.sleep(100.0)
    emulator = KeysightScopeEmulator(bench, {1: "force", 2: "response"}, {"force": FORCE_V_PER_N, "response": RESPONSE_V_PER_M},
                                     gain_error=0.0)
    server = InstrumentServer(emulator)
    profile = load_profile("keysight-infiniivision")
    link = VisaLink("scope", server.resource, termination="\n", timeout_s=5.0)
    try:
        scope = ScpiScope("scope", profile, link, (1,), "ext", 1.0, bench.clock)
        scope.initialise()
        scope.range_for(1, FORCE_V_PER_N)
        ours = scope.record(3.0, min_rate_hz=2000.0).volts[1]  # 5 s (0.5 s/div) at 10 000 points
        theirs = keysight.KeysightDSOX1102G(f"TCPIP::127.0.0.1::{server.port}::SOCKET", visa_library="@py",
                                            read_termination="\n", write_termination="\n")
        try:
            data, preamble = theirs.download_data("channel1", points=62500)
        finally:
            theirs.adapter.close()
        assert preamble["points"] == ours.size == 10000  # (PyMeasure reads the preamble before it switches to ASCII)
        np.testing.assert_allclose(np.asarray(data, dtype=float), ours, atol=1e-9, rtol=1e-5)
    finally:
        link.close()
        server.close()


def test_scope_profiles_declare_their_datasheet_figures_and_validate():
    rigol = load_profile("rigol-ds1000z")
    assert rigol.kind == "scpi-scope" and rigol.gain_accuracy == 0.03 and rigol.adc_bits == 8 and not rigol.has_ext_trigger
    # the programming guide's :ACQuire:MDEPth table: 3 and 4 channels share the 4-channel depths
    assert rigol.record_points[1][0] == 12000 and rigol.record_points[2][-1] == 12000000
    assert rigol.record_points[3] == rigol.record_points[4] == (3000, 30000, 300000, 3000000, 6000000)
    keysight = load_profile("keysight-infiniivision")
    assert keysight.has_ext_trigger and keysight.data_format == "word" and keysight.done_clear_mask == 8
    with pytest.raises(ProcedureError, match=r"\[commands\].*missing key 'arm'"):
        parse_profile(rigol.source and open(rigol.source).read().replace('arm = ":SING"\n', ""), "broken.toml")
    with pytest.raises(ProcedureError, match="exactly one of expect"):
        parse_profile(open(rigol.source).read().replace("[done]\nexpect = '^STOP$'", "[done]"), "broken.toml")


def test_a_window_a_sample_longer_than_a_time_scale_keeps_that_scale(rig):
    """A dwell's 120 s window is a whole number of samples (it asks 120.01 s): 10 s/div x 12
    divisions holds it; asking 1 % more moves to the next 1-2-5 step. The record's own time axis
    says how long it is."""
    bench, _, scope = rig
    divisions = scope.profile.time_divisions
    step = next(s for s in scope.profile.time_scales_s if s * divisions >= 1.0)
    length = step * divisions
    assert scope.record_length_for(length * 1.0001) == pytest.approx(length)
    bigger = next(s for s in scope.profile.time_scales_s if s > step) * divisions
    assert scope.record_length_for(length * 1.02) == pytest.approx(bigger)
    record = scope.record(length * 1.0001)
    assert record.t_s[-1] - record.t_s[0] + record.sample_interval_s == pytest.approx(length, rel=1e-3)


def test_the_ds1000z_memory_depth_is_set_while_running_as_its_users_report():
    """DS1000Z users report ``:ACQ:MDEP`` refused with -221 "Settings conflict" while the scope
    is stopped (after ``:STOP`` or a single acquisition); the emulator refuses it there, and the
    driver's record still gets the depth it needs (issue 40, item 1)."""
    bench = EmulatedBench(beam_parameters(), BenchSettings())
    bench.set_generator(frequency_hz=6.0 / (2 * math.pi), amplitude_v=0.25, output_on=True)
    bench.clock.sleep(2000.0)
    emulator = RigolScopeEmulator(bench, {1: "force", 2: "response", 4: "sync"}, {"force": FORCE_V_PER_N, "response": RESPONSE_V_PER_M})
    server = InstrumentServer(emulator)
    profile = load_profile("rigol-ds1000z")
    link = VisaLink("scope", server.resource, termination=profile.termination, timeout_s=profile.timeout_s)
    try:
        # the rule itself, as a user meets it: set in STOP, the error queue says -221
        link.write(":STOP")
        link.write(":ACQ:MDEP 30000")
        assert link.query(":SYST:ERR?").startswith("-221,")
        assert link.query(":ACQ:MDEP?") == "12000"  # not executed
        scope = ScpiScope("scope", profile, link, (1, 2), "ch4", 1.0, bench.clock)
        scope.initialise()
        for rate in (0.0, 3000.0 / 0.6):  # the shallowest depth, then a deeper one after a record
            scope.range_for(1, FORCE_V_PER_N)
            scope.range_for(2, RESPONSE_V_PER_M * 1.2)
            record = scope.record(0.5, min_rate_hz=rate)
            assert record.volts[1].size == int(link.query(":ACQ:MDEP?")) == scope.points
        assert scope.points == 30000
    finally:
        link.close()
        server.close()
