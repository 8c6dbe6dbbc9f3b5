"""Issue 13, the pieces: SCPI headers, profiles, register codec, lock-in phasor statistics,
the emulated bench's physics and the phasor dwell's safety order."""

from __future__ import annotations

import math
import re
import struct

import numpy as np
import pytest

from setmem_hil.drivers.instruments.profile import RegisterSpec, load_profile, parse_profile, shipped_profiles
from setmem_hil.drivers.instruments.register_codec import decode, encode
from setmem_hil.drivers.instruments.scpi_commands import canonical_header
from setmem_hil.errors import ProcedureError
from setmem_hil.estimation.phasor_estimate import calibration_radius, noise_radius, phasor_point, settling_test


@pytest.mark.parametrize("a, b", [
    (":SOURce1:FREQuency?", "SOUR1:FREQ?"), ("sour1:freq", "SOUR1:FREQ"), ("OUTPut2:LOAD", "OUTP2:LOAD"),
    ("SYSTem:ERRor?", "SYST:ERR?"), ("SOURce:VOLTage:OFFSet", "SOUR:VOLT:OFFS"), ("OUTPut:IMPedance", "OUTP:IMP"),
])
def test_scpi_long_and_short_forms_compare_equal(a, b):
    # SCPI-99 vol. 1, 6.2.1: the short form is the first four letters, three if the fourth is a vowel
    assert canonical_header(a) == canonical_header(b)


def test_every_shipped_profile_loads_with_its_kind():
    kinds = {name: load_profile(name).kind for name in shipped_profiles()}
    assert kinds["keysight-33500b"] == kinds["rigol-dg800"] == "scpi-generator"
    assert kinds["srs-sr830"] == kinds["srs-sr860"] == "scpi-lockin"
    assert kinds["modbus-shaker-controller"] == "modbus"


def test_profile_errors_name_file_table_and_key(tmp_path):
    good = (load_profile("keysight-33500b").source)
    text = open(good).read()
    with pytest.raises(ProcedureError, match=r"bad\.toml: \[commands\]\.frequency_hz: unknown key 'tolerence_rel'; did you mean 'tolerance_rel'"):
        parse_profile(text.replace("tolerance_rel = 1e-9", "tolerence_rel = 1e-9"), "bad.toml")
    with pytest.raises(ProcedureError, match=r"unknown field \{chan\}"):
        parse_profile(text.replace("SOUR{ch}:FREQ {value:.10g}", "SOUR{chan}:FREQ {value:.10g}"), "bad.toml")
    with pytest.raises(ProcedureError, match="kind: expected one of"):
        parse_profile('kind = "scpi-oscilloscope"\n', "bad.toml")
    modbus = open(load_profile("modbus-shaker-controller").source).read()
    with pytest.raises(ProcedureError, match="type: a coil is one bit and takes no type"):
        parse_profile(modbus.replace('output = { table = "coil", address = 0 }', 'output = { table = "coil", address = 0, type = "uint16" }'), "m.toml")
    with pytest.raises(ProcedureError, match="word_order: expected 'big' or 'little'"):
        parse_profile(modbus.replace('word_order = "big" }', 'word_order = "middle" }', 1), "m.toml")


@pytest.mark.parametrize("kind, value, scale", [("uint16", 65535, 1.0), ("int16", -2.5, 0.01), ("uint32", 4e9, 1.0),
                                                 ("int32", -123456.7, 0.1), ("float32", 1234.5, 1.0)])
@pytest.mark.parametrize("order", ["big", "little"])
def test_register_codec_against_struct(kind, value, scale, order):
    spec = RegisterSpec("holding", 0, kind, scale, order)
    words = encode(value, spec)
    fmt = {"uint16": ">H", "int16": ">h", "uint32": ">I", "int32": ">i", "float32": ">f"}[kind]
    raw = value / scale if kind == "float32" else round(value / scale)
    data = struct.pack(fmt, raw)
    big = [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]
    assert words == (big if order == "big" else big[::-1])
    assert decode(words, spec) == pytest.approx(value, rel=1e-7, abs=scale / 2)


