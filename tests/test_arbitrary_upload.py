"""Issue 26 item 3: arbitrary waveforms on the three generator families the project ships
profiles for, through our driver and PyVISA to emulators written from each programming guide:

* Keysight 33500B: ``SOURce:DATA:ARBitrary:DAC <name>,<IEEE block>`` (16-bit codes, ``FORMat:BORDer``),
  then ``*OPC?`` with a timeout from the upload's size (the emulator takes time to parse one);
* Rigol DG800: ``:DATA:DAC16 VOLATILE,<CON|END>,<IEEE block>`` (14-bit codes, packages);
* Siglent SDG: ``C<n>:WVDT WVNM,<name>,LENGTH,<n>B,WAVEDATA,<bytes>`` (16-bit two's complement).

Truth is the waveform asked for: what the emulator decodes from the bytes on the wire must equal
it within half a DAC step, and the points the driver says are playing must be exactly what the
instrument decoded (the levelling fits the force to them). The wire format is checked a second
way with PyVISA's own block parser.
"""

from __future__ import annotations

import numpy as np
import pytest
from pyvisa import util as visa_util

from setmem_hil.drivers.instruments.profile import load_profile
from setmem_hil.drivers.instruments.scpi_generator import ScpiGenerator, dac_codes, points_of_codes
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceRejectedError, DeviceTimeoutError
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.instrument_bench import EmulatedBench
from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, InstrumentServer, SiglentGeneratorEmulator

GENERATORS = {  # profile: (emulator class, emulator model, half a DAC step in points)
    "keysight-33500b": (GeneratorEmulator, "33500B", 1.0 / 32767),
    "rigol-dg800": (GeneratorEmulator, "DG800", 1.0 / 16383),
    "siglent-sdg2000x": (SiglentGeneratorEmulator, "SDG2000X", 1.0 / 32767),
    "siglent-sdg1000x": (SiglentGeneratorEmulator, "SDG1000X", 1.0 / 32767),
}


class Rig:
    def __init__(self, profile_name: str):
        cls, model, self.step = GENERATORS[profile_name]
        self.bench = EmulatedBench(beam_parameters())
        self.emulator = cls(self.bench, model, channel=1)
        self.server = InstrumentServer(self.emulator)
        profile = load_profile(profile_name)
        self.gen = ScpiGenerator("fgen", profile, VisaLink("fgen", self.server.resource, termination=profile.termination,
                                                          timeout_s=profile.timeout_s))
        self.gen.check_identity()
        self.gen.initialise()

    def close(self):
        self.gen.set_output(False)
        self.gen.close()
        self.server.close()


@pytest.fixture(params=sorted(GENERATORS))
def rig(request):
    r = Rig(request.param)
    yield r
    r.close()


def _waveform(n: int, seed: int = 0) -> np.ndarray:
    """A multisine-like record whose bytes hold every value, newlines and ';' included."""
    t = np.arange(n) / n
    x = np.sin(2 * np.pi * 3 * t) + 0.6 * np.sin(2 * np.pi * 17 * t + 1.0) + 0.05 * np.random.default_rng(seed).standard_normal(n)
    return x / np.max(np.abs(x))


@pytest.mark.parametrize("n", [8, 1000, 20000])
def test_the_generator_plays_the_waveform_asked_for_and_says_so(rig, n):
    n = min(n, rig.gen.profile.arbitrary.max_points)  # the SDG1000X's whole memory: 16384
    points = _waveform(n)
    rate = 123.456
    played = rig.gen.play_arbitrary(points, rate)
    assert played.size == n and np.max(np.abs(played)) <= 1.0
    assert np.max(np.abs(played - points)) <= rig.step * (1 + 1e-9)  # the waveform asked for, to half a DAC step
    assert np.max(np.abs(rig.bench.arb_points - played)) <= 1e-12  # what the instrument decoded (to rounding)
    assert rig.bench.arb_rate_hz == pytest.approx(rate, rel=1e-12)
    rig.gen.set_amplitude_v(0.2)
    rig.gen.set_output(True)
    assert rig.bench.output_on  # it plays: the function is the arbitrary one, held at the rate
    rig.gen.set_output(False)
    rig.gen.play_sine()
    rig.gen.set_output(True)
    assert rig.bench.output_on and rig.bench.arb_points is None  # the generator's own sine again


def test_the_dg800_waveform_goes_in_packages_of_8_kpts_flagged_con_then_end():
    r = Rig("rigol-dg800")
    try:
        r.gen.play_arbitrary(_waveform(20000), 100.0)
        uploads = [c for c in r.emulator.commands if "DAC16" in c.upper()]
        assert [c.split(",")[1] for c in uploads] == ["CON", "CON", "END"]
        assert r.emulator.settings[1]["FUNC"] == "ARB" and r.emulator.settings[1]["SRAT"] == 100.0
    finally:
        r.close()


