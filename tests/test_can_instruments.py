"""Issue 13, CAN: a DBC-described drive and a CANopen identity, on python-can's virtual bus.

The device side is written in the test with cantools and canopen only: it decodes our command
frames from their raw bytes with ``cantools`` (independently of how the driver encoded them) and
answers status and identity frames that cantools encodes; a ``canopen.LocalNode`` answers the
SDO reads of object 0x1018.
"""

from __future__ import annotations

import threading
import time
import uuid

import pytest

can = pytest.importorskip("can")
cantools = pytest.importorskip("cantools")
canopen = pytest.importorskip("canopen")

from setmem_hil.drivers.instruments.canopen_identity import check_canopen_identity  # noqa: E402
from setmem_hil.drivers.instruments.dbc_generator import DbcGenerator, parse_can_resource  # noqa: E402
from setmem_hil.drivers.instruments.profile import CanopenIdentity, load_profile  # noqa: E402
from setmem_hil.errors import DeviceIdentityError, DeviceTimeoutError, ProcedureError  # noqa: E402

PROFILE = load_profile("dbc-shaker-example")


class DbcDevice:
    """A CAN shaker drive: applies decoded commands, answers status and identity frames."""

    def __init__(self, channel: str, device_type: int = 0x1234, misreport: float | None = None):
        self.db = cantools.database.load_file(PROFILE.dbc_path)
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.device_type, self.misreport = device_type, misreport
        self.commands: list[dict] = []  # decoded by cantools from the raw frames
        self.times: list[float] = []
        self.state = {"Frequency": 0.0, "Amplitude": 0.0, "Enable": 0}
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _send(self, name: str, data: dict) -> None:
        m = self.db.get_message_by_name(name)
        self.bus.send(can.Message(arbitration_id=m.frame_id, data=m.encode(data), is_extended_id=False))

    def _run(self) -> None:
        cmd = self.db.get_message_by_name("ShakerCommand").frame_id
        req = self.db.get_message_by_name("ShakerIdentRequest").frame_id
        while not self._stop:
            frame = self.bus.recv(timeout=0.02)
            if frame is None:
                continue
            if frame.arbitration_id == cmd:
                decoded = self.db.decode_message(cmd, bytes(frame.data))
                self.commands.append(decoded)
                self.times.append(time.monotonic())
                self.state = dict(decoded)
                status = dict(self.state)
                if self.misreport is not None:
                    status["Frequency"] = self.misreport
                self._send("ShakerStatus", status)
            elif frame.arbitration_id == req:
                self._send("ShakerIdent", {"DeviceType": self.device_type, "Firmware": 7})

    def close(self) -> None:
        self._stop = True
        self._thread.join(2)
        self.bus.shutdown()


@pytest.fixture
def channel():
    return f"setmem-test-{uuid.uuid4().hex[:8]}"


def test_commands_reach_the_device_as_cantools_decodes_them(channel):
    device = DbcDevice(channel)
    gen = DbcGenerator("drive", PROFILE, f"can://virtual/{channel}")
    try:
        assert "4660" in gen.check_identity()
        gen.initialise()
        gen.set_frequency_hz(123.456)
        gen.set_amplitude_v(1.25)
        gen.set_output(True)
        assert device.state == {"Frequency": pytest.approx(123.456), "Amplitude": pytest.approx(1.25), "Enable": 1}
        n_before = len(device.commands)
        time.sleep(5 * PROFILE.period_s)
        assert len(device.commands) >= n_before + 3  # the cyclic command (dead-man) keeps coming
        gen.set_output(False)
        assert device.state["Enable"] == 0, device.commands[-6:]
        n_off = len(device.commands)
        time.sleep(4 * PROFILE.period_s)
        assert len(device.commands) == n_off  # the cyclic task stopped after output off
    finally:
        gen.close()
        device.close()


