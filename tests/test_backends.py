"""Backends factory: sim and serial-loopback from a procedure; the truth inside the bounds."""

import dataclasses
import socket

import numpy as np
import pytest

from setmem_hil.experiment_factory import open_experiment
from setmem_hil.errors import ProcedureError
from setmem_hil.io.procedure import BackendSettings, default_procedure
from setmem_hil.sim_backends.beam import beam_parameters
from setmem_hil.sim_backends.simulated_beam import SimulatedBeamExperiment

TRUTH8 = beam_parameters()
TRUTH3 = TRUTH8.truncated(3)


def _procedure(kind, **backend):
    p = default_procedure()
    return dataclasses.replace(p, backend=dataclasses.replace(p.backend, kind=kind, **backend))


def test_sim_backend_is_the_simulated_beam_with_the_procedure_settings():
    with open_experiment(_procedure("sim"), seed=4) as exp:
        got = [exp.measure(w) for w in (0.8, 6.0)]
    ref = SimulatedBeamExperiment(seed=4)
    assert got == [ref.measure(0.8), ref.measure(6.0)]


def test_serial_loopback_measures_the_model_within_bound_including_w1():
    from setmem_hil.model.experiment import Experiment

    proc = _procedure("serial-loopback")
    with open_experiment(proc, seed=3) as exp:
        assert isinstance(exp, Experiment)
        for w in proc.initial_omegas_rad_s[::3]:
            m = exp.measure(w)
            # what the identification needs: |g - g_3modes| <= R (eq. 3.7 with unmodelled modes)
            assert abs(m.response - TRUTH3.frequency_response(w)[0]) <= m.bound
            assert abs(m.response - TRUTH8.frequency_response(w)[0]) <= m.bound
            assert m.bound >= proc.weights.w1_magnitude(w)
        assert exp.n_measured == 5
        url = exp.rig.link.url
    port = int(url.rsplit(":", 1)[1])
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()


def test_serial_loopback_resume_reproduces_the_measurement():
    proc = _procedure("serial-loopback")
    with open_experiment(proc, seed=9) as a:
        first = [a.measure(w) for w in (1.5, 3.0)]
    with open_experiment(proc, seed=9) as b:
        b.n_measured = 1
        assert b.measure(3.0) == first[1]


def test_serial_loopback_with_faults_from_the_procedure():
    proc = _procedure(
        "serial-loopback",
        faults={"rate": 0.03, "seed": 4, "rates": {"disconnect": 0.005}},
        transport={"reply_timeout_s": 0.1},
    )
    with open_experiment(proc, seed=2) as exp:
        for w in (0.95, 5.9, 18.0):
            m = exp.measure(w)
            assert abs(m.response - TRUTH3.frequency_response(w)[0]) <= m.bound
        device = exp.rig.owned[0]
        injected = device.injected
        stats = exp.rig.link.stats
    assert sum(injected.values()) >= 3, injected
    assert stats["retries"] + stats["stale_discarded"] + exp.counters.get("discarded_dwell", 0) >= 1
    assert device.core.status().output_on is False


def test_bad_backend_settings_raise_procedure_errors():
    with pytest.raises(ProcedureError, match="kind"):
        open_experiment(dataclasses.replace(default_procedure(), backend=BackendSettings(kind="telepathy")), 1)
    with pytest.raises(ProcedureError, match="reply_timeout_s"):
        open_experiment(_procedure("serial-loopback", transport={"reply_timeout_s": -1}), 1)
    with pytest.raises(ProcedureError, match="learn_poles"):
        open_experiment(_procedure("serial-loopback", transport={"learn_poles": "yes"}), 1)
    with pytest.raises(ProcedureError, match="unknown kinds"):
        open_experiment(_procedure("serial-loopback", faults={"kinds": ["gremlin"]}), 1)


def test_dwell_options_from_the_transport_table():
    with open_experiment(_procedure("serial-loopback", transport={"learn_poles": True, "max_window_s": 60}), seed=1) as exp:
        assert exp.settings.learn_poles and exp.settings.max_window_s == 60.0
        m = exp.measure(0.95)
        assert abs(m.response - TRUTH8.frequency_response(0.95)[0]) <= m.bound
        assert exp.pole_tracker.estimate(0) is not None
