"""Issue 13: the shipped profiles and drivers against independent implementations of the protocols.

* PyMeasure's drivers (``Agilent33500``, ``DG800``, ``SR830``, ``SR860``) run against a recording
  adapter; for the same operations our profiles must send the same command (canonical SCPI
  header, or the SRS mnemonic) with the same value.
* pyvisa-sim: a 33500B defined in YAML (dialogues, properties with limits, an error queue) driven
  by our generator driver through PyVISA.
* pymodbus: a plain pymodbus server (no code of ours) with hand-encoded registers in both word
  orders, driven by our Modbus driver; the words it stores are checked against IEEE 754 by hand.
"""

from __future__ import annotations

import asyncio
import math
import re
import threading
from pathlib import Path

import pytest

from setmem_hil.drivers.instruments.lockin import LockIn
from setmem_hil.drivers.instruments.modbus_generator import ModbusGenerator
from setmem_hil.drivers.instruments.profile import load_profile, parse_profile
from setmem_hil.drivers.instruments.scpi_commands import canonical_header
from setmem_hil.drivers.instruments.scpi_generator import ScpiGenerator
from setmem_hil.drivers.instruments.visa_link import VisaLink
from setmem_hil.errors import DeviceIdentityError, DeviceRejectedError

pymeasure_adapters = pytest.importorskip("pymeasure.adapters")
FIXTURES = Path(__file__).with_name("fixtures")


# -- PyMeasure transcripts ------------------------------------------------------------------------
class Recorder(pymeasure_adapters.Adapter):
    """A PyMeasure adapter that records what the driver writes (no instrument)."""

    def __init__(self):
        super().__init__()
        self.sent: list[str] = []

    def _write(self, command, **kwargs):
        self.sent.append(command)

    def _read(self, **kwargs):  # pragma: no cover - the operations compared only write
        return "0"


def pymeasure_commands(cls, operation) -> list[str]:
    adapter = Recorder()
    inst = cls(adapter)
    adapter.sent.clear()
    operation(inst)
    return adapter.sent


class EchoLink:
    """Stands in for a VisaLink: records writes, answers read-backs with the last value set."""

    def __init__(self, identity: str, error_reply: str):
        self.resource, self.transcript, self.identity, self.error_reply = "ECHO", [], identity, error_reply
        self.values: dict[tuple, str] = {}

    def write(self, command: str) -> None:
        self.transcript.append(command)
        head, _, args = command.partition(" ")
        self.values[canonical_header(head)] = args

    def query(self, command: str) -> str:
        if command.startswith("*IDN"):
            return self.identity
        if command in ("SYST:ERR?", ":SYST:ERR?"):
            return self.error_reply
        if command == "*ESR?":
            return "0"
        value = self.values.get(canonical_header(command.partition(" ")[0]), "0")
        return {"ON": "1", "OFF": "0"}.get(value.upper(), value) if "OUTP" in command.upper() and "DG" not in self.identity else value

    def close(self) -> None:
        pass


SCPI_BOOLEANS = {"ON": 1.0, "OFF": 0.0}


def scpi_parts(command: str) -> tuple[tuple[str, ...], list[float | str]]:
    """Canonical header and values; SCPI booleans ON/OFF as 1/0 (SCPI-99 7.3 <Boolean>)."""
    head, _, args = command.strip().partition(" ")
    values = []
    for a in (x.strip() for x in args.split(",") if x.strip()):
        try:
            values.append(float(a))
        except ValueError:
            values.append(SCPI_BOOLEANS.get(a.upper(), a.upper()))
    return canonical_header(head), values


def srs_parts(command: str) -> tuple[str, list[float]]:
    """SRS syntax: letters (and '?') then optional space then comma-separated numbers."""
    m = re.fullmatch(r"\s*([A-Za-z*]+\??)\s*(.*?)\s*;?\s*", command)
    return m.group(1).upper(), [float(x) for x in m.group(2).split(",") if x.strip()]


