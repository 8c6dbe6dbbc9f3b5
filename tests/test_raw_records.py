"""Raw records and re-processing (issue 39): ``RUN_DIR/raw.h5`` read with h5py alone (the layout
a lab's own tools see), ``setmem-hil reprocess`` agreeing with the journal on runs of the
simulated beam, a serial loopback rig and a time-domain multisine record, exit 3 naming the
measurement whose record was changed by one sample, exit 2 without raw records.

The truth: the journal's points (written by the campaign before any re-processing), the
samples the sensor delivered (read back from the file and compared with what the dwell used)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
from pathlib import Path

import h5py
import numpy as np
import pytest

from setmem_hil.campaign.runner import run_campaign
from setmem_hil.cli.main import main
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.journal import Journal
from setmem_hil.io.procedure_file import parse_procedure_text

HELPERS = Path(__file__).with_name("_campaign_helpers.py")


def helpers():
    spec = importlib.util.spec_from_file_location("_campaign_helpers", HELPERS)
    h = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(h)
    return h


def campaign(tmp_path, monkeypatch, backend: str, *, max_experiments: int = 1, multisine: bool = False):
    """A cheap campaign on ``backend`` into ``tmp_path`` (fast analysis stand-in); its journal's points."""
    h = helpers()
    h.install_fast_analysis(monkeypatch)
    text = h.cheap_procedure_text(max_experiments) + f'\n[backend]\nkind = "{backend}"\n'
    if backend != "sim":
        text += "\n[safety]\nmax_amplitude_n = 1.0\nomega_min_rad_s = 0.05\nomega_max_rad_s = 2000.0\nmax_dwell_s = 600.0\n"
    if multisine:
        text += '\n[dwell]\nsignal = "multisine"\n'
    procedure = parse_procedure_text(text, "cheap")
    journal = Journal.create(tmp_path / "journal.sqlite", procedure_text=text, procedure_name="cheap", seed=procedure.seed,
                             software_version="t", backend=backend, strategy="mu")
    with open_experiment(procedure, procedure.seed) as experiment:
        run_campaign(procedure, experiment, journal)
    points = journal.measurements()
    journal.close()
    return points


def record_files(run_dir: Path) -> dict[int, tuple[int, ...]]:
    """``{group name: seqs}`` as h5py reads the index."""
    with h5py.File(run_dir / "raw.h5", "r") as f:
        return {int(name): tuple(int(s) for s in f["measurements"][name].attrs["seqs"]) for name in f["measurements"]}