def test_register_codec_refuses_what_does_not_fit():
    with pytest.raises(ValueError, match="does not fit a uint16"):
        encode(70000, RegisterSpec("holding", 0, "uint16"))
    with pytest.raises(ValueError, match="does not fit a int16"):
        encode(-1.0, RegisterSpec("holding", 0, "int16", 1e-5))


# -- phasor statistics ---------------------------------------------------------------------------------
def test_noise_radius_covers_the_true_mean_at_its_confidence():
    rng = np.random.default_rng(7)
    truth, sigma, n, trials = 2.0 - 1.0j, 0.05, 8, 4000
    hits = 0
    for _ in range(trials):
        z = truth + sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
        hits += abs(z.mean() - truth) <= noise_radius(z, 0.99)
    assert 0.985 <= hits / trials <= 0.996


def test_settling_test_false_alarm_rate_and_power():
    rng = np.random.default_rng(3)
    noise = lambda n: 0.01 * (rng.standard_normal(n) + 1j * rng.standard_normal(n))  # noqa: E731
    steady = [settling_test(1.0 + noise(8), 0.99) for _ in range(3000)]
    assert 0.98 <= np.mean(steady) <= 0.997
    t = np.arange(8)
    decaying = [settling_test(1.0 + 0.2 * np.exp(-t / 3.0) + noise(8), 0.99) for _ in range(300)]
    assert np.mean(decaying) < 0.05  # a transient 20x the noise is seen


def test_calibration_radius_is_the_worst_case_over_the_sensitivity_box():
    g, cf, cr = 3.0 + 4.0j, 0.02, 0.01
    worst = max(abs(g * (1 + ef) / (1 + er) - g) for ef in np.linspace(-cf, cf, 41) for er in np.linspace(-cr, cr, 41))
    assert calibration_radius(g, cf, cr) >= worst * (1 - 1e-12)
    assert calibration_radius(g, cf, cr) <= worst * 1.02


def test_phasor_point_ratio_units_and_force_amplitude():
    F = np.full(8, 0.0225 * 0.8 / math.sqrt(2)) + 0j  # 0.8 N peak through 22.5 mV/N, as RMS
    g_true = 0.3 - 0.1j
    R = F / 0.0225 * g_true * 1000.0  # 1000 V per metre
    p = phasor_point(F, R, 0.0225, 1000.0)
    assert p.response == pytest.approx(g_true)
    assert p.force_amplitude == pytest.approx(0.8)


def test_sensor_quantities_convert_to_receptance():
    from setmem_hil.drivers.instruments.phasor_dwell import to_receptance

    w, x = 7.0, 0.02 - 0.01j  # displacement per newton
    assert to_receptance(1j * w * x, w, "velocity") == pytest.approx(x)  # v = j w x
    assert to_receptance(-(w**2) * x, w, "acceleration") == pytest.approx(x)  # a = -w^2 x
    assert to_receptance(x, w, "displacement") == x


@pytest.mark.parametrize("resource, problem", [
    ("tcp://10.0.0.5", "expected tcp://HOST:PORT"), ("rtu://?baudrate=9600", "expected rtu://PORT"),
    ("rtu:///dev/ttyUSB0?baud=9600", "unknown RTU option 'baud'"), ("rtu:///dev/ttyUSB0?parity=X", "parity must be N, E or O"),
    ("modbus://10.0.0.5:502", "a Modbus resource is tcp://"),
])
def test_modbus_resource_errors_say_what_is_expected(resource, problem):
    from setmem_hil.drivers.instruments.modbus_generator import parse_modbus_resource

    with pytest.raises(ValueError, match=re.escape(problem)):
        parse_modbus_resource(resource)