def ours_generator(profile_name: str, identity: str, operation) -> list[str]:
    link = EchoLink(identity, '+0,"No error"' if "33500" in profile_name else '0,"No error"')
    gen = ScpiGenerator("gen", load_profile(profile_name), link, channel=1)
    link.transcript.clear()
    operation(gen)
    return [c for c in link.transcript if not c.endswith("?")]


KEYSIGHT_ID = "Keysight Technologies,33522B,MY1,5.02"
RIGOL_ID = "Rigol Technologies,DG812,DG8A1,00.01.14"


@pytest.mark.parametrize("value", [0.1, 12.5, 1234.5, 2.0e4])
def test_33500b_frequency_command_matches_pymeasure(value):
    from pymeasure.instruments.agilent.agilent33500 import Agilent33500

    theirs = pymeasure_commands(Agilent33500, lambda g: setattr(g.ch_1, "frequency", value))
    ours = ours_generator("keysight-33500b", KEYSIGHT_ID, lambda g: g.set_frequency_hz(value))
    assert [scpi_parts(c) for c in ours] == [scpi_parts(c) for c in theirs]


def test_33500b_amplitude_output_and_setup_match_pymeasure():
    from pymeasure.instruments.agilent.agilent33500 import Agilent33500

    def theirs(g):
        g.ch_1.amplitude_unit = "VPP"
        g.ch_1.amplitude = 0.5  # Vpp
        g.ch_1.output = True
        g.ch_1.output = False
        g.ch_1.shape = "SIN"
        g.ch_1.offset = 0
        g.ch_1.output_load = "INF"

    expected = [scpi_parts(c) for c in pymeasure_commands(Agilent33500, theirs)]
    ours = ours_generator("keysight-33500b", KEYSIGHT_ID, lambda g: (g.set_amplitude_v(0.25), g.set_output(True), g.set_output(False)))
    init = [c.format(ch=1, load="INF") for c in load_profile("keysight-33500b").init]
    ours_parts = [scpi_parts(c) for c in ours + init]
    for command in expected:
        assert command in ours_parts, f"PyMeasure sends {command}; our profile never does"


def test_dg800_commands_match_pymeasure():
    from pymeasure.instruments.rigol.rigol_dg800 import DG800

    def theirs(g):
        g.channel_1.frequency = 1234.5
        g.channel_1.output_enabled = True
        g.channel_1.output_enabled = False
        g.channel_1.high_impedance = True

    expected = [scpi_parts(c) for c in pymeasure_commands(DG800, theirs)]
    ours = ours_generator("rigol-dg800", RIGOL_ID, lambda g: (g.set_frequency_hz(1234.5), g.set_output(True), g.set_output(False)))
    init = [c.format(ch=1, load="INF") for c in load_profile("rigol-dg800").init]
    ours_parts = [scpi_parts(c) for c in ours + init]
    for command in expected:
        assert command in ours_parts, f"PyMeasure sends {command}; our profile never does"


def _lockin_commands(profile_name: str, operation) -> list[str]:
    link = EchoLink("Stanford_Research_Systems,SR830,1,1", "0")
    li = LockIn("lia", load_profile(profile_name), link)
    link.transcript.clear()
    operation(li)
    return [c for c in link.transcript if not c.endswith("?") or c.startswith("SNAP")]


@pytest.mark.parametrize("model", ["SR830", "SR860"])
def test_lockin_time_constants_match_pymeasure(model):
    """For every time constant the profile lists, the index we send is PyMeasure's."""
    from pymeasure.instruments.srs.sr830 import SR830
    from pymeasure.instruments.srs.sr860 import SR860

    cls, name = (SR830, "srs-sr830") if model == "SR830" else (SR860, "srs-sr860")
    profile = load_profile(name)
    assert list(profile.time_constants_s) == list(cls.TIME_CONSTANTS)
    for tau in profile.time_constants_s:
        theirs = pymeasure_commands(cls, lambda li: setattr(li, "time_constant", tau))
        ours = _lockin_commands(name, lambda li: li.set_time_constant(tau))
        assert [srs_parts(c) for c in ours] == [srs_parts(c) for c in theirs], tau


