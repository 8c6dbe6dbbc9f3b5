"""Issue 40 item 4: IEPE accelerometers and force sensors on NI-DAQmx, and AC coupling.

The nidaqmx stand-in records every call and attribute set; each is checked against the installed
``nidaqmx`` API (a call must bind to the real method's signature, an attribute must be a real
property of ``AIChannel``), so the stand-in cannot drift from the library. Truth for the AC
coupling's bound: the first-order high-pass's response computed by ``scipy.signal.freqs``.
"""

from __future__ import annotations

import inspect
import math
import types
from pathlib import Path

import numpy as np
import pytest

nidaqmx = pytest.importorskip("nidaqmx")

from nidaqmx.task.channels._ai_channel import AIChannel  # noqa: E402
from nidaqmx.task.collections._ai_channel_collection import AIChannelCollection  # noqa: E402

from setmem_hil.drivers.instruments.nidaq_sensor import DaqInputSetup, NidaqSensor, ac_coupling_error  # noqa: E402
from setmem_hil.drivers.instruments.sampled_rig import DaqChannel  # noqa: E402
from setmem_hil.errors import ProcedureError  # noqa: E402
from setmem_hil.estimation.sine_fit import fit_sine  # noqa: E402

import importlib.util as _importlib_util  # noqa: E402

_spec = _importlib_util.spec_from_file_location("_daq_procedures", Path(__file__).with_name("_daq_procedures.py"))
_daq_procedures = _importlib_util.module_from_spec(_spec)
_spec.loader.exec_module(_daq_procedures)
daq_procedure_text = _daq_procedures.daq_procedure_text

OMEGA = 2 * math.pi * 40.0
FORCE_N, ACCEL = 0.8, 3.0  # amplitudes: newtons, m/s^2


class Recorder:
    """nidaqmx's Task with the channel methods a DAQ path may call; the IEPE channels read in
    engineering units (N, m/s^2), as NI-DAQmx scales them."""

    def __init__(self):
        self.calls: list[tuple[str, tuple, dict]] = []
        self.attributes: list[tuple[str, str, object]] = []

    def module(self):
        rec = self

        class Channel:
            def __init__(self, name):
                object.__setattr__(self, "name", name)

            def __setattr__(self, key, value):
                rec.attributes.append((self.name, key, value))

        def adder(method):
            def add(name, **kwargs):
                rec.calls.append((method, (name,), kwargs))
                return Channel(name)
            return add

        class Task:
            def __init__(self):
                self.ai_channels = types.SimpleNamespace(**{m: adder(m) for m in ("add_ai_voltage_chan", "add_ai_accel_chan",
                                                                                  "add_ai_force_iepe_chan")})
                self.timing = types.SimpleNamespace(cfg_samp_clk_timing=self._timing)

            def _timing(self, rate, **k):
                self.rate, self.n = rate, k["samps_per_chan"]

            def read(self, **k):
                t = np.arange(self.n) / self.rate
                return [(FORCE_N * np.sin(OMEGA * t)).tolist(), (ACCEL * np.sin(OMEGA * t + 0.3)).tolist()]

            def close(self):
                pass

        return types.SimpleNamespace(Task=Task, constants=nidaqmx.constants, errors=nidaqmx.errors)