def test_modbus_controller_watchdog_switches_the_output_off():
    """The dead-man: with the output on, the emulated controller stops driving when the
    watchdog register is not rewritten within its timeout (bench clock)."""
    from setmem_hil.drivers.instruments.modbus_generator import ModbusGenerator
    from setmem_hil.sim_backends.beam import beam_parameters
    from setmem_hil.sim_backends.instrument_bench import EmulatedBench
    from setmem_hil.sim_backends.modbus_controller_emulator import ModbusControllerEmulator

    profile = load_profile("modbus-shaker-controller")
    bench = EmulatedBench(beam_parameters())
    controller = ModbusControllerEmulator(bench, profile).start()
    gen = ModbusGenerator("plc", profile, f"tcp://127.0.0.1:{controller.port}")
    try:
        gen.check_identity()
        gen.initialise()
        gen.set_frequency_hz(1.0)
        gen.set_amplitude_v(0.1)
        gen.set_output(True)
        bench.clock.sleep(0.9 * profile.watchdog_timeout_s)
        gen.keepalive()
        assert bench.output_on  # refreshed in time
        bench.clock.sleep(1.5 * profile.watchdog_timeout_s)
        gen.read(profile.output, "output")  # any request: the controller notices the silence
        assert not bench.output_on and controller.watchdog_trips == 1
    finally:
        gen.close()
        controller.close()


@pytest.mark.parametrize("model", ["SR830", "SR860"])
def test_lockin_sensitivity_lists_match_pymeasure(model):
    pymeasure_srs = pytest.importorskip("pymeasure.instruments.srs")
    cls = pymeasure_srs.SR830 if model == "SR830" else pymeasure_srs.SR860
    profile = load_profile("srs-sr830" if model == "SR830" else "srs-sr860")
    assert list(profile.sensitivities_v) == [float(v) for v in cls.SENSITIVITIES]


def _emulated_experiment(response_volt_per_unit: float):
    import dataclasses
    from pathlib import Path

    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.procedure_file import load_procedure

    p = load_procedure(Path(__file__).resolve().parents[1] / "procedures" / "instruments_emulated.toml")
    sensor = dataclasses.replace(p.instruments["lia_response"], volt_per_unit=response_volt_per_unit)
    return open_experiment(dataclasses.replace(p, instruments={**p.instruments, "lia_response": sensor}), seed=1)


def test_auto_range_picks_the_smallest_full_scale_with_room():
    with _emulated_experiment(0.004) as exp:
        w = 14.0376  # between modes: a small response
        exp.measure(w)
        lia = exp.response
        force_n = 1.0 / 1.01  # the level target: max_amplitude_n / (1 + force calibration uncertainty)
        rms = 0.004 * abs(exp.bench.true_response(w)) * force_n / math.sqrt(2)  # response signal, V RMS
        # 3 x max(|X|, |Y|) lies between 3 rms / sqrt(2) and 3 rms
        assert lia.full_scale_v >= 3 * rms / math.sqrt(2) * 0.98
        smaller = [v for v in lia.profile.sensitivities_v if v < lia.full_scale_v]
        assert not smaller or max(smaller) < 3 * rms * 1.02
        assert lia.full_scale_v < 1.0  # ranged down from the init's 1 V


def test_overload_at_the_largest_range_stops_with_the_output_off():
    from setmem_hil.errors import DeviceRejectedError

    with _emulated_experiment(0.1) as exp:  # 4 V peak at 0.95 rad/s: beyond the 1 V full scale
        # a device fault (exit 4), not a data-quality error (exit 1)
        with pytest.raises(DeviceRejectedError, match=r"lia_response .*overload.*1 V full scale.*largest full scale"):
            exp.measure(0.95)
        assert not exp.bench.output_on


def test_a_fault_mid_dwell_propagates_even_when_output_off_also_fails(caplog):
    """The cause reaches the technician; the failing output-off is logged, not substituted."""
    from setmem_hil.errors import DeviceDisconnectedError, DeviceError, DeviceTimeoutError

    exp = _emulated_experiment(0.004)
    try:
        def timeout(*a, **k):
            raise DeviceTimeoutError("fgen: no reply to 'SOUR1:FREQ?' within 2 s")

        def refuse_off(on):
            raise DeviceDisconnectedError("fgen: connection lost")

        exp.source.set_frequency_hz = timeout
        exp.source.set_output = refuse_off
        with pytest.raises(DeviceTimeoutError, match="no reply"):
            exp.measure(3.0)
        assert "could not be confirmed off" in caplog.text and "switch it off at the instrument" in caplog.text
        exp.closed = True
        with pytest.raises(DeviceError, match=r"measure\(\) after close\(\)"):
            exp.measure(3.0)
    finally:
        exp.closed = False
        del exp.source.set_output  # the real one again, so close() switches the emulated output off
        exp.close()
        assert not exp.bench.output_on
