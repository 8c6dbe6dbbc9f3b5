"""Modbus register map and ADU codec: byte-exact (vs. the spec's example and pymodbus's framers),
typed errors on malformed frames, and hypothesis fuzzing of register decoding."""

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.framer import FramerRTU, FramerSocket
from pymodbus.pdu import DecodePDU

from setmem_hil.drivers import modbus_registers as mr
from setmem_hil.errors import DeviceError, FrameError


def test_crc16_matches_the_catalogue_check_value():
    # CRC-16/MODBUS: check("123456789") = 0x4B37 (reveng catalogue)
    assert mr.crc16_modbus(b"123456789") == 0x4B37


def test_rtu_read_request_matches_the_classic_example_and_pymodbus():
    pdu = mr.encode_read_request_pdu(0, 10)
    adu = mr.rtu_frame(1, pdu)
    assert adu == bytes.fromhex("01030000000AC5CD")  # the well-known example frame
    assert adu == FramerRTU(DecodePDU(False)).encode(pdu, 1, 0)  # an independent implementation
    assert mr.rtu_unframe(adu, 1) == pdu


def test_socket_framing_matches_pymodbus_and_checks_the_transaction_id():
    pdu = mr.encode_read_response_pdu([1, 0xBEEF])
    adu = mr.mbap_frame(0x1234, 1, pdu)
    assert adu == FramerSocket(DecodePDU(True)).encode(pdu, 1, 0x1234)
    assert mr.decode_read_response_pdu(mr.mbap_unframe(adu, 0x1234, 1), 2) == [1, 0xBEEF]
    with pytest.raises(FrameError, match="transaction id 4660 \\(expected 4661\\): stale or duplicated"):
        mr.mbap_unframe(adu, 0x1235, 1)


@pytest.mark.parametrize(
    "adu, message",
    [
        (b"\x01\x03", "too short"),
        (bytes.fromhex("01030000000AC5CE"), "CRC-16 mismatch"),
        (mr.rtu_frame(2, mr.encode_read_request_pdu(0, 1)), "unit 2 \\(expected 1\\)"),
    ],
)
def test_malformed_rtu_frames_raise_frame_error(adu, message):
    with pytest.raises(FrameError, match=message):
        mr.rtu_unframe(adu, 1)


def test_exception_response_is_a_typed_device_error_with_its_code():
    with pytest.raises(mr.ModbusExceptionError) as info:
        mr.decode_read_response_pdu(bytes([0x83, 0x06]), 4)
    assert info.value.code == 6 and info.value.retryable
    assert isinstance(info.value, DeviceError)
    assert not mr.ModbusExceptionError(3, 2).retryable
    with pytest.raises(FrameError, match="byte count 4"):
        mr.decode_read_response_pdu(bytes([3, 4, 0, 1, 0, 2]), 3)


def test_scalar_registers_are_big_endian_words():
    assert mr.u32_to_registers(0x12345678) == [0x1234, 0x5678]
    assert mr.registers_to_i32([0xFFFF, 0xFFFE]) == -2
    assert mr.float32_to_registers(10.5) == [0x4128, 0x0000]
    assert mr.registers_to_u64(mr.u64_to_registers(2**40 + 7)) == 2**40 + 7
    assert mr.scale_unsigned(6.2832, mr.OMEGA_LSB_RAD_S, "omega") == 628320
    with pytest.raises(ValueError, match="exceeds the register range"):
        mr.scale_unsigned(1e5, mr.OMEGA_LSB_RAD_S, "omega")
    with pytest.raises(FrameError, match="expected 2 registers, found 3"):
        mr.registers_to_u32([1, 2, 3])
    with pytest.raises(FrameError, match="not a 16-bit word"):
        mr.registers_to_u32([1, 70000])