def test_sr830_reference_and_setup_match_pymeasure():
    from pymeasure.instruments.srs.sr830 import SR830

    def theirs(li):
        li.reference_source = "External"
        li.filter_slope = 24
        li.sensitivity = 1.0
        li.input_config = "A"
        li.input_coupling = "AC"
        li.reference_source_trigger = "SINE"
        li.reserve = "Normal"

    expected = [srs_parts(c) for c in pymeasure_commands(SR830, theirs)]
    profile = load_profile("srs-sr830")
    ours = [srs_parts(c) for c in (*profile.init, profile.reference.set)]
    for command in expected:
        assert command in ours, f"PyMeasure sends {command}; our SR830 profile never does"
    assert srs_parts(profile.read_xy) == srs_parts("SNAP? 1,2")  # PyMeasure's snap("X", "Y"): indices 1, 2
    assert pymeasure_snap(SR830) == [srs_parts(profile.read_xy)]


def pymeasure_snap(cls):
    adapter = Recorder()
    inst = cls(adapter)
    adapter.sent.clear()
    adapter._read = lambda **kw: "1.0,2.0"
    inst.snap()
    return [srs_parts(c) for c in adapter.sent]


def test_sr860_reference_and_setup_match_pymeasure():
    from pymeasure.instruments.srs.sr860 import SR860

    def theirs(li):
        li.reference_source = "EXT"
        li.filter_slope = 3
        li.sensitivity = 1
        li.input_signal = "VOLT"
        li.input_voltage_mode = "A"
        li.input_coupling = "AC"
        li.reference_triggermode = "SIN"

    expected = [srs_parts(c) for c in pymeasure_commands(SR860, theirs)]
    profile = load_profile("srs-sr860")
    ours = [srs_parts(c) for c in (*profile.init, profile.reference.set)]
    for command in expected:
        assert command in ours, f"PyMeasure sends {command}; our SR860 profile never does"
    # PyMeasure's snap() asks "SNAP? X, Y"; the SR860 manual's SNAP? table: X is 0, Y is 1
    assert srs_parts(profile.read_xy) == ("SNAP?", [0.0, 1.0])
    adapter = Recorder()
    inst = SR860(adapter)
    adapter.sent.clear()
    adapter._read = lambda **kw: "1.0,2.0"
    inst.snap()
    assert [c.replace(" ", "") for c in adapter.sent] == ["SNAP?X,Y"]


# -- pyvisa-sim -----------------------------------------------------------------------------------
SIM_YAML = FIXTURES / "keysight_33500b_sim.yaml"
SIM_RESOURCE = "TCPIP::192.168.0.20::5025::SOCKET"


def _sim_generator():
    pytest.importorskip("pyvisa_sim")
    profile = load_profile("keysight-33500b")
    link = VisaLink("fgen", SIM_RESOURCE, visa_library=f"{SIM_YAML}@sim", termination=profile.termination)
    return ScpiGenerator("fgen", profile, link, channel=1)


def test_pyvisa_sim_33500b_identity_init_and_settings():
    gen = _sim_generator()
    try:
        assert gen.check_identity().startswith("Keysight Technologies,33522B")
        gen.initialise()
        gen.set_frequency_hz(1234.5)
        assert float(gen.link.query("SOUR1:FREQ?")) == 1234.5
        gen.set_amplitude_v(0.25)  # peak: 0.5 Vpp on the instrument
        assert float(gen.link.query("SOUR1:VOLT?")) == 0.5
    finally:
        gen.close()


def test_pyvisa_sim_errors_reach_the_driver():
    gen = _sim_generator()
    try:
        gen.link.write("SOUR1:BOGUS 1")
        with pytest.raises(DeviceRejectedError, match="Undefined header"):
            gen.check_errors("SOUR1:BOGUS 1")
        # the simulated instrument accepts at most 1 MHz (a cheaper model): the read-back catches it
        with pytest.raises(DeviceRejectedError, match="reads back"):
            gen.set_frequency_hz(5e6)
    finally:
        gen.close()