def test_the_siglent_plays_truearb_held_at_the_rate():
    r = Rig("siglent-sdg2000x")
    try:
        r.gen.play_arbitrary(_waveform(500), 250.0)
        s = r.emulator.channels[1]
        assert s["WVTP"] == "ARB" and s["ARWV"] == "SETMEM" and s["SRATE"] == ("TARB", 250.0, "HOLD")
    finally:
        r.close()


@pytest.mark.parametrize("codes, signed", [((0, 16383), False), ((-32767, 32767), True)])
def test_dac_codes_on_the_wire_decode_with_pyvisas_own_parser(codes, signed):
    """The block our driver builds, read back by PyVISA's IEEE 488.2 parser (a second formulation
    of the framing), holds codes that decode to the points within half a step."""
    points = _waveform(300)
    datatype = "h" if signed else "H"
    block = visa_util.to_ieee_block(dac_codes(points, codes).tolist(), datatype, False)
    back = np.array(visa_util.from_ieee_block(block, datatype, False))
    assert np.max(np.abs(points_of_codes(back, codes) - points)) <= 1.0 / (codes[1] - codes[0]) * (1 + 1e-9)
    assert back.min() >= codes[0] and back.max() <= codes[1]
    assert np.array_equal(points_of_codes(dac_codes(np.array([-1.0, 1.0]), codes), codes), [-1.0, 1.0])


def test_a_waveform_the_generator_cannot_hold_is_refused_before_anything_is_sent():
    r = Rig("siglent-sdg1000x")
    try:
        before = len(r.emulator.commands)
        with pytest.raises(DeviceRejectedError, match=r"fgen .*8-16384 points.*nothing was sent"):
            r.gen.play_arbitrary(_waveform(20000), 100.0)
        assert len(r.emulator.commands) == before
    finally:
        r.close()


def test_an_upload_the_instrument_rejects_names_the_package():
    """A DG800 whose memory is smaller than its profile says: the error queue after the package
    names it (exit 4 in a run), and the output stays off."""
    r = Rig("rigol-dg800")
    try:
        r.emulator.DG800_MAX_POINTS = 10000
        with pytest.raises(DeviceRejectedError, match=r"fgen .*Data out of range.*DAC16 \(package 2 of 3, 6667 points\)"):
            r.gen.play_arbitrary(_waveform(20000), 100.0)
        assert not r.bench.output_on and r.bench.arb_points is None
    finally:
        r.close()


def test_the_33500b_takes_a_long_record_as_a_binary_block_and_waits_for_it():
    """Issue 40 item 2: the 881,852 points of the hold-out rig's multisine go as one block of
    16-bit codes (1.8 MB, not 7 MB of text), and ``*OPC?`` waits for the instrument to take it
    in: the emulator parses as slowly as a real one would parse text, longer than the link's
    2 s timeout, and the run goes on without a late reply answering a later query."""
    r = Rig("keysight-33500b")
    try:
        r.emulator.binary_s_per_byte = 3.0 / (2 * 881_852)  # 3 s to take the block in: longer than the 2 s timeout
        points = _waveform(881_852)
        played = r.gen.play_arbitrary(points, 40e3)
        assert np.max(np.abs(played - points)) <= 1.0 / 32767 * (1 + 1e-9)
        assert np.max(np.abs(r.bench.arb_points - played)) <= 1e-12
        sent = [c for c in r.emulator.commands if "DATA:ARB" in c.upper()]
        assert sent == ["SOUR1:DATA:ARB:DAC SETMEM,"] and "FORM:BORD NORM" in r.emulator.commands
        assert r.emulator.commands[r.emulator.commands.index(sent[0]) + 1] == "*OPC?"
        assert r.gen.link.stale_replies == 0
        r.gen.set_output(True)
        r.gen.set_output(False)  # the read-backs answer their own queries
    finally:
        r.close()


def test_a_reply_that_arrives_after_its_query_timed_out_never_answers_the_next_query():
    """The failure issue 40 reports: an ASCII upload parsed for longer than the timeout, the
    error query times out, and the next query read that late reply ('+0,"No error"' for
    'OUTP1?'). The link opens a fresh session after a timeout: the next query gets its own reply."""
    bench = EmulatedBench(beam_parameters())
    emulator = GeneratorEmulator(bench, "33500B", channel=1)
    emulator.ascii_parse_s_per_byte = 1.5 / 70_000  # 1.5 s for this upload
    server = InstrumentServer(emulator)
    link = VisaLink("fgen", server.resource, timeout_s=0.5)
    try:
        link.write("SOUR1:DATA:ARB SLOW," + ",".join(["0.123456"] * 7_500))
        with pytest.raises(DeviceTimeoutError, match=r"fgen .*no reply to 'SYST:ERR\?' within 0.5 s"):
            link.query("SYST:ERR?")
        import time
        time.sleep(1.5)  # the late reply is on its way meanwhile
        assert link.query("OUTP1?") == "0"
        assert link.stale_replies == 1
    finally:
        link.close()
        server.close()
