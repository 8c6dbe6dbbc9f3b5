"""A run directory in seconds (not collected: no ``test_`` prefix): one iteration whose box is the
beam's first three modes +- ``half_width`` and whose compensator is the thesis's H2 design for
it, on the stored 6.3.2 procedure (the simulated beam). For tests of what reads a finished run
(export, verify, report) where the campaign itself is not what is tested."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def one_iteration_run(run_dir: Path, half_width: float = 0.005, groups: tuple = (), measured: bool = False):
    """Write the run into ``run_dir``; returns ``(run_dir, box, analysis)``. ``measured``: the
    iteration's 15 points are in the journal too (the truth's response, bound 1 % of it + 1e-4)."""
    from setmem_hil.campaign.persistence import iteration_fields
    from setmem_hil.io.journal import JOURNAL_FILENAME, IterationRecord, Journal
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.robust.analysis import analyze_robust_performance
    from setmem_hil.sim_backends.beam import beam_parameters

    run_dir.mkdir(parents=True, exist_ok=True)
    procedure = load_procedure(REPO / "procedures" / "beam_6_3_2.toml")
    truth = beam_parameters().truncated(3).values
    low, high = truth * (1 - half_width), truth * (1 + half_width)
    box = IntervalModel(np.minimum(low, high), np.maximum(low, high))
    analysis = analyze_robust_performance(box, procedure.weights)
    doc = dict(k=1, n_points=15, mu_peak=analysis.mu_peak, safeguard="new-design", mu_peak_certified=analysis.mu_peak_certified,
               outputs=None, design="h2", floor_modes=(), model=box, plant=box, gain=None, analysis=analysis,
               identification=SimpleNamespace(embedding_gamma=np.zeros(3), mismatch_ratio=np.zeros(3), groups=groups))
    journal = Journal.create(run_dir / JOURNAL_FILENAME, procedure_text=procedure.source_text, procedure_name=procedure.name, seed=1,
                             software_version="test", backend=procedure.backend.kind, strategy="mu", design="h2")
    if measured:
        from setmem_hil.model.experiment import Measurement
        from setmem_hil.model.modal_model import ModalParameters

        w = np.geomspace(0.3, 30.0, 15)
        G = ModalParameters(truth).frequency_response(w)
        for omega, g in zip(w, G):
            journal.add_measurement(Measurement(float(omega), complex(g), 0.01 * abs(g) + 1e-4), iteration=0, role="initial")
    journal.add_iteration(IterationRecord(**iteration_fields(doc, None, 0.0)))
    journal.close()
    return run_dir, box, analysis
