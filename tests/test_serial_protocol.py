"""Serial line protocol: byte-exact frames, malformed input gives typed errors, fuzzing."""

import binascii

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from setmem_hil.drivers import serial_protocol as sp
from setmem_hil.errors import DeviceError, FrameError


def _crc_bitwise(data: bytes) -> int:
    # independent CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, MSB first
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def test_crc_matches_the_standard_check_value_and_a_bitwise_implementation():
    assert sp.crc16(b"123456789") == 0x29B1  # CRC-16/CCITT-FALSE check value
    for data in (b"", b"0a SINE 1.5 0.5", bytes(range(256))):
        assert sp.crc16(data) == _crc_bitwise(data)


def test_request_frames_are_byte_exact():
    payload = b"0a SINE 1.5 0.25"
    expected = b"@" + payload + b"*" + f"{_crc_bitwise(payload):04X}".encode() + b"\n"
    assert sp.encode_request(10, "SINE", 1.5, 0.25) == expected
    assert sp.encode_request(255, "READ", 64, 32).startswith(b"@ff READ 64 32*")
    assert sp.decode_request(expected) == sp.Request(10, "SINE", (1.5, 0.25))


def test_responses_round_trip_including_errors_and_nonfinite_samples():
    line = sp.encode_response(7, 0, 1, 0.5, float("nan"), float("inf"))
    resp = sp.decode_response(line)
    assert resp.ok and resp.seq == 7 and resp.values == ("0", "1", "0.5", "nan", "inf")
    t, f, y = sp.parse_samples(resp.values, 0, 1, "test")
    assert t == [0.5] and f[0] != f[0] and y == [float("inf")]
    err = sp.decode_response(sp.encode_error(3, "range", "amplitude 12 N outside [0, 10]"))
    assert not err.ok and err.code == "range" and "amplitude 12 N" in err.message
    with pytest.raises(sp.DeviceRejectedError, match=r"\(range\): amplitude") as info:
        sp.raise_for_error(err)
    assert isinstance(info.value, DeviceError)


@pytest.mark.parametrize(
    "line, error, match",
    [
        (b"@0a STOP*1234", sp.TruncatedFrameError, "terminator"),
        (b"0a STOP*1234\n", sp.TruncatedFrameError, "start character"),
        (b"@0a STOP\n", sp.TruncatedFrameError, "checksum"),
        (b"@0a STOP*12\n", sp.TruncatedFrameError, "checksum"),
        (b"@0a STOP*ZZZZ\n", sp.ChecksumError, "hex"),
        (b"@0a STOP*0000\n", sp.ChecksumError, "does not match"),
    ],
)
def test_broken_frames_raise_typed_errors(line, error, match):
    with pytest.raises(error, match=match):
        sp.decode_request(line)


def _signed(payload: bytes, start=b"@") -> bytes:
    return start + payload + b"*" + f"{sp.crc16(payload):04X}".encode() + b"\n"


@pytest.mark.parametrize(
    "payload, match",
    [
        (b"0a FLY 1", "unknown command"),
        (b"0a SINE 1.0", "expected 2 arguments"),
        (b"0a SINE nan 1.0", "finite"),
        (b"0a SINE abc 1.0", "expected a number"),
        (b"0a READ -1 3", "non-negative integer"),
        (b"0A STOP", "two lower-case hex"),
        (b"0a  STOP", "single spaces"),
        (b"0a", "expected '<seq> <field>"),
        (b"0a STOP \xff", "not ASCII"),
    ],
)
def test_wellformed_checksums_with_bad_content_are_malformed(payload, match):
    with pytest.raises(sp.MalformedFrameError, match=match):
        sp.decode_request(_signed(payload))


def test_response_status_and_sample_answers_are_checked():
    with pytest.raises(sp.MalformedFrameError, match="neither OK nor ERR"):
        sp.decode_response(_signed(b"01 MAYBE", b"!"))
    with pytest.raises(sp.MalformedFrameError, match="requested"):
        sp.parse_samples(("0", "2", "1", "2", "3", "4", "5", "6"), 2, 2, "READ")
    with pytest.raises(sp.MalformedFrameError, match="expected 6 values"):
        sp.parse_samples(("0", "2", "1", "2", "3"), 0, 2, "READ")
    with pytest.raises(ValueError, match="unknown|expected one of"):
        sp.encode_request(1, "FLY")


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_arbitrary_bytes_only_raise_frame_errors(data):
    for decode in (sp.decode_request, sp.decode_response):
        try:
            decode(data)
        except FrameError:
            pass


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(sorted(sp.COMMANDS)),
    st.integers(0, 255),
    st.lists(st.text(alphabet="0123456789.-einfa", min_size=1, max_size=8), max_size=3),
    st.data(),
)
def test_fuzz_mutated_valid_frames_only_raise_frame_errors(command, seq, args, data):
    payload = (f"{seq:02x} " + " ".join([command] + args)).encode()
    frame = bytearray(_signed(payload))
    # mutate: flip, drop or insert bytes at random places
    for _ in range(data.draw(st.integers(0, 3))):
        op = data.draw(st.sampled_from(["flip", "drop", "insert", "cut"]))
        if not frame:
            break
        k = data.draw(st.integers(0, len(frame) - 1))
        if op == "flip":
            frame[k] ^= 1 << data.draw(st.integers(0, 7))
        elif op == "drop":
            del frame[k]
        elif op == "insert":
            frame.insert(k, data.draw(st.integers(0, 255)))
        else:
            del frame[k:]
    try:
        req = sp.decode_request(bytes(frame))
    except FrameError:
        return
    assert req.command in sp.COMMANDS


def test_checksum_detects_every_single_bit_flip_of_a_frame():
    frame = sp.encode_request(0x2C, "SINE", 6.2832, 0.75)
    body_end = frame.index(b"*")
    for k in range(1, body_end):
        for bit in range(8):
            bad = bytearray(frame)
            bad[k] ^= 1 << bit
            with pytest.raises(FrameError):
                sp.decode_request(bytes(bad))
    assert binascii.crc_hqx(b"", 0xFFFF) == 0xFFFF