def test_pyvisa_sim_wrong_identity_is_refused():
    pytest.importorskip("pyvisa_sim")
    link = VisaLink("fgen", SIM_RESOURCE, visa_library=f"{SIM_YAML}@sim")
    gen = ScpiGenerator("fgen", load_profile("rigol-dg800"), link)
    try:
        with pytest.raises(DeviceIdentityError, match="expected a Rigol DG800 .* it answered 'Keysight Technologies,33522B"):
            gen.check_identity()
    finally:
        gen.close()


# -- pymodbus: hand-encoded registers in both word orders ---------------------------------------------
# 1234.5 = 1.00110100101b x 2^10: sign 0, exponent 137 (0x89), mantissa 0011010010100...: 0x449A5000
HAND_1234_5 = (0x449A, 0x5000)
# 2.5 = 1.01b x 2^1: exponent 128: 0x40200000
HAND_2_5 = (0x4020, 0x0000)


def _profile_text(word_order: str) -> str:
    return f'''
kind = "modbus"
model = "hand-encoded test controller"
device_id = 3
identity = {{ table = "holding", address = 0, type = "uint32", word_order = "{word_order}", expect = 305419896 }}
frequency_hz = {{ table = "holding", address = 10, type = "float32", word_order = "{word_order}" }}
amplitude_v = {{ table = "holding", address = 12, type = "int16", scale = 0.001 }}
output = {{ table = "coil", address = 5 }}
[limits]
frequency_hz = [0.1, 5000.0]
amplitude_v = [0.0, 10.0]
'''


class PlainModbusServer:
    """A pymodbus server with preset registers and nothing of ours behind it."""

    def __init__(self, holding: dict[int, int], device_id: int, framer: str = "socket"):
        from pymodbus.framer import FramerType
        from pymodbus.server import ModbusTcpServer
        from pymodbus.simulator import SimData, SimDevice
        from pymodbus.simulator.simdata import DataType

        from setmem_hil.sim_backends.instrument_emulators import free_port

        self.port = free_port()
        self.framer = FramerType.RTU if framer == "rtu" else FramerType.SOCKET
        regs = [0] * 64
        for a, v in holding.items():
            regs[a] = v
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()

        async def serve():
            device = SimDevice(device_id, simdata=(
                [SimData(0, count=64, values=False, datatype=DataType.BITS)], [SimData(0, count=64, values=False, datatype=DataType.BITS)],
                [SimData(0, values=regs, datatype=DataType.REGISTERS)], [SimData(0, count=64, values=0, datatype=DataType.REGISTERS)]))
            self.server = ModbusTcpServer(device, address=("127.0.0.1", self.port),
                                          framer=FramerType.RTU if framer == "rtu" else FramerType.SOCKET)
            await self.server.serve_forever(background=True)

        def run():
            asyncio.set_event_loop(self.loop)
            self.loop.run_until_complete(serve())
            ready.set()
            self.loop.run_forever()

        threading.Thread(target=run, daemon=True).start()
        assert ready.wait(10)

    def read_holding(self, address: int, count: int) -> list[int]:
        from pymodbus.client import ModbusTcpClient

        client = ModbusTcpClient("127.0.0.1", port=self.port, framer=self.framer)
        client.connect()
        try:
            return list(client.read_holding_registers(address, count=count, device_id=3).registers)
        finally:
            client.close()

    def close(self):
        asyncio.run_coroutine_threadsafe(self.server.shutdown(), self.loop).result(5)
        self.loop.call_soon_threadsafe(self.loop.stop)


