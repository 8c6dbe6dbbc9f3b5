"""What the live view shows, read from the journal (one truth for every viewer and reload)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from setmem_hil.io.journal import read_snapshot
from setmem_hil.model.modal_model import IntervalModel

__all__ = ["journal_state"]

BAND_POINTS = 300


def _num(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _model_band(rec, omega_lo: float, omega_hi: float) -> dict:
    """|G| range of the current interval model over a frequency grid: the 3^p corners are too
    many, so the envelope of the thesis's Table 6-6 samples plus the midpoint (an illustration,
    as in the report, not a bound)."""
    from setmem_hil.report.figures import table_6_6_offsets

    model = IntervalModel(rec.lower, rec.upper)
    if not (np.all(np.isfinite(model.lower)) and np.all(np.isfinite(model.upper))):
        return {}
    w = np.geomspace(omega_lo, omega_hi, BAND_POINTS)
    mags = np.array([np.abs(model.sample(x).frequency_response(w)) for x in table_6_6_offsets(model.n_modes)])
    return {"omega": w.tolist(), "lo": mags.min(axis=0).tolist(), "hi": mags.max(axis=0).tolist(),
            "mid": np.abs(model.midpoint.frequency_response(w)).tolist()}


def _output_names(info: dict, last) -> list[str]:
    """Every output's name, the control output first (several sensors, issue 25; one sensor:
    one name): from the last iteration, or from the procedure before the first one."""
    if last is not None and last.outputs:
        return list(last.outputs["names"])
    text = info.get("procedure_text")
    if not text:
        return []
    from setmem_hil.errors import ProcedureError
    from setmem_hil.io.procedure_file import parse_procedure_text

    try:
        return list(parse_procedure_text(text, "stored procedure").backend.output_order())
    except ProcedureError:  # a procedure of another version: the names are only a label
        return []


def _run_rig_s(rows: list) -> float | None:
    """The run's rig time: the sum of its measurements' (None when the backend reported none)."""
    times = [r["rig_s"] for r in rows if r["rig_s"] is not None]
    return float(sum(times)) if times else (0.0 if not rows else None)


def _run_elapsed_s(info: dict) -> float | None:
    """Wall time from the run's start to its end (a finished run) or to now (issue 40: a viewer of
    a finished run showed its own uptime instead)."""
    from datetime import datetime, timezone

    try:
        start = datetime.fromisoformat(info["created_utc"])
        end = datetime.fromisoformat(info["finished_utc"]) if info.get("finished") and info.get("finished_utc") else datetime.now(timezone.utc)
    except (KeyError, TypeError, ValueError):
        return None
    return max(0.0, (end - start).total_seconds())


def journal_state(run_dir: str | Path, live: dict | None = None) -> dict:
    """The API's state document (``GET /api/state``); ``live`` adds what only the running process
    knows (status from the buttons, the current dwell)."""
    live = dict(live or {})
    snap = read_snapshot(run_dir)
    info, rows, iterations, events = snap.info, snap.rows, snap.iterations, snap.events
    kinds = [e["kind"] for e in events]
    if info["finished"]:
        status = "finished"
    elif live.get("status"):
        status = live["status"]
    elif kinds and kinds[-1] in ("interrupted", "aborted", "device-fault", "error"):
        status = "aborted"
    else:
        status = "running"
    last = iterations[-1] if iterations else None
    omegas = [r["omega_rad_s"] for r in rows]
    band = _model_band(last, min(omegas) / 2, max(omegas) * 2) if last is not None and omegas else {}
    started = info.get("created_utc")
    return {
        "status": status,
        "procedure": info.get("procedure_name"),
        "backend": info.get("backend"),
        "started_utc": started,
        "iteration": last.k if last else 0,
        "n_points": len(rows),
        "mu_peak": _num(last.mu_peak) if last else None,
        "design": (last.design or "h2") if last else None,
        "rig_s": live.get("rig_s") if live.get("rig_s") is not None else _run_rig_s(rows),
        "run_elapsed_s": _run_elapsed_s(info),
        "dwell": live.get("dwell"),
        "measurements": [{"omega": r["omega_rad_s"], "re": r["re"], "im": r["im"], "bound": r["bound"], "role": r["role"],
                          "iteration": r["iteration"], "others": json.loads(r["others"]) if r["others"] else []} for r in rows],
        "outputs": _output_names(info, last),
        "iterations": [{"k": it.k, "n_points": it.n_points, "mu_peak": _num(it.mu_peak), "mu_peak_omega": _num(it.mu_peak_omega),
                        "next_omega": _num(it.next_omega), "omega": [float(w) for w in it.omega],
                        "mu": [_num(m) for m in it.mu], "lower": it.lower.tolist(), "upper": it.upper.tolist(),
                        "sensitivities": it.sensitivities, "outputs": it.outputs, "design": it.design or "h2",
                        "floor_modes": list(it.floor_modes or ())} for it in iterations],
        "model_band": band,
        "events": [{"utc": e["utc"], "kind": e["kind"], "message": e["message"][:300]}
                   for e in events if e["kind"] != "exact-resolve"][-50:],  # that one is data for figure 6-14
        "summary": info.get("summary"),
    }