def test_iepe_channels_are_created_with_nidaqmxs_accelerometer_and_force_types():
    rec = Recorder()
    force_v_per_n, accel_v_per_ms2 = 0.0225, 0.0102  # 22.5 mV/N; 100 mV/g
    sensor = NidaqSensor("Dev1/ai0", "Dev1/ai1", force_v_per_n, accel_v_per_ms2, range_v=5.0, nidaqmx_module=rec.module(),
                         setups=[DaqInputSetup("force", 0.004, "AC"), DaqInputSetup("acceleration", 0.002, "AC")])
    sensor.set_sample_rate(40.0 * 32)
    block = sensor.acquire(1.0)
    real = {"add_ai_accel_chan": AIChannelCollection.add_ai_accel_chan, "add_ai_force_iepe_chan": AIChannelCollection.add_ai_force_iepe_chan}
    for name, args, kwargs in rec.calls:
        inspect.signature(real[name]).bind(None, *args, **kwargs)  # TypeError if nidaqmx has no such call
    (force_call, accel_call) = rec.calls
    constants = nidaqmx.constants
    assert force_call[0] == "add_ai_force_iepe_chan" and force_call[1] == ("Dev1/ai0",)
    assert force_call[2]["sensitivity"] == pytest.approx(22.5)
    assert force_call[2]["sensitivity_units"] == constants.ForceIEPESensorSensitivityUnits.MILLIVOLTS_PER_NEWTON
    assert force_call[2]["units"] == constants.ForceUnits.NEWTONS
    assert force_call[2]["current_excit_source"] == constants.ExcitationSource.INTERNAL and force_call[2]["current_excit_val"] == 0.004
    assert force_call[2]["max_val"] == pytest.approx(5.0 / force_v_per_n)  # the +-5 V input in newtons
    assert accel_call[0] == "add_ai_accel_chan" and accel_call[2]["units"] == constants.AccelUnits.METERS_PER_SECOND_SQUARED
    assert accel_call[2]["sensitivity"] == pytest.approx(accel_v_per_ms2 * 1000 * 9.80665)  # mV/g
    assert accel_call[2]["sensitivity_units"] == constants.AccelSensitivityUnits.MILLIVOLTS_PER_G
    assert accel_call[2]["current_excit_val"] == 0.002
    assert rec.attributes == [("Dev1/ai0", "ai_coupling", constants.Coupling.AC), ("Dev1/ai1", "ai_coupling", constants.Coupling.AC)]
    assert isinstance(inspect.getattr_static(AIChannel, "ai_coupling"), property)
    # the readings come in N and m/s^2 and stay so (not divided by the sensitivity a second time)
    assert abs(fit_sine(block.t_s, block.force, OMEGA).phasor) == pytest.approx(FORCE_N, rel=1e-9)
    assert abs(fit_sine(block.t_s, block.response, OMEGA).phasor) == pytest.approx(ACCEL, rel=1e-9)


def test_a_plain_voltage_channel_may_be_ac_coupled_and_nothing_else_changes():
    rec = Recorder()
    sensor = NidaqSensor("Dev1/ai0", "Dev1/ai1", 1.0, 1.0, nidaqmx_module=rec.module(),
                         setups=[DaqInputSetup("force"), DaqInputSetup("displacement", 0.0, "AC")])
    sensor.acquire(0.1)
    assert [c[0] for c in rec.calls] == ["add_ai_voltage_chan", "add_ai_voltage_chan"]
    assert rec.attributes == [("Dev1/ai1", "ai_coupling", nidaqmx.constants.Coupling.AC)]


@pytest.mark.parametrize("f_hz", [0.1, 0.5, 2.0, 40.0])
def test_the_ac_coupling_bound_holds_the_high_pass_and_is_tight(f_hz):
    """``|H(j w) - 1|`` of the first-order high-pass at 0.5 Hz, from scipy's own evaluation of
    ``s / (s + w_c)``: the relative disc the bound adds equals it (it is the worst case: a
    reading is the truth times H)."""
    from scipy.signal import freqs

    corner = 0.5
    w = 2 * math.pi * f_hz
    _, h = freqs([1.0, 0.0], [1.0, 2 * math.pi * corner], worN=[w])
    assert ac_coupling_error(w, corner) == pytest.approx(abs(h[0] - 1.0), rel=1e-12)
    assert DaqChannel(ac_corner_hz=corner).error_at(w).relative == pytest.approx(abs(h[0] - 1.0), rel=1e-12)
    assert DaqChannel().error_at(w).relative == 0.0
    # the force trip's margin: how much larger the truth may be than the reading
    assert DaqChannel(ac_corner_hz=corner).shortfall_at(w) == pytest.approx(1.0 / abs(h[0]) - 1.0, rel=1e-12)


def test_an_ac_coupled_response_point_carries_the_high_pass_in_its_bound():
    """Through the sampled rig's correction: a point at 1 Hz on a 0.5 Hz AC-coupled response
    input has a bound of at least |H - 1| |g|; the truth (reading / H) is inside it."""
    from setmem_hil.drivers.instruments.sampled_rig import LevelledDaqSensor
    from setmem_hil.model.experiment import Measurement

    corner, w = 0.5, 2 * math.pi * 1.0
    h = 1j * w / (1j * w + 2 * math.pi * corner)
    truth = 0.02 * np.exp(-0.4j)
    reading = truth * h  # the response input's high-pass; the force input DC coupled
    sensor = LevelledDaqSensor.__new__(LevelledDaqSensor)
    sensor.force, sensor.responses = DaqChannel(quantity="force"), (DaqChannel(ac_corner_hz=corner),)
    sensor.leveller = types.SimpleNamespace(where="NI-DAQ")
    m = sensor.corrected(Measurement(omega_rad_s=w, response=complex(reading), bound=0.0), 1.0)
    assert m.bound >= abs(h - 1) * abs(reading) and abs(m.response - truth) <= m.bound
    dc = LevelledDaqSensor.__new__(LevelledDaqSensor)
    dc.force, dc.responses, dc.leveller = DaqChannel(quantity="force"), (DaqChannel(),), sensor.leveller
    assert dc.corrected(Measurement(omega_rad_s=w, response=complex(reading), bound=0.0), 1.0).bound == 0.0


