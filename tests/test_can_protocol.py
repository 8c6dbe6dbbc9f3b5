"""CAN frame codec: byte-exact frames, CRC catalogue value, typed errors on malformed frames, fuzzing."""

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from setmem_hil.drivers import can_protocol as cp
from setmem_hil.errors import DeviceError, FrameError

NODE = 0x21


def test_crc8_matches_the_catalogue_check_value():
    # CRC-8/SMBUS: poly 0x07, init 0, check("123456789") = 0xF4 (reveng catalogue).
    assert cp.crc8(b"123456789") == 0xF4
    assert cp.crc8(b"") == 0


def test_set_frequency_command_is_byte_exact():
    # omega = 6.2832 rad/s -> 628320 counts of 1e-5 rad/s, little-endian u32.
    counts = cp.scale_unsigned(6.2832, cp.OMEGA_LSB_RAD_S, "omega")
    assert counts == 628320
    arb, data = cp.encode_command(NODE, cp.Command(cp.Opcode.SET_FREQUENCY, 7, counts, 0))
    assert arb == 0x221
    body = bytes([0x01, 0x07]) + (628320).to_bytes(4, "little") + bytes([0])
    assert data[:7] == body
    assert data[7] == cp.crc8(bytes([0x02, 0x21]) + body)
    assert cp.decode_frame(NODE, arb, data) == cp.Command(cp.Opcode.SET_FREQUENCY, 7, 628320, 0)


def test_sample_frame_is_byte_exact_and_counts_are_scaled_by_the_range():
    counts = cp.sample_to_counts(-0.25, 1.0)
    assert counts == round(-0.25 * (2**31 - 1))
    arb, data = cp.encode_sample(NODE, cp.SampleFrame("response", 3, 513, counts))
    assert arb == 0x3A1
    assert data[:7] == bytes([3]) + (513).to_bytes(2, "little") + struct.pack("<i", counts)
    frame = cp.decode_frame(NODE, arb, data)
    assert frame == cp.SampleFrame("response", 3, 513, counts)
    assert cp.counts_to_sample(frame.counts, 1.0) == pytest.approx(-0.25, abs=1e-9)
    # saturation at full scale instead of wrapping
    assert cp.sample_to_counts(5.0, 1.0) == 2**31 - 1
    assert cp.sample_to_counts(-5.0, 1.0) == -(2**31 - 1)


def test_reply_heartbeat_and_host_heartbeat_round_trip():
    reply = cp.Reply(cp.Opcode.START_ACQUISITION, 9, cp.ReplyStatus.OK, 123456)
    assert cp.decode_frame(NODE, *cp.encode_reply(NODE, reply)) == reply
    hb = cp.Heartbeat(1, 2, 250, 2**32 - 1)
    assert cp.decode_frame(NODE, *cp.encode_heartbeat(NODE, hb)) == hb
    assert cp.decode_frame(NODE, *cp.encode_host_heartbeat(5)) == cp.HostHeartbeat(5)


def test_frames_of_other_nodes_and_extended_ids_are_ignored_not_errors():
    arb, data = cp.encode_reply(NODE + 1, cp.Reply(cp.Opcode.STOP, 1, cp.ReplyStatus.OK, 0))
    assert cp.decode_frame(NODE, arb, data) is None
    assert cp.decode_frame(NODE, 0x221, b"\x00" * 8, is_extended_id=True) is None


def test_error_frame_decodes_with_bus_off_flag():
    frame = cp.decode_frame(NODE, cp.CAN_ERR_BUSOFF, b"\x00" * 8, is_error_frame=True)
    assert isinstance(frame, cp.ErrorFrame) and frame.bus_off
    assert not cp.ErrorFrame(cp.CAN_ERR_CRTL).bus_off


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d[:5], "expected 8 data bytes, found 5"),
        (lambda d: d[:7] + bytes([d[7] ^ 0x01]), "CRC-8 mismatch"),
        (lambda d: bytes([d[0] ^ 0x10]) + d[1:], "CRC-8 mismatch"),
        (lambda d: d + b"\x00", "expected 8 data bytes, found 9"),
    ],
)
def test_malformed_reply_frames_raise_frame_error_naming_the_problem(mutate, message):
    arb, data = cp.encode_reply(NODE, cp.Reply(cp.Opcode.ENABLE, 1, cp.ReplyStatus.OK, 1))
    with pytest.raises(FrameError, match=message) as info:
        cp.decode_frame(NODE, arb, mutate(data))
    assert "0x2A1" in str(info.value)
    assert isinstance(info.value, DeviceError) and isinstance(info.value, ValueError)


