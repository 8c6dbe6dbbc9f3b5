"""Sine dwell on the in-process fake device: truth inside the bound, safety, faults, resume."""

import numpy as np
import pytest

from setmem_hil.drivers.protocols import SampleBlock
from setmem_hil.drivers.sine_dwell import DwellSettings, SineDwellExperiment
from setmem_hil.estimation.dwell_estimate import check_block
from setmem_hil.errors import DataQualityError, DeviceError, SafetyLimitError
from setmem_hil.io.procedure import SafetyLimits, default_procedure, thesis_beam_prior
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.core_rig import CoreRig
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore, FaultSettings

TRUTH = beam_parameters()  # the fake device simulates all 8 modes


def _experiment(seed=1, faults=None, **kw):
    core = FakeDeviceCore.from_procedure(default_procedure(), seed, faults=faults or FaultSettings())
    return core, SineDwellExperiment(CoreRig(core), SafetyLimits(), model=thesis_beam_prior().initial_bounds(), **kw)


@pytest.mark.slow
def test_seeded_sweep_of_200_dwells_contains_the_truth_in_99_percent():
    # the acceptance test: 200 dwells, fully damped noise profile, from 0.3 to 40 rad/s
    rng = np.random.default_rng(2024)
    omegas = np.exp(rng.uniform(np.log(0.3), np.log(40.0), 200))
    core, exp = _experiment(seed=11)
    inside = 0
    for w in omegas:
        m = exp.measure(w)
        inside += abs(m.response - TRUTH.frequency_response(w)[0]) <= m.bound
    assert inside >= 198, f"{inside}/200 dwells contain the true response"
    assert exp.n_measured == 200


def test_bound_is_informative_not_just_large():
    # per-sample noise RMS is the profile's R(omega); hundreds of samples must do much better
    from setmem_hil.sim_backends.noise import noise_bound_function

    r = noise_bound_function("fully_damped", TRUTH)
    _, exp = _experiment(seed=2)
    for w in (0.9, 3.0, 6.0, 12.0):
        m = exp.measure(w)
        g = TRUTH.frequency_response(w)[0]
        assert abs(m.response - g) <= m.bound
        assert m.bound < 0.5 * r(np.array([w]))[0]


def test_short_dwell_near_first_mode_beats_five_time_constants():
    _, exp = _experiment(seed=3)
    exp.measure(0.95)
    r = exp.last_result
    assert r.dwell_s < 0.3 * 500.0  # 5 tau of the first mode is 500 s
    assert abs(r.measurement.response - TRUTH.frequency_response(0.95)[0]) <= r.measurement.bound


class RecordingRig:
    """A rig that records commands; the sensor can be told to fail."""

    def __init__(self, fail=None, stop_fail=None):
        from setmem_hil.drivers.protocols import RigMetadata

        self.metadata = RigMetadata(10.0, 10.0, 1000.0)
        self.sent = []
        self.fail = fail
        self.stop_fail = stop_fail
        outer = self

        class Ex:
            def set_sine(self, w, a):
                outer.sent.append(("sine", w, a))

            def stop(self):
                outer.sent.append(("stop",))
                if outer.stop_fail is not None:
                    raise outer.stop_fail

        class Se:
            def acquire(self, duration_s):
                if outer.fail is not None:
                    raise outer.fail
                n = int(duration_s * 10)
                t = np.arange(n) / 10.0
                return SampleBlock(t, np.sin(t), np.cos(t))

        self.exciter, self.sensor = Ex(), Se()
        self.closed = False

    def close(self):
        self.closed = True


def test_safety_limits_raise_before_anything_is_sent():
    rig = RecordingRig()
    exp = SineDwellExperiment(rig, SafetyLimits(omega_min_rad_s=0.5, omega_max_rad_s=50.0))
    for w in (0.1, 60.0, float("nan")):
        with pytest.raises(SafetyLimitError, match="omega"):
            exp.measure(w)
    assert rig.sent == []
    with pytest.raises(SafetyLimitError, match="amplitude"):
        SineDwellExperiment(rig, SafetyLimits(max_amplitude_n=0.5), DwellSettings(amplitude_n=1.0))
    with pytest.raises(SafetyLimitError, match="max_dwell_s"):
        SineDwellExperiment(rig, SafetyLimits(max_dwell_s=10.0)).measure(0.6)
    assert rig.sent == []