def test_identity_mismatch_before_any_enable(channel):
    device = DbcDevice(channel, device_type=0x9999)
    gen = DbcGenerator("drive", PROFILE, f"can://virtual/{channel}")
    try:
        with pytest.raises(DeviceIdentityError, match=r"drive .*expected a Example CAN shaker drive .*it answered 39321"):
            gen.check_identity()
        assert not any(c["Enable"] for c in device.commands)
    finally:
        gen.close()
        device.close()


def test_read_back_mismatch_is_refused(channel):
    device = DbcDevice(channel, misreport=1.0)
    gen = DbcGenerator("drive", PROFILE, f"can://virtual/{channel}")
    try:
        with pytest.raises(Exception, match="frequency_hz set to 50, the device reports 1"):
            gen.set_frequency_hz(50.0)
    finally:
        gen.close()
        device.close()


def test_silent_device_times_out_with_a_clear_message(channel):
    gen = DbcGenerator("drive", PROFILE, f"can://virtual/{channel}")
    try:
        with pytest.raises(DeviceIdentityError, match="no ShakerIdent frame within"):
            gen.check_identity()
    finally:
        gen.close()


def _local_node(channel: str, node_id: int, vendor: int, product: int):
    od = canopen.ObjectDictionary()
    record = canopen.objectdictionary.ODRecord("Identity object", 0x1018)
    for sub, name, value in ((1, "Vendor-ID", vendor), (2, "Product code", product)):
        var = canopen.objectdictionary.ODVariable(name, 0x1018, sub)
        var.data_type = canopen.objectdictionary.UNSIGNED32
        var.default = value
        record.add_member(var)
    od.add_object(record)
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    network.create_node(node_id, od)
    return network


def test_canopen_identity_read_from_object_1018(channel):
    network = _local_node(channel, 5, 0x000000A1, 0x00C0FFEE)
    try:
        answer = check_canopen_identity({"interface": "virtual", "channel": channel}, CanopenIdentity(5, 0xA1, 0xC0FFEE), "drive")
        assert "vendor 0x000000A1 product 0x00C0FFEE" in answer
        with pytest.raises(DeviceIdentityError, match="expected vendor 0x000000A1 product 0x00000001, it answered vendor 0x000000A1 product 0x00C0FFEE"):
            check_canopen_identity({"interface": "virtual", "channel": channel}, CanopenIdentity(5, 0xA1, 0x1), "drive")
        with pytest.raises(DeviceTimeoutError, match="node 9 does not answer"):
            check_canopen_identity({"interface": "virtual", "channel": channel}, CanopenIdentity(9, 0xA1, 0x1), "drive", timeout_s=0.1)
    finally:
        network.disconnect()


def test_dbc_profile_names_missing_messages_and_signals(tmp_path):
    text = open(PROFILE.source).read().replace('dbc = "dbc-shaker-example.dbc"', f'dbc = "{PROFILE.dbc_path}"')
    from setmem_hil.drivers.instruments.profile import parse_profile

    with pytest.raises(ProcedureError, match="no message 'ShakerCommnd'.*did you mean 'ShakerCommand'"):
        parse_profile(text.replace('message = "ShakerCommand"', 'message = "ShakerCommnd"'), str(tmp_path / "p.toml"))
    with pytest.raises(ProcedureError, match="no signal 'Freq' in message 'ShakerStatus'"):
        parse_profile(text.replace('[status]\nmessage = "ShakerStatus"\nfrequency_hz = "Frequency"',
                                   '[status]\nmessage = "ShakerStatus"\nfrequency_hz = "Freq"'), str(tmp_path / "p.toml"))


@pytest.mark.parametrize("resource, problem", [("socketcan/can0", "a CAN resource is can://"), ("can://socketcan", "expected can://<interface>/<channel>"),
                                                ("can://pcan/PCAN_USBBUS1?bitrate=fast", "bitrate must be an integer")])
def test_can_resource_errors(resource, problem):
    with pytest.raises(ValueError, match=problem):
        parse_can_resource(resource)
    assert parse_can_resource("can://pcan/PCAN_USBBUS1?bitrate=500000") == {"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 500000}