IEPE_FORCE = "iepe_current_a = 0.004"
IEPE_ACCELEROMETER = 'quantity = "acceleration"\niepe_current_a = 0.004\ncoupling = "AC"'
DAQ_RIG = daq_procedure_text("TCPIP::192.168.1.20::5025::SOCKET", force="force_sensor", response="accelerometer",
                             force_keys=IEPE_FORCE, response_keys=IEPE_ACCELEROMETER)


def test_the_procedure_keys_reach_the_channels():
    from setmem_hil.drivers.instruments.instrument_set import ac_corner, check_instruments, daq_input_setup
    from setmem_hil.drivers.instruments.profile import load_profile
    from setmem_hil.io.procedure_file import format_procedure, parse_procedure_text

    procedure = parse_procedure_text(DAQ_RIG, "iepe.toml")
    check_instruments(procedure)
    force, accel = procedure.instruments["force_sensor"], procedure.instruments["accelerometer"]
    assert force.iepe_current_a == 0.004 and force.coupling is None and accel.coupling == "AC"
    assert daq_input_setup(force, "force") == DaqInputSetup("force", 0.004, "AC")  # AC by default with IEPE
    assert daq_input_setup(accel, "displacement") == DaqInputSetup("acceleration", 0.004, "AC")
    assert accel.resource == "Dev1/ai1" and accel.volt_per_unit == 0.004
    assert ac_corner(force, load_profile("ni-daqmx")) == 0.5
    again = parse_procedure_text(format_procedure(procedure), "again.toml")  # the journal's copy keeps them
    assert again.instruments["accelerometer"] == accel and again.instruments["force_sensor"] == force


@pytest.mark.parametrize("change, where, words", [
    ('quantity = "acceleration"\niepe_current_a = 0.004\ncoupling = "AC"', "", ""),
    ('quantity = "acceleration"\niepe_current_a = 0.004\ncoupling = "DC"', "[instruments.accelerometer] key 'coupling'", "bias"),
    ('quantity = "displacement"\niepe_current_a = 0.004', "[instruments.accelerometer] key 'iepe_current_a'", "force and acceleration"),
    ('quantity = "acceleration"\niepe_current_a = 0.5', "iepe_current_a", "0.025"),
    ('quantity = "acceleration"\ncoupling = "ACDC"', "coupling", "AC"),
])
def test_a_wrong_iepe_setting_is_refused_naming_the_key(change, where, words):
    from setmem_hil.drivers.instruments.instrument_set import check_instruments
    from setmem_hil.io.procedure_file import parse_procedure_text

    text = DAQ_RIG.replace(IEPE_ACCELEROMETER, change)
    if not where:
        check_instruments(parse_procedure_text(text, "iepe.toml"))
        return
    with pytest.raises(ProcedureError) as info:
        check_instruments(parse_procedure_text(text, "iepe.toml"))
    assert where in str(info.value) and words in str(info.value)


def test_iepe_on_a_lock_in_is_refused():
    from setmem_hil.drivers.instruments.instrument_set import check_instruments
    from setmem_hil.io.procedure_file import load_procedure


    path = Path(__file__).resolve().parents[1] / "procedures" / "instruments_emulated.toml"
    text = path.read_text().replace('profile = "srs-sr830"', 'profile = "srs-sr830"\niepe_current_a = 0.004', 1)
    from setmem_hil.io.procedure_file import parse_procedure_text

    with pytest.raises(ProcedureError, match=r"key 'iepe_current_a'.*only NI-DAQmx channels"):
        check_instruments(parse_procedure_text(text, str(path)))
    assert load_procedure(path)  # the shipped file itself is fine