@pytest.mark.parametrize("exc", [KeyboardInterrupt(), RuntimeError("boom")])
def test_exciter_goes_to_zero_on_unexpected_errors(exc):
    rig = RecordingRig(fail=exc)
    exp = SineDwellExperiment(rig, SafetyLimits())
    with pytest.raises(type(exc)):
        exp.measure(2.0)
    assert rig.sent[-1] == ("stop",)
    exp.close()
    assert rig.closed and rig.sent[-1] == ("stop",)


def test_ctrl_c_stays_ctrl_c_when_the_stop_also_fails():
    rig = RecordingRig(fail=KeyboardInterrupt(), stop_fail=DeviceError("link down"))
    exp = SineDwellExperiment(rig, SafetyLimits())
    with pytest.raises(KeyboardInterrupt):
        exp.measure(2.0)
    assert sum(1 for s in rig.sent if s[0] == "sine") == 1  # not retried
    assert ("stop",) in rig.sent


def test_device_errors_are_retried_then_raised_with_every_attempt_listed():
    rig = RecordingRig(fail=DeviceError("link down"))
    exp = SineDwellExperiment(rig, SafetyLimits(), DwellSettings(max_attempts=3))
    with pytest.raises(DeviceError, match="after 3 attempts.*attempt 3: device fault: link down"):
        exp.measure(2.0)
    assert sum(1 for s in rig.sent if s[0] == "sine") == 3
    assert rig.sent[-1] == ("stop",)


@pytest.mark.parametrize("kind", ["saturation", "nan", "inf", "timestamp_jump"])
def test_corrupted_dwells_are_discarded_and_measured_again(kind):
    core, exp = _experiment(seed=4, faults=FaultSettings(rate=0.5, kinds=(kind,), seed=1))
    for w in (1.2, 4.0, 9.0):
        m = exp.measure(w)
        assert abs(m.response - TRUTH.frequency_response(w)[0]) <= m.bound
    assert core.faults.injected[kind] >= 1
    assert exp.counters["discarded_dwell"] == core.faults.injected[kind]


def test_persistent_bad_data_raises_data_quality_error():
    core, exp = _experiment(seed=4, faults=FaultSettings(rate=1.0, kinds=("nan",), seed=1), settings=DwellSettings(max_attempts=2))
    with pytest.raises(DataQualityError, match="after 2 attempts.*NaN"):
        exp.measure(3.0)
    assert core.status().output_on is False


def test_check_block_names_the_problem():
    t = np.arange(20) / 10.0
    ok = SampleBlock(t, np.zeros(20), np.zeros(20))
    check_block(ok, 10.0, 1.0, 10.0)
    with pytest.raises(DataQualityError, match="full scale"):
        check_block(SampleBlock(t, np.zeros(20), np.full(20, 1.0)), 10.0, 1.0, 10.0)
    with pytest.raises(DataQualityError, match="timestamp jump"):
        check_block(SampleBlock(np.r_[t[:10], t[10:] + 1.0], np.zeros(20), np.zeros(20)), 10.0, 1.0, 10.0)


def test_resumed_experiment_measures_what_an_uninterrupted_one_would():
    _, a = _experiment(seed=7)
    full = [a.measure(w) for w in (0.8, 2.0, 5.0)]
    _, b = _experiment(seed=7)
    b.n_measured = 2
    assert b.measure(5.0) == full[2]


def test_extra_bound_is_added():
    _, a = _experiment(seed=8)
    _, b = _experiment(seed=8, extra_bound=lambda w: 0.5)
    assert b.measure(3.0).bound == pytest.approx(a.measure(3.0).bound + 0.5)


def test_interpreter_exit_without_close_zeroes_the_output():
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import atexit
        from setmem_hil.drivers.sine_dwell import SineDwellExperiment
        from setmem_hil.io.procedure import SafetyLimits
        from setmem_hil.sim_backends.core_rig import CoreRig
        from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
        core = FakeDeviceCore(seed=1)
        rig = CoreRig(core)
        atexit.register(lambda: print("output_on", core.status().output_on, "closed", rig.closed))
        exp = SineDwellExperiment(rig, SafetyLimits())
        exp.exciter.set_sine(2.0, 1.0)  # left running, exp never closed
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "output_on False closed True" in out.stdout


