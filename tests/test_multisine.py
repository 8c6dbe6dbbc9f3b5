"""Multisine dwells (issue 15): the signal, the simulated structure under it, the per-line bounds
(coverage against the simulated truth), the procedure key, the campaign's records and their resume."""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lsim

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.cli.main import main
from setmem_hil.errors import ProcedureError, SafetyLimitError
from setmem_hil.estimation.multisine import design_multisine
from setmem_hil.estimation.sine_fit import fit_sine
from setmem_hil.experiment_factory import dwell_experiment, open_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import default_procedure
from setmem_hil.io.procedure_file import load_procedure, parse_procedure_text
from setmem_hil.io.procedure_writer import format_procedure as procedure_text
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.core_rig import CoreRig
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore
from setmem_hil.sim_backends.noise import noise_bound_function
from setmem_hil.sim_backends.time_domain_beam import TimeDomainBeam

_spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)

INITIAL = default_procedure().initial_omegas_rad_s


def test_peak_of_the_sum_is_within_the_limit_over_the_whole_record():
    duration = 80.0
    ms = design_multisine(INITIAL, peak_n=1.0, duration_s=duration)
    t = np.linspace(0.0, duration, 2_000_001)  # independent check: 100x finer than the design's grid
    peak = float(np.max(np.abs(ms.force(t))))
    assert peak <= 1.0
    assert len(set(ms.amplitudes_n)) == 1
    # the phases earn their keep: aligned phases would need amplitudes summing to 1 N
    assert sum(ms.amplitudes_n) > 1.5


def test_safe_exciter_refuses_a_multisine_over_the_limit_before_sending():
    from setmem_hil.drivers.safety import SafeExciter

    sent = []

    class Recorder:
        def set_multisine(self, *args):
            sent.append(args)

        def stop(self):
            pass

    limits = default_procedure().safety
    ms = design_multisine([1.0, 2.0, 3.0], peak_n=limits.max_amplitude_n * 1.2, duration_s=30.0)
    with pytest.raises(SafetyLimitError, match="peak force"):
        SafeExciter(Recorder(), limits).set_multisine(ms, 30.0)
    assert sent == []


def test_time_domain_beam_under_a_multisine_matches_lsim():
    truth = beam_parameters().truncated(3)
    ms = design_multisine([0.7, 3.0, 9.0], peak_n=1.0, duration_s=40.0)
    beam = TimeDomainBeam(truth)
    beam.set_multisine(ms.omegas_rad_s, ms.amplitudes_n, ms.phases_rad)
    dt = 0.01
    force, disp = beam.simulate(4000, dt)
    t = np.arange(4000) * dt
    np.testing.assert_allclose(force, ms.force(t), atol=1e-12)
    A, B, C, D = truth.state_space_matrices()
    fine = np.arange(40001) * (dt / 10)  # lsim interpolates the input linearly: a fine grid
    _, y, _ = lsim((A, B, C, D), ms.force(fine), fine)
    np.testing.assert_allclose(disp, y[::10][:4000], atol=2e-5 * np.max(np.abs(y)))


def test_joint_fit_of_several_lines_recovers_each_phasor():
    rng = np.random.default_rng(5)
    lines = np.array([0.9, 0.95, 1.06, 5.0, 17.0])
    true = np.array([1 + 2j, 0.5 - 1j, 3j, 0.1, 0.02 - 0.01j])
    t = np.arange(12000) * 0.01
    y = sum((Y * np.exp(1j * w * t)).real for w, Y in zip(lines, true)) + 0.01 * rng.standard_normal(t.size)
    fit = fit_sine(t, y, lines)
    for k in range(lines.size):
        err = fit.line_phasors[k] - true[k]
        assert abs(err) < 5 * np.sqrt(np.trace(fit.line_covariances[k]))
        assert abs(err) < 1e-3


def _coverage_records(seeds):
    procedure = default_procedure()
    outcome = []
    for seed in seeds:
        core = FakeDeviceCore.from_procedure(procedure, seed)
        with dwell_experiment(procedure, CoreRig(core)) as exp:
            measured = exp.measure_multisine(INITIAL)
            measured += exp.measure_multisine([0.85, 0.97, 1.03, 6.1, 18.0])
            block = core.read_buffer(0, core.buffer_length)
        truth = core.true_response(np.array([m.omega_rad_s for m in measured]))
        outcome.append((measured, truth, float(np.max(np.abs(block.force))), core.force_noise_n))
    return outcome


