"""Issue 5 and 8 end to end: a short campaign through every loopback transport, with faults
injected at a high rate (issue 8 soak). It must end with intervals that contain the fake
device's true parameters, an exciter at zero, and every injected fault survived."""

import dataclasses

import numpy as np
import pytest

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure import BackendSettings, Goal
from setmem_hil.io.procedure_file import load_procedure
from setmem_hil.sim_backends.beam import beam_parameters

PROCEDURES = {
    "serial-loopback": ("procedures/serial_loopback.toml", ("timeout", "corrupt", "truncate", "duplicate", "reorder", "disconnect")),
    "can-virtual": ("procedures/can_virtual.toml", ("timeout", "corrupt", "duplicate", "reorder", "error_frame", "bus_off")),
    "modbus-loopback": ("procedures/modbus_loopback.toml", ("timeout", "corrupt", "exception", "disconnect")),
}
DATA_KINDS = ("saturation", "nan", "inf", "timestamp_jump")


def fake_devices(experiment) -> list:
    """The fake devices behind an experiment's rig: every loopback rig lists them in ``rig.owned``."""
    rig = getattr(experiment, "rig", None)
    return [res for res in getattr(rig, "owned", ()) if hasattr(res, "core")]


def fake_device_cores(experiment):
    return [device.core for device in fake_devices(experiment)]


def injected_counts(experiment) -> dict:
    """Faults injected per kind, summed over the experiment's fake devices."""
    counts: dict[str, int] = {}
    for device in fake_devices(experiment):
        for kind, n in device.injected.items():
            counts[kind] = counts.get(kind, 0) + n
    return counts


@pytest.mark.slow
@pytest.mark.parametrize("backend", sorted(PROCEDURES))
def test_soak_campaign_with_faults_contains_truth_and_leaves_exciter_at_zero(backend, tmp_path, request):
    path, frame_kinds = PROCEDURES[backend]
    procedure = load_procedure(request.config.rootpath / path)
    faults = {"rate": 0.04, "kinds": list(frame_kinds + DATA_KINDS), "seed": 11}
    if "disconnect" in frame_kinds:
        faults["rates"] = {"disconnect": 0.01}  # a reconnect per ~100 frames is plenty
    procedure = dataclasses.replace(
        procedure,
        goal=Goal(mu_target=procedure.goal.mu_target, max_experiments=1),
        backend=dataclasses.replace(procedure.backend, faults=faults),
    )
    journal = Journal.create(tmp_path / "journal.sqlite", procedure_text=procedure.source_text, procedure_name=procedure.name,
                             seed=procedure.seed, software_version="test", backend=backend, strategy="mu")
    experiment = open_experiment(procedure, procedure.seed)
    try:
        # the transport under faults is what this soaks: the H2 loop keeps it at the cost it had
        summary = run_campaign(procedure, experiment, journal, design="h2")
        cores = fake_device_cores(experiment)
        counts = injected_counts(experiment)
    finally:
        experiment.close()
        journal.close()
    assert cores, "the test must see the fake device"
    for core in cores:
        status = core.status()
        assert not status.output_on and status.amplitude_n == 0.0
    assert sum(counts.values()) >= 3, counts  # faults were really injected, and survived
    print(f"\n{backend}: faults injected and survived {counts}")

    final = Journal.open(tmp_path / "journal.sqlite")
    try:
        last = final.iterations()[-1]
        n_measured = len(final.measurements())
    finally:
        final.close()
    truth = beam_parameters().truncated(3).values
    assert np.all((last.lower <= truth) & (truth <= last.upper))
    assert n_measured == len(procedure.initial_omegas_rad_s) + summary.to_document()["experiments_added"]
