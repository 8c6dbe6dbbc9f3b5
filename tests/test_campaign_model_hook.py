"""The campaign tells the experiment every identified model (``update_model``, issue 5), and a
resumed campaign still reproduces the uninterrupted one exactly with a sine-dwell experiment
whose transient fit depends on that model."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.experiment_factory import dwell_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.model.modal_model import IntervalModel
from setmem_hil.io.procedure_file import load_procedure
from setmem_hil.sim_backends.core_rig import CoreRig
from setmem_hil.sim_backends.fake_device_core import FakeDeviceCore

_spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)


class RecordingExperiment(H.ForwardingExperiment):
    """Forwards to ``inner`` and records ``update_model`` calls; KeyboardInterrupt at dwell ``interrupt_at``."""

    def __init__(self, inner, interrupt_at=None):
        super().__init__(inner)
        self.interrupt_at = interrupt_at
        self.calls = 0
        self.models: list[IntervalModel] = []
        self.measures_before_update: list[int] = []

    def __getattr__(self, name):  # total_bound only when the inner experiment has it
        if name == "total_bound":
            return getattr(self.inner, name)
        raise AttributeError(name)

    def measure(self, omega_rad_s):
        self.calls += 1
        if self.calls == self.interrupt_at:
            raise KeyboardInterrupt
        return self.inner.measure(omega_rad_s)

    def update_model(self, model):
        self.models.append(model)
        self.measures_before_update.append(self.calls)
        forward = getattr(self.inner, "update_model", None)
        if forward is not None:
            forward(model)


def _procedure(tmp_path, max_experiments=2):
    path = tmp_path / "cheap.toml"
    path.write_text(H.cheap_procedure_text(max_experiments))
    return load_procedure(path)


def _journal(path, p):
    return Journal.create(path, procedure_text=p.source_text, procedure_name=p.name, seed=p.seed,
                          software_version="test", backend="core-rig", strategy="mu")


def _dwell(p, seed):
    return dwell_experiment(p, CoreRig(FakeDeviceCore.from_procedure(p, seed)))


def test_hook_receives_each_iterations_model(tmp_path, monkeypatch):
    H.install_fast_analysis(monkeypatch)
    p = _procedure(tmp_path, max_experiments=2)
    exp = RecordingExperiment(H.simulated(p, p.seed))  # the simulated beam has no update_model itself
    j = _journal(tmp_path / "j.sqlite", p)
    summary = run_campaign(p, exp, j)
    its = j.iterations()
    j.close()
    assert len(its) == len(summary.iterations) == 3  # initial identification + one per added dwell
    assert len(exp.models) == len(its)
    for model, rec in zip(exp.models, its):  # exactly the bounds the journal stores
        np.testing.assert_array_equal(model.lower, rec.lower)
        np.testing.assert_array_equal(model.upper, rec.upper)
    # called after the identification of the data measured so far, before the next dwell
    assert exp.measures_before_update == [rec.n_points for rec in its]
    # the models narrow (eq. 5.4-5.5): later dwells really get new pole bands
    assert np.all(exp.models[-1].width <= exp.models[0].width + 1e-15)
    assert np.any(exp.models[-1].width < exp.models[0].width)


def test_resumed_core_rig_campaign_reproduces_uninterrupted(tmp_path, monkeypatch):
    H.install_fast_analysis(monkeypatch)
    p = _procedure(tmp_path, max_experiments=2)
    seed = 5

    ref_exp = RecordingExperiment(_dwell(p, seed))
    ref = _journal(tmp_path / "ref.sqlite", p)
    run_campaign(p, ref_exp, ref)
    ref_ms, ref_its = ref.measurements(), ref.iterations()
    ref.close()
    assert len(ref_ms) == 17

    # the hook matters: the same added dwells measured with the prior's poles differ
    prior_exp = _dwell(p, seed)
    prior_exp.n_measured = 15
    with_prior = prior_exp.measure(ref_ms[15].omega_rad_s)
    assert (with_prior.response, with_prior.bound) != (ref_ms[15].response, ref_ms[15].bound)

    # interrupted at the second added dwell (after the model of iteration 2 was set), resumed
    path = tmp_path / "run.sqlite"
    j = _journal(path, p)
    first = RecordingExperiment(_dwell(p, seed), interrupt_at=17)
    with pytest.raises(KeyboardInterrupt):
        run_campaign(p, first, j)
    j.close()
    j = Journal.open(path)
    assert j.measurements() == ref_ms[:16]
    second = RecordingExperiment(_dwell(p, seed))
    run_campaign(p, second, j)
    got_ms, got_its = j.measurements(), j.iterations()
    j.close()
    assert second.calls == 1  # only the missing dwell was measured
    assert got_ms == ref_ms
    assert [(r.k, r.next_omega) for r in got_its] == [(r.k, r.next_omega) for r in ref_its]
    # the replay made the same update_model calls as the uninterrupted run
    assert len(second.models) == len(ref_exp.models)
    for a, b in zip(second.models, ref_exp.models):
        np.testing.assert_array_equal(a.lower, b.lower)
        np.testing.assert_array_equal(a.upper, b.upper)