@pytest.mark.slow
def test_multisine_lines_cover_the_truth_like_single_sines():
    """Truth inside the bound for >= 99% of lines (the single sine's coverage test), 6 seeds x 20 lines."""
    inside, total = 0, 0
    for measured, truth, peak, force_noise in _coverage_records(range(1, 7)):
        err = np.abs(np.array([m.response for m in measured]) - truth)
        bound = np.array([m.bound for m in measured])
        inside += int(np.sum(err <= bound))
        total += err.size
        assert peak <= 1.0 + 6 * force_noise  # the peak of the sum, not each line, is limited
        assert np.all(bound < 20 * np.abs(truth) + 1.0)  # informative, not a blanket bound
    assert inside / total >= 0.99, f"{inside}/{total} lines inside their bounds"


@pytest.mark.slow
def test_a_record_costs_one_settling_not_one_per_line():
    procedure = default_procedure()
    core = FakeDeviceCore.from_procedure(procedure, 2)
    with dwell_experiment(procedure, CoreRig(core)) as exp:
        record = exp.measure_multisine(INITIAL)
        record_s = exp.rig_s
        assert exp.n_measured == len(INITIAL)
    single_core = FakeDeviceCore.from_procedure(procedure, 2)
    with dwell_experiment(procedure, CoreRig(single_core)) as exp:
        for w in INITIAL:
            exp.measure(w)
        single_s = exp.rig_s
    assert sum(m.rig_s for m in record) == pytest.approx(record_s)
    assert record_s < 0.25 * single_s


def test_coloured_noise_during_a_multisine_follows_the_profile():
    procedure = default_procedure()
    core = FakeDeviceCore.from_procedure(procedure, 4)
    core.begin_measurement(0)
    core.set_sample_rate(20.0)
    core.set_multisine([1.0, 10.0], [0.0, 0.0], [0.0, 0.0])  # no force: the response is noise only
    core.capture(16384)
    noise = core.read_buffer(0, 16384).response
    spectrum = np.abs(np.fft.rfft(noise)) ** 2 / noise.size
    omega = 2 * np.pi * np.fft.rfftfreq(noise.size, 1 / 20.0)
    profile = noise_bound_function("fully_damped", beam_parameters())
    for w in (0.5, 3.0, 20.0):
        near = np.abs(omega / w - 1) < 0.05
        assert np.mean(spectrum[near]) == pytest.approx(float(profile(np.array([w]))[0]) ** 2, rel=0.25)


def test_dwell_signal_key_defaults_to_sine_and_refuses_single_sine_exciters(tmp_path):
    text = Path("setmem_hil/procedures/beam_6_3_2.toml").read_text() if Path("setmem_hil/procedures/beam_6_3_2.toml").exists() else None
    base = text or procedure_text(default_procedure())
    assert parse_procedure_text(base).dwell_signal == "sine"
    multisine = parse_procedure_text(base + '\n[dwell]\nsignal = "multisine"\n')
    assert multisine.dwell_signal == "multisine"
    assert parse_procedure_text(procedure_text(multisine)).dwell_signal == "multisine"
    serial = base.replace('kind = "sim"', 'kind = "serial-loopback"') + '\n[dwell]\nsignal = "multisine"\n'
    with pytest.raises(ProcedureError, match=r"\[dwell\] key 'signal'.*single sines"):
        parse_procedure_text(serial)
    with pytest.raises(ProcedureError, match=r"\[dwell\].*signal"):
        parse_procedure_text(base + '\n[dwell]\nsignal = "chirp"\n')


class _Recording(H.ForwardingExperiment):
    """Counts how the campaign asks for measurements (single dwells or records)."""

    def __init__(self, inner):
        super().__init__(inner)
        self.records, self.singles = [], []

    def update_model(self, model):
        self.inner.update_model(model)

    def measure(self, w):
        self.singles.append(w)
        return self.inner.measure(w)

    def measure_multisine(self, ws):
        self.records.append(list(ws))
        return self.inner.measure_multisine(ws)

    def close(self):
        self.inner.close()


def _cheap(signal: str, per_iteration: int = 2, kind: str = "sim"):
    text = H.cheap_procedure_text(2) + f"\nper_iteration = {per_iteration}\n\n[dwell]\nsignal = \"{signal}\"\n"
    if kind != "sim":
        text = text.replace('seed = 3\n', f'seed = 3\n\n[backend]\nkind = "{kind}"\n\n[safety]\nmax_amplitude_n = 1.0\nomega_min_rad_s = 0.05\nomega_max_rad_s = 2000.0\nmax_dwell_s = 3600.0\n', 1)
    return parse_procedure_text(text)


