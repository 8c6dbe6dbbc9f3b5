"""Fuzzing the host side of the CAN link: whatever arrives on the bus, only typed errors escape."""

import can
from hypothesis import given, settings
from hypothesis import strategies as st

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.drivers.can_rig import CanLink, CanSettings
from setmem_hil.drivers.transport import RetryPolicy
from setmem_hil.errors import DeviceError

NODE = 0x21
IDS = [cp.REPLY_BASE + NODE, cp.FORCE_DATA_BASE + NODE, cp.RESPONSE_DATA_BASE + NODE, cp.TIME_DATA_BASE + NODE,
       cp.HEARTBEAT_BASE + NODE, cp.HEADER_BASE + NODE, cp.CAN_ERR_BUSOFF]


class ScriptedBus:
    """A bus that delivers a scripted list of messages, then silence; records what is sent."""

    def __init__(self, messages):
        self.messages = list(messages)
        self.sent = []

    def send(self, msg, timeout=None):
        self.sent.append(msg)

    def recv(self, timeout=None):
        return self.messages.pop(0) if self.messages else None

    def shutdown(self):
        pass


messages = st.lists(
    st.builds(
        lambda arb, data, err, ext: can.Message(arbitration_id=arb, data=data, is_error_frame=err, is_extended_id=ext),
        st.sampled_from(IDS) | st.integers(0, 0x7FF),
        st.binary(max_size=8),
        st.booleans(),
        st.booleans(),
    ),
    max_size=30,
)


@settings(max_examples=150, deadline=None)
@given(script=messages)
def test_random_traffic_gives_a_reply_or_a_typed_error(script):
    buses = []

    def factory():
        buses.append(ScriptedBus(script if not buses else []))
        return buses[-1]

    link = CanLink(factory, CanSettings(node=NODE, retry=RetryPolicy(0.001, 2, 0.0, 0.0), gap_timeout_s=0.001, max_resend_rounds=1))
    try:
        link.request(cp.Opcode.GET_INFO, 0, what="GET_INFO")
    except DeviceError:
        pass
    try:
        link.acquire_block(3)
    except DeviceError:
        pass
    link.close()


def test_bus_off_while_collecting_samples_reopens_the_bus_and_asks_again():
    arb, data = cp.encode_reply(NODE, cp.Reply(cp.Opcode.START_ACQUISITION, 1, cp.ReplyStatus.OK, 2))
    script = [
        can.Message(arbitration_id=arb, data=data, is_extended_id=False),
        can.Message(arbitration_id=cp.CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)),
    ]
    buses = []

    def factory():
        buses.append(ScriptedBus(script if not buses else []))
        return buses[-1]

    link = CanLink(factory, CanSettings(node=NODE, retry=RetryPolicy(0.001, 2, 0.0, 0.0), gap_timeout_s=0.001, max_resend_rounds=1))
    try:
        link.acquire_block(2)
    except DeviceError as exc:  # nobody answers the RESEND on the new bus
        assert "no valid reply to RESEND" in str(exc)
    assert link.stats.as_dict()["bus_off"] == 1 and len(buses) >= 2
    # the RESEND went out on the reopened bus
    assert any(m.arbitration_id == cp.COMMAND_BASE + NODE and m.data[0] == cp.Opcode.RESEND for m in buses[1].sent)


def test_a_valid_reply_among_garbage_is_found():
    arb, data = cp.encode_reply(NODE, cp.Reply(cp.Opcode.GET_INFO, 1, cp.ReplyStatus.OK, 42))
    script = [
        can.Message(arbitration_id=arb, data=b"\x01\x02", is_extended_id=False),  # truncated
        can.Message(arbitration_id=arb, data=data[:7] + bytes([data[7] ^ 0xFF]), is_extended_id=False),  # bad CRC
        can.Message(arbitration_id=cp.CAN_ERR_CRTL, is_error_frame=True, data=bytes(8)),
        can.Message(arbitration_id=arb, data=data, is_extended_id=False),
    ]
    link = CanLink(lambda: ScriptedBus(script), CanSettings(node=NODE, retry=RetryPolicy(0.01, 1, 0.0, 0.0)))
    assert link.request(cp.Opcode.GET_INFO, 0, what="GET_INFO").value == 42
    assert link.stats.as_dict() == {"crc_errors": 1, "error_frames": 1, "malformed_frames": 1}