def test_safety_checks_are_inclusive_at_the_limits_and_reject_non_finite():
    from setmem_hil.drivers.safety import SafeExciter, check_dwell, check_sine_command

    lim = SafetyLimits(max_amplitude_n=0.5, omega_min_rad_s=1.0, omega_max_rad_s=10.0, max_dwell_s=60.0)
    check_sine_command(lim, 1.0, 0.5)
    check_sine_command(lim, 10.0, 0.0)
    for w, a, what in ((0.999, 0.1, "omega"), (10.001, 0.1, "omega"), (5.0, 0.5001, "amplitude"),
                       (5.0, -0.1, "amplitude"), (float("inf"), 0.1, "omega"), (5.0, float("nan"), "amplitude")):
        with pytest.raises(SafetyLimitError, match=f"{what}.*nothing was sent"):
            check_sine_command(lim, w, a)
    check_dwell(lim, 60.0)
    with pytest.raises(SafetyLimitError, match="max_dwell_s"):
        check_dwell(lim, 60.5)
    rig = RecordingRig()
    safe = SafeExciter(rig.exciter, lim)
    with pytest.raises(SafetyLimitError):
        safe.set_sine(20.0, 0.1)
    safe.set_sine(2.0, 0.1)
    assert rig.sent == [("sine", 2.0, 0.1)]


def test_learned_poles_converge_to_the_true_pole_and_shrink_the_bound():
    core = FakeDeviceCore.from_procedure(default_procedure(), 12)
    settings = DwellSettings(max_window_s=60.0, learn_poles=True)
    exp = SineDwellExperiment(CoreRig(core), SafetyLimits(), settings, model=thesis_beam_prior().initial_bounds())
    _, plain = _experiment(seed=12, settings=DwellSettings(max_window_s=60.0))
    g = TRUTH.frequency_response(0.95)[0]
    bounds, plain_bounds = [], []
    for _ in range(12):
        m = exp.measure(0.95)
        assert abs(m.response - g) <= m.bound
        bounds.append(m.bound)
        plain_bounds.append(plain.measure(0.95).bound)
    pole, cov = exp.pole_tracker.estimate(0)
    true = TRUTH.natural_frequencies[0] * np.sqrt(1 - 0.01**2)
    assert abs(pole.omega_d_rad_s - true) < 5 * np.sqrt(cov[1, 1]) and np.sqrt(cov[1, 1]) < 1e-3  # prior: 0.1
    assert abs(pole.sigma_per_s - 0.01) < 5 * np.sqrt(cov[0, 0])
    assert np.mean(bounds[-4:]) < 0.85 * np.mean(plain_bounds[-4:])


def test_update_model_uses_the_new_poles():
    from setmem_hil.estimation.dwell_estimate import pole_bands
    from setmem_hil.model.modal_model import IntervalModel

    _, exp = _experiment(seed=13)
    wide = exp.plan(5.0)
    v = TRUTH.truncated(3).values
    exp.update_model(IntervalModel(v * [0.999, 0.999, 1, 0.9], v * [1.001, 1.001, 1, 1.1]))
    bands = pole_bands(exp.model)
    assert bands[1].omega_min_rad_s == pytest.approx(np.sqrt(v[1, 1] * 0.999))
    assert exp.plan(5.0).window_s != wide.window_s  # the separation from mode 2 is now known
    m = exp.measure(5.0)
    assert abs(m.response - TRUTH.frequency_response(5.0)[0]) <= m.bound


def test_the_rig_time_of_a_refused_record_is_counted():
    """A timed sensor's acquisition that fails (a clipped record taken again, a levelling that
    failed) took rig time: the dwell's rig_s holds it, not only the attempt that succeeded."""
    from setmem_hil.errors import DataQualityError

    rig = RecordingRig()
    inner = rig.sensor.acquire
    calls = []

    class TimedSensor:
        last_acquire_s, last_sample_rate_hz = 0.0, 10.0

        def acquire(self, duration_s):
            calls.append(duration_s)
            self.last_acquire_s = duration_s + 1.0  # what the instrument's clock counted
            if len(calls) == 2:  # the first window is refused
                raise DataQualityError("clipped")
            return inner(duration_s)

        def corrected(self, m, force_amplitude):
            return m

    rig.sensor = TimedSensor()
    with SineDwellExperiment(rig, default_procedure().safety) as exp:
        m = exp.measure(3.0)
    assert len(calls) == 4  # settle + refused window, settle + window
    assert m.rig_s == pytest.approx(sum(calls) + len(calls))