def test_unknown_opcode_and_status_with_a_valid_crc_are_frame_errors():
    arb = cp.REPLY_BASE + NODE
    body = bytes([0x5A, 0, 0, 0, 0, 0, 0])
    with pytest.raises(FrameError, match="unknown opcode 0x5A"):
        cp.decode_frame(NODE, arb, cp._seal(arb, body))
    body = bytes([0x01, 0, 0x77, 0, 0, 0, 0])
    with pytest.raises(FrameError, match="unknown status 119"):
        cp.decode_frame(NODE, arb, cp._seal(arb, body))
    with pytest.raises(FrameError, match="remote request"):
        cp.decode_frame(NODE, arb, b"", is_remote_frame=True)


def test_encoders_reject_values_that_do_not_fit():
    with pytest.raises(ValueError, match="arg"):
        cp.encode_command(NODE, cp.Command(cp.Opcode.SET_AMPLITUDE, 0, 2**32, 0))
    with pytest.raises(ValueError, match="node id"):
        cp.encode_command(0, cp.Command(cp.Opcode.STOP, 0))
    with pytest.raises(ValueError, match="exceeds the wire range"):
        cp.scale_unsigned(1e6, cp.OMEGA_LSB_RAD_S, "omega")
    with pytest.raises(ValueError, match="finite value"):
        cp.scale_unsigned(float("nan"), 1.0, "amplitude")


@settings(max_examples=400, deadline=None)
@given(
    arb=st.sampled_from([0x221, 0x2A1, 0x321, 0x3A1, 0x421, 0x4A1, 0x721, 0x77F]) | st.integers(0, 0x7FF),
    data=st.binary(min_size=0, max_size=12),
    error=st.booleans(),
    remote=st.booleans(),
)
def test_fuzzed_frames_decode_or_raise_frame_error_only(arb, data, error, remote):
    try:
        cp.decode_frame(NODE, arb, data, is_error_frame=error, is_remote_frame=remote)
    except FrameError:
        pass


@settings(max_examples=300, deadline=None)
@given(
    acq=st.integers(0, 255),
    index=st.integers(0, 0xFFFF),
    counts=st.integers(-(2**31 - 1), 2**31 - 1),
    flip_byte=st.integers(0, 7),
    flip_bit=st.integers(0, 7),
)
def test_every_single_bit_flip_of_a_sample_frame_is_detected(acq, index, counts, flip_byte, flip_bit):
    arb, data = cp.encode_sample(NODE, cp.SampleFrame("force", acq, index, counts))
    assert cp.decode_frame(NODE, arb, data) == cp.SampleFrame("force", acq, index, counts)
    corrupted = bytearray(data)
    corrupted[flip_byte] ^= 1 << flip_bit
    # a CRC-8 with polynomial 0x07 detects every single-bit error
    with pytest.raises(FrameError):
        cp.decode_frame(NODE, arb, bytes(corrupted))


def test_invalid_and_out_of_range_samples_keep_their_meaning_on_the_wire():
    assert cp.sample_to_counts(float("nan"), 10.0) == cp.INVALID_SAMPLE
    assert cp.counts_to_sample(cp.INVALID_SAMPLE, 10.0) != cp.counts_to_sample(cp.INVALID_SAMPLE, 10.0)  # NaN
    assert cp.counts_to_sample(cp.sample_to_counts(float("inf"), 10.0), 10.0) == 10.0  # clipped at full scale
    assert cp.counts_to_sample(cp.sample_to_counts(-12.0, 10.0), 10.0) == -10.0
    arb, data = cp.encode_sample(NODE, cp.SampleFrame("time", 1, 2, cp.time_offset_to_counts(-1.2345e-6)))
    assert arb == 0x421
    assert cp.decode_frame(NODE, arb, data).counts == -1234 or cp.decode_frame(NODE, arb, data).counts == -1235
    assert cp.time_offset_to_counts(10.0) == 2**31 - 1  # saturates: a jump is still a jump


def test_block_header_and_float_sample_rate():
    start = cp.block_start_to_counts(3723.000000001)
    assert start == 3_723_000_000_001
    arb, data = cp.encode_header(NODE, cp.BlockHeader(9, start))
    assert arb == 0x4A1 and data[1:7] == start.to_bytes(6, "little")
    assert cp.decode_frame(NODE, arb, data) == cp.BlockHeader(9, start)
    # binary32 bits of 10.5 are 0x41280000 (exact in binary)
    assert cp.float_to_u32(10.5) == 0x41280000
    assert cp.u32_to_float(0x41280000) == 10.5
    rate = 32 * 2.0 / (2 * 3.141592653589793)
    assert abs(cp.wire_sample_rate(rate) / rate - 1) < 2**-24