def test_simulated_run_keeps_every_phasor_and_reprocesses_identically(tmp_path, monkeypatch, capsys):
    points = campaign(tmp_path, monkeypatch, "sim")
    groups = record_files(tmp_path)
    assert sorted(s for seqs in groups.values() for s in seqs) == list(range(1, len(points) + 1))
    with h5py.File(tmp_path / "raw.h5", "r") as f:  # (no h5py object may outlive the block: it holds the linked file open)
        assert f["measurements/3"].attrs["kind"] == "simulated-phasor"
        assert f["measurements/3/phasor"][0, 0] == points[2].response  # the simulated phasor is the point, as read
    out = tmp_path / "reprocess.json"
    assert main(["reprocess", str(tmp_path), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["agree"] and len(doc["measurements"]) == len(points) and doc["first_difference_seq"] is None
    # one value of one record changed: exit 3 naming that measurement
    with h5py.File(tmp_path / "raw" / "3.h5", "r+") as f:
        f["phasor"][0, 0] = f["phasor"][0, 0] * (1 + 1e-6)
    capsys.readouterr()
    assert main(["reprocess", str(tmp_path)]) == 3
    assert "measurement seq 3 " in capsys.readouterr().err
    (tmp_path / "raw.h5").unlink()
    assert main(["reprocess", str(tmp_path)]) == 2
    assert "raw.h5" in capsys.readouterr().err


def test_serial_loopback_dwell_keeps_its_samples_and_one_changed_sample_is_named(tmp_path, monkeypatch, capsys):
    points = campaign(tmp_path, monkeypatch, "serial-loopback", max_experiments=0)
    groups = record_files(tmp_path)
    assert sorted(groups) == list(range(1, len(points) + 1))
    with h5py.File(tmp_path / "raw.h5", "r") as f:
        assert f["measurements/2"].attrs["kind"] == "sine-dwell"
        plan = json.loads(f["measurements/2"].attrs["plan"])
        t, force, response = (f[f"measurements/2/{name}"][()] for name in ("t_s", "force", "response"))
        assert t.size == force.size == response.size >= plan["n_samples"] // 2 and np.all(np.diff(t) > 0)
        # the samples are those of a sine at the dwell's frequency (independent least squares)
        w = points[1].omega_rad_s
        basis = np.column_stack([np.cos(w * t), np.sin(w * t), np.ones_like(t)])
        fit = np.linalg.lstsq(basis, force, rcond=None)[0]
        assert np.hypot(fit[0], fit[1]) == pytest.approx(1.0, rel=0.05)  # the 1 N drive
    assert main(["reprocess", str(tmp_path)]) == 0
    with h5py.File(tmp_path / "raw" / "2.h5", "r+") as f:
        y = f["response"][()]
        y[y.size // 2] += 10 * np.std(y)
        f["response"][...] = y
    capsys.readouterr()
    assert main(["reprocess", str(tmp_path)]) == 3
    assert "measurement seq 2 " in capsys.readouterr().err


@pytest.mark.slow
def test_time_domain_multisine_record_serves_several_measurements(tmp_path, monkeypatch):
    points = campaign(tmp_path, monkeypatch, "time-domain", max_experiments=0, multisine=True)
    groups = record_files(tmp_path)
    assert any(len(seqs) > 1 for seqs in groups.values())  # one record, several lines
    assert sorted(s for seqs in groups.values() for s in seqs) == list(range(1, len(points) + 1))
    with h5py.File(tmp_path / "raw.h5", "r") as f:
        assert json.loads(f["measurements"][str(min(groups))].attrs["plan"])["omegas_rad_s"] == [points[s - 1].omega_rad_s for s in groups[min(groups)]]
    assert main(["reprocess", str(tmp_path)]) == 0


def test_reprocess_of_a_run_without_raw_records_is_exit_2(tmp_path, capsys):
    Journal.create(tmp_path / "journal.sqlite", procedure_text="x", procedure_name="old", seed=1, software_version="t",
                   backend="sim", strategy="mu").close()
    assert main(["reprocess", str(tmp_path)]) == 2
    assert "no raw records" in capsys.readouterr().err


def test_a_committed_measurement_without_its_record_is_exit_2_naming_it(tmp_path, monkeypatch, capsys):
    campaign(tmp_path, monkeypatch, "sim", max_experiments=0)
    (tmp_path / "raw" / "4.h5").unlink()
    from setmem_hil.io.raw_store import RawStore

    RawStore(tmp_path).rebuild_index()
    assert main(["reprocess", str(tmp_path)]) == 2
    assert "no raw record for measurement 4" in capsys.readouterr().err


def test_raw_store_round_trips_datasets_and_settings_exactly(tmp_path):
    from setmem_hil.io.raw_store import RawStore, read_raw_records
    from setmem_hil.model.experiment import RawRecord

    rng = np.random.default_rng(5)
    record = RawRecord("toy", {"codes": rng.integers(-128, 128, 5000).astype(np.int8), "t_s": np.cumsum(rng.uniform(size=3000)),
                               "readings": rng.normal(size=40) + 1j * rng.normal(size=40)},
                       {"scale_v": 0.1 / 3, "name": "CH1", "settings": {"tau_s": [0.1, 0.3], "range": None}})
    RawStore(tmp_path).write((7, 8, 9), record)
    (back,) = read_raw_records(tmp_path)
    assert back.seqs == (7, 8, 9) and back.record.kind == "toy" and back.record.attrs == record.attrs
    for name, data in record.datasets.items():
        assert back.record.datasets[name].dtype == data.dtype
        np.testing.assert_array_equal(back.record.datasets[name], data)
    with h5py.File(tmp_path / "raw" / "7.h5", "r") as f:
        assert f["codes"].compression == "gzip"  # large arrays compressed
    assert dataclasses.is_dataclass(back)
