"""Issue 26 item 3: arbitrary waveforms on the three generator families the project ships
profiles for, through our driver and PyVISA to emulators written from each programming guide:

* Keysight 33500B: ``SOURce:DATA:ARBitrary <name>,<floats>`` (ASCII);
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
from setmem_hil.errors import DeviceRejectedError
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.instrument_bench import EmulatedBench
from setmem_hil.sim_backends.instrument_emulators import GeneratorEmulator, InstrumentServer, SiglentGeneratorEmulator

GENERATORS = {  # profile: (emulator class, emulator model, half a DAC step in points)
    "keysight-33500b": (GeneratorEmulator, "33500B", 0.5e-6),
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