@pytest.mark.parametrize("word_order, framer", [("big", "socket"), ("little", "socket"), ("little", "rtu")])
def test_modbus_registers_against_a_plain_pymodbus_server(word_order, framer, tmp_path):
    """Modbus TCP, and RTU framing (through pyserial's socket:// port, as a serial line would carry it)."""
    ident = (0x1234, 0x5678) if word_order == "big" else (0x5678, 0x1234)  # 305419896 = 0x12345678
    server = PlainModbusServer({0: ident[0], 1: ident[1]}, device_id=3, framer=framer)
    resource = (f"tcp://127.0.0.1:{server.port}" if framer == "socket"
                else f"rtu://socket://127.0.0.1:{server.port}?baudrate=19200&parity=E")
    try:
        profile = parse_profile(_profile_text(word_order), str(tmp_path / "hand.toml"))
        gen = ModbusGenerator("plc", profile, resource)
        try:
            assert "305419896" in gen.check_identity()
            gen.set_frequency_hz(1234.5)
            gen.set_amplitude_v(2.5)
            gen.set_output(True)
            words = server.read_holding(10, 3)
        finally:
            gen.close()
        expected = HAND_1234_5 if word_order == "big" else HAND_1234_5[::-1]
        assert tuple(words[:2]) == expected
        assert words[2] == 2500  # int16 with scale 0.001: 2.5 V
    finally:
        server.close()


def test_modbus_identity_mismatch_names_the_value(tmp_path):
    server = PlainModbusServer({0: 0, 1: 7}, device_id=3)
    try:
        profile = parse_profile(_profile_text("big"), str(tmp_path / "hand.toml"))
        gen = ModbusGenerator("plc", profile, f"tcp://127.0.0.1:{server.port}")
        try:
            with pytest.raises(DeviceIdentityError, match=r"plc .*expected .*305419896.* it answered 7"):
                gen.check_identity()
        finally:
            gen.close()
    finally:
        server.close()


def test_hand_encodings_are_ieee754():
    import struct

    assert struct.unpack(">f", bytes.fromhex("449A5000"))[0] == 1234.5
    assert struct.unpack(">f", bytes.fromhex("40200000"))[0] == 2.5
    assert math.isclose(HAND_2_5[0] * 65536 + HAND_2_5[1], 0x40200000)


# -- PyMeasure's own expected_protocol, fed with the commands our profiles send -------------------------
def test_expected_protocol_sr830_accepts_our_time_constant_slope_and_sensitivity_commands():
    """``expected_protocol`` fails unless PyMeasure's SR830 driver sends exactly these messages;
    they are our profile's commands (the SR830 ignores the space between header and value,
    PyMeasure writes none)."""
    from pymeasure.test import expected_protocol
    from pymeasure.instruments.srs.sr830 import SR830

    profile = load_profile("srs-sr830")
    for index, tau in enumerate(profile.time_constants_s):
        ours = profile.time_constant.set.format(index=index).replace(" ", "")
        with expected_protocol(SR830, [(ours, None)]) as inst:
            inst.time_constant = tau
    slope = next(c for c in profile.init if c.startswith("OFSL")).replace(" ", "")
    sens = next(c for c in profile.init if c.startswith("SENS")).replace(" ", "")
    with expected_protocol(SR830, [(slope, None), (sens, None)]) as inst:
        inst.filter_slope = 24
        inst.sensitivity = profile.full_scale_v


def test_expected_protocol_33500b_accepts_our_frequency_and_output_commands():
    """Our 33500B commands, with the value written in PyMeasure's format (``%f``, booleans as
    1/0), are exactly what PyMeasure's driver sends for the same settings."""
    from pymeasure.test import expected_protocol
    from pymeasure.instruments.agilent.agilent33500 import Agilent33500

    sent = ours_generator("keysight-33500b", KEYSIGHT_ID, lambda g: (g.set_frequency_hz(1234.5), g.set_output(True)))
    (freq_head, freq_value), (out_head, out_value) = (scpi_parts(c) for c in sent)
    pairs = [(f"{':'.join(freq_head)} {freq_value[0]:f}", None), (f"{':'.join(out_head)} {int(out_value[0])}", None)]
    with expected_protocol(Agilent33500, pairs) as gen:
        gen.ch_1.frequency = 1234.5
        gen.ch_1.output = True