@pytest.mark.slow  # two campaigns end to end (85 s); the batching's parts are unit-tested here
def test_campaign_measures_initial_points_and_each_batch_in_one_record(monkeypatch):
    H.install_fast_analysis(monkeypatch)
    p = _cheap("multisine")
    with open_experiment(p, p.seed) as inner:
        exp = _Recording(inner)
        summary = run_campaign(p, exp, seed=p.seed)
    assert exp.records[0] == list(p.initial_omegas_rad_s)
    assert exp.singles == []
    assert all(len(r) == 2 for r in exp.records[1:]) and len(exp.records) == 2
    assert summary.experiments_added == 2
    # the sim backend's lines carry less force than a unit sine: larger bounds than sine dwells
    sine = _cheap("sine")
    with open_experiment(sine, sine.seed) as inner:
        single = _Recording(inner)
        run_campaign(sine, single, seed=sine.seed)
    assert single.records == [] and single.singles[:15] == list(p.initial_omegas_rad_s)


def test_sim_backend_lines_carry_their_force_share():
    p = dataclasses.replace(default_procedure(), dwell_signal="multisine")
    with open_experiment(p, 1) as exp:
        record = exp.measure_multisine(INITIAL)
        truth = exp.truth.frequency_response(np.array(INITIAL))
    with open_experiment(default_procedure(), 1) as exp:
        singles = exp.measure_many(INITIAL)
    ratio = np.array([r.bound - s.bound for r, s in zip(record, singles)]) / np.array(
        [noise_bound_function("fully_damped", beam_parameters())(np.array([w]))[0] for w in INITIAL])
    assert np.all(ratio > 1.0)  # each line's noise bound is R / a_k - R, a_k < 1 N
    assert np.allclose(ratio, ratio[0])  # equal amplitudes: the same factor for every line
    assert all(abs(m.response - g) <= m.bound for m, g in zip(record, truth))


class _Interrupting(_Recording):
    """Raises KeyboardInterrupt on its ``interrupt_at``-th dwell (a record or a single sine)."""

    def __init__(self, inner, interrupt_at):
        super().__init__(inner)
        self.interrupt_at = interrupt_at
        self.closed = False

    def _tick(self):
        if len(self.records) + len(self.singles) + 1 == self.interrupt_at:
            raise KeyboardInterrupt

    def measure(self, w):
        self._tick()
        return super().measure(w)

    def measure_multisine(self, ws):
        self._tick()
        return super().measure_multisine(ws)

    def close(self):
        self.closed = True
        super().close()


def _strip(rows):
    return [(r["seq"], r["iteration"], r["role"], r["omega_rad_s"], r["re"], r["im"], r["bound"]) for r in rows]


@pytest.mark.slow
@pytest.mark.parametrize("stop", ["record", "journal"])
def test_resumed_multisine_campaign_equals_the_uninterrupted_one(tmp_path, monkeypatch, capsys, stop):
    """Kill at the first dwell after the initial record (time-domain backend), or while the initial
    record's lines are being journaled; the resumed run stores exactly the uninterrupted run's
    measurements."""
    H.install_fast_analysis(monkeypatch)
    proc = tmp_path / "ms.toml"
    proc.write_text(procedure_text(_cheap("multisine", kind="time-domain")))
    p = load_procedure(proc)
    ref_journal = Journal.create(tmp_path / "ref" / "journal.sqlite", procedure_text=p.source_text, procedure_name=p.name,
                                 seed=p.seed, software_version="ref", backend=p.backend.kind, strategy="mu")
    with open_experiment(p, p.seed) as inner:
        run_campaign(p, _Recording(inner), ref_journal)
    ref_rows = ref_journal.measurement_rows()
    ref_journal.close()
    assert len(ref_rows) == 17

    import setmem_hil.cli.commands.run as run_cmd

    real_open = run_cmd.open_backend
    made = []
    if stop == "record":
        monkeypatch.setattr(run_cmd, "open_backend", lambda q, s: made.append(_Interrupting(real_open(q, s), 2 if not made else None)) or made[-1])
    else:
        real_add = Journal.add_measurement
        calls = {"n": 0}

        def add_then_die(self, m, **kw):
            calls["n"] += 1
            if calls["n"] == 8:  # the initial record's eighth line is never written
                raise KeyboardInterrupt
            return real_add(self, m, **kw)

        monkeypatch.setattr(Journal, "add_measurement", add_then_die)
    run_dir = tmp_path / "run"
    assert main(["run", str(proc), "--out", str(run_dir), "--quiet"]) == 130
    j = Journal.open(run_dir)
    stored = j.measurement_rows()
    assert _strip(stored) == _strip(ref_rows[: len(stored)]) and len(stored) == (15 if stop == "record" else 7)
    j.close()
    capsys.readouterr()
    monkeypatch.undo()
    H.install_fast_analysis(monkeypatch)
    assert main(["run", "--resume", str(run_dir), "--quiet"]) == 0
    j = Journal.open(run_dir)
    assert _strip(j.measurement_rows()) == _strip(ref_rows)
    j.close()
