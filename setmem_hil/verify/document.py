"""The document the verification plan defines (issue 63 item 6), stored as ``verify.json``.

:func:`verification_document` builds it from the plan's result; its file (name, the keys readers
rely on, the write into the verification's and the run's directory, the checked read the run's
report uses) is :mod:`setmem_hil.io.verification_file`. The command module only prints and exits.

Keys: ``verified``, ``uninformative_points``, ``iteration``, ``target`` (``kind``, ``identity``,
``fs_hz``, ``delay_samples``, ``checksum_read_back``), ``implemented_mu_bar``,
``continuous_mu_bar``, ``baseline_response_rms``, ``steps[]`` with their ``points[]``,
``performance`` (``measured``, ``claimed``), ``first_outside``, ``discrepancy``
(:mod:`setmem_hil.verify.closed_loop_discrepancy`) and ``figure`` (the PNG's path, where drawn).
"""

from __future__ import annotations

import json
import math

__all__ = ["verification_document"]


def verification_document(result, setup, target_procedure, record) -> dict:
    """The document of one verification: what was loaded, each step's points, the claim and what
    was measured against it, the first point outside and, where there is one, what it names."""
    from setmem_hil.verify.closed_loop_discrepancy import closed_loop_discrepancy

    identity = result.identity
    # the performance is claimed for the full gain only (a fraction of it rejects less)
    measured = max((p.weighted_performance for p in result.points if p.gain >= 1.0), default=None)
    first = result.first_outside
    claimed = None if not math.isfinite(result.implemented_mu_bar) else result.implemented_mu_bar
    doc = {
        "verified": bool(result.points) and first is None and len(result.steps) == len(setup.gains) and result.informative_in_every_step(),
        "uninformative_points": sum(not p.informative for p in result.points),
        "iteration": int(record.k),
        "target": {"kind": target_procedure.target.kind, "identity": None if identity is None else identity.text,
                   "fs_hz": setup.fs_hz, "delay_samples": setup.delay_samples,
                   "checksum_read_back": None if result.checksum is None else f"{result.checksum:08X}"},
        "implemented_mu_bar": claimed,
        "continuous_mu_bar": float(record.mu_peak),
        "baseline_response_rms": None if not math.isfinite(result.baseline_rms) else result.baseline_rms,
        "steps": result.steps,
        "performance": {"measured": measured, "claimed": claimed},
        "first_outside": None if first is None else first.to_document() | {"gain": first.gain},
        "discrepancy": None,
    }
    if first is not None:
        doc["discrepancy"] = closed_loop_discrepancy(result.points, setup)
    return json.loads(json.dumps(doc, default=float))