def _control(**over):
    regs = [0] * mr.N_CONTROL_REGISTERS
    regs[mr.REG_MAGIC], regs[mr.REG_VERSION] = mr.MAGIC, mr.VERSION
    regs[mr.REG_SAMPLE_RATE : mr.REG_SAMPLE_RATE + 2] = mr.float32_to_registers(over.get("rate", 100.0))
    regs[mr.REG_FORCE_RANGE : mr.REG_FORCE_RANGE + 2] = mr.u32_to_registers(10_000_000)
    regs[mr.REG_ACQ_T0 : mr.REG_ACQ_T0 + 4] = mr.u64_to_registers(1_500_000_000)
    regs[mr.REG_STATUS] = over.get("status", mr.STATUS_OUTPUT_ON)
    return regs


def test_control_block_decodes_units_and_rejects_a_foreign_device():
    info = mr.decode_control_block(_control())
    assert info.sample_rate_hz == 100.0 and info.force_range_n == pytest.approx(10.0)
    assert info.acq_t0_s == pytest.approx(1.5) and info.output_on and not info.watchdog_tripped
    bad = _control()
    bad[mr.REG_MAGIC] = 0x1234
    with pytest.raises(FrameError, match="magic/version 0x1234/1"):
        mr.decode_control_block(bad)
    with pytest.raises(FrameError, match="not a finite rate"):
        mr.decode_control_block(_control(rate=float("nan")))


def test_page_round_trip_and_stale_or_corrupt_pages_are_rejected():
    rng = np.random.default_rng(0)
    dev = rng.integers(-(2**31), 2**31 - 1, 13)
    f = rng.integers(-(2**31), 2**31 - 1, 13)
    y = rng.integers(-(2**31), 2**31 - 1, 13)
    regs = mr.encode_page(7, 3, dev, f, y)
    assert len(regs) == mr.PAGE_REGISTERS == 124
    page = mr.decode_page(regs, 7, 3)
    np.testing.assert_array_equal(page.dev_counts, dev)
    np.testing.assert_array_equal(page.force_counts, f)
    np.testing.assert_array_equal(page.response_counts, y)
    with pytest.raises(FrameError, match="stale page \\(acquisition 7, page 3; expected 8, 3\\)"):
        mr.decode_page(regs, 8, 3)
    corrupted = list(regs)
    corrupted[50] ^= 0x0100
    with pytest.raises(FrameError, match="CRC-16 mismatch"):
        mr.decode_page(corrupted, 7, 3)
    with pytest.raises(FrameError, match="expected 124 registers, found 123"):
        mr.decode_page(regs[:-1], 7, 3)


def test_sample_counts_saturate_and_mark_nan():
    assert mr.sample_to_counts(float("nan"), 1.0) == mr.INVALID_SAMPLE
    assert mr.sample_to_counts(float("inf"), 1.0) == 2**31 - 1
    out = mr.counts_to_samples(np.array([mr.INVALID_SAMPLE, 2**31 - 1]), 2.0)
    assert np.isnan(out[0]) and out[1] == 2.0


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(-5, 70000), min_size=0, max_size=130), st.integers(0, 3), st.integers(0, 600))
def test_fuzzed_pages_and_control_blocks_give_only_frame_errors(regs, acq, page):
    for call in (lambda: mr.decode_page(regs, acq, page), lambda: mr.decode_control_block(regs[:30])):
        try:
            call()
        except FrameError:
            pass


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=0, max_size=40), st.integers(1, 5))
def test_fuzzed_adus_give_only_typed_errors(adu, count):
    for call in (
        lambda: mr.decode_read_response_pdu(mr.rtu_unframe(adu, 1), count),
        lambda: mr.decode_read_response_pdu(mr.mbap_unframe(adu, 0, 1), count),
        lambda: mr.decode_read_response_pdu(adu, count),
    ):
        try:
            call()
        except DeviceError:  # FrameError or ModbusExceptionError
            pass


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 123), st.integers(0, 15), st.integers(0, 255))
def test_every_single_bit_flip_of_a_page_is_detected(word, bit, acq):
    regs = mr.encode_page(acq, 1, [1, 2], [3, 4], [5, 6])
    bad = list(regs)
    bad[word] ^= 1 << bit
    with pytest.raises(FrameError):
        mr.decode_page(bad, acq, 1)
