"""The compensator a campaign kept, read back from its journal (export, validation).

The journal stores each iteration's compensator after the safeguard of eq. 5.12 (so a
"previous-controller" iteration holds the controller actually kept). Journals written before it
did are upgraded on open with an empty column; their compensator is designed again from the
stored intervals (H2 is deterministic) where the iteration kept a new design.
"""

from __future__ import annotations

from setmem_hil.errors import InputFormatError

__all__ = ["kept_controller", "kept_box", "stored_procedure"]


def _error(where: str, problem: str) -> InputFormatError:
    return InputFormatError(where, "", problem)


def kept_controller(run_dir: str, iteration: int | None, command: str = "setmem-hil controller"):
    """``(record, StateSpace)`` of the compensator iteration K (or the last) kept."""
    from setmem_hil.io.journal import Journal
    from setmem_hil.robust.controller_forms import statespace_from_lists

    with Journal.open(run_dir) as journal:
        records = journal.iterations()
        procedure_text = journal.run_info()["procedure_text"]
    if not records:
        raise _error(str(run_dir), "the run has no iteration yet: no compensator was designed (let the campaign reach its first analysis)")
    if iteration is None:
        record = records[-1]
    else:
        found = [r for r in records if r.k == iteration]
        if not found:
            raise _error(command, f"--iteration {iteration}: {run_dir} holds iterations 1-{records[-1].k}")
        record = found[0]
    if record.controller is not None:
        return record, statespace_from_lists(record.controller)
    return record, designed_again(run_dir, record, procedure_text)


def designed_again(run_dir: str, record, procedure_text: str):
    """A journal from before compensators were stored: the H2 design of the stored intervals."""
    if record.safeguard != "new-design":
        raise _error(str(run_dir), f"iteration {record.k} kept an earlier compensator (safeguard {record.safeguard!r}) and the "
                     "journal predates stored compensators: export an iteration that kept a new design (--iteration)")
    from setmem_hil.io.procedure_file import parse_procedure_text
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.robust.analysis import analyze_robust_performance
    from setmem_hil.robust.controller_forms import statespace_from_lists
    from setmem_hil.campaign.runner import controller_matrices

    weights = parse_procedure_text(procedure_text, f"{run_dir} (stored procedure)").weights
    analysis = analyze_robust_performance(IntervalModel(record.lower, record.upper), weights)
    return statespace_from_lists(controller_matrices(analysis.controller))


def kept_box(record):
    """``(IntervalModel, gain)`` the iteration's compensator was analysed on: the stored box, or
    with calibration scales the sensors' box and the common gain interval."""
    import numpy as np

    from setmem_hil.model.modal_model import IntervalModel

    if record.common_gain:
        doc = record.common_gain
        return IntervalModel(np.asarray(doc["lower"], dtype=float), np.asarray(doc["upper"], dtype=float)), tuple(doc["gain"])
    return IntervalModel(record.lower, record.upper), None


def stored_procedure(run_dir: str):
    """The run's stored procedure (the text its journal keeps), parsed."""
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import parse_procedure_text

    with Journal.open(run_dir) as journal:
        text = journal.run_info()["procedure_text"]
    return parse_procedure_text(text, f"{run_dir} (stored procedure)")
