"""The run report: ``setmem-hil report DIR`` writes ``DIR/report.html`` with PNG figures.

Plain HTML (no JavaScript, nothing fetched from the network); the PNGs sit next to it, so the
directory can be zipped or copied as is. Contents, all read from the run's journal:

* the run: procedure name and description, seed, software version, backend, strategy, state,
  outcome (the summary);
* figure 6-12: peak mu-bar per iteration labelled with the chosen frequency;
* figure 6-13: mu-bar against frequency per iteration;
* figure 6-14: estimated improvement against candidate frequency, per iteration;
* the data with the model's uncertainty as the nine sample transfer functions of Table 6-6
  and their pole-zero pattern (figures 6-9/6-10, 6-15/6-16, 6-18/6-19, 6-23/6-24), after the
  initial data, the first two added points and at the end;
* per iteration, the parameter intervals and mu-sensitivities (appendix B tables);
* the discrepancy results, when a check was run; the events (faults, interruptions, resumes);
* the measurements and the procedure text.
"""

from __future__ import annotations

import html
import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from setmem_hil.errors import InputFormatError, SetmemError
from setmem_hil.io.atomic_file import write_text_atomic
from setmem_hil.io.journal import IterationRecord, journal_path, read_snapshot
from setmem_hil.model.modal_model import PARAM_NAMES, IntervalModel

__all__ = ["write_report", "REPORT_FILENAME", "FIGURE_FILES", "figure_iterations"]

REPORT_FILENAME = "report.html"
FIGURE_FILES = {
    "mu_peak": "fig_mu_peak.png",
    "mu_vs_omega": "fig_mu_vs_omega.png",
    "improvement": "fig_improvement.png",
    "intervals": "fig_intervals.png",
}
EXACT_RATIO_FIGURE = "fig_exact_ratio.png"
"""Drawn where the journal holds witness notes with per-mode ratios (runs since issue 62 item 6)."""


def _exact_resolves(events) -> dict:
    """``k -> (omega, improvement)`` from the runner's exact-resolve events (none in older journals)."""
    out = {}
    for e in events:
        if e["kind"] == "exact-resolve":
            try:
                doc = json.loads(e["message"])
                out[int(doc["k"])] = (np.array(doc["omega_rad_s"], dtype=float),
                                      np.array([np.nan if v is None else v for v in doc["improvement"]], dtype=float))
            except (ValueError, KeyError, TypeError):  # a malformed event is shown in the events table, not plotted
                continue
    return out


def _witnesses(events) -> dict:
    """``k -> witness note`` (issue 62: ``fits``, ``misfit``, ``reach_ratio_max``) from the plan's
    witness events (none in older journals)."""
    out = {}
    for e in events:
        if e["kind"] == "witness":
            try:
                doc = json.loads(e["message"])
                out[int(doc["k"])] = doc
            except (ValueError, KeyError, TypeError):
                continue
    return out


def _shown_event(e) -> list | None:
    """An events-table row: exact re-solves are figure 6-14's data, not news; a witness note is
    news only where no point was found to fit (its warning)."""
    if e["kind"] == "exact-resolve":
        return None
    if e["kind"] == "witness":
        try:
            warning = json.loads(e["message"]).get("warning")
        except (ValueError, AttributeError):
            warning = e["message"]
        return None if not warning else [e["utc"], e["kind"], warning]
    return [e["utc"], e["kind"], e["message"]]


def figure_iterations(iterations: Sequence[IterationRecord]) -> list[int]:
    """Iterations that get sample-transfer-function and pole-zero figures.

    As in the thesis: after the initial data (k = 1), after the first and second added points
    (k = 2, 3) and the final model.
    """
    ks = [rec.k for rec in iterations]
    chosen = [k for k in ks if k <= 3]
    if ks and ks[-1] not in chosen:
        chosen.append(ks[-1])
    return chosen


def _stored_procedure(procedure_text: str):
    """The run's stored procedure, parsed once for the whole report; ``None`` when it does not
    parse (an old or hand-edited journal: the report still renders, with defaults)."""
    try:
        from setmem_hil.io.procedure_file import parse_procedure_text

        return parse_procedure_text(procedure_text, "<journal>")
    except SetmemError:
        return None


def _mu_target(procedure) -> float:
    return 1.0 if procedure is None else float(procedure.goal.mu_target)


def _e(x: Any) -> str:
    return html.escape(str(x), quote=True)


def _num(x: Any, digits: int = 5) -> str:
    if x is None:
        return "-"
    x = float(x)
    if math.isnan(x):
        return "nan"
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return f"{x:.{digits}g}"


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], table_id: str, caption: str = "") -> str:
    out = [f'<table id="{_e(table_id)}">']
    if caption:
        out.append(f"<caption>{_e(caption)}</caption>")
    out.append("<thead><tr>" + "".join(f"<th>{_e(h)}</th>" for h in header) + "</tr></thead><tbody>")
    for row in rows:
        out.append("<tr>" + "".join(f"<td>{_e(c)}</td>" for c in row) + "</tr>")
    out.append("</tbody></table>")
    return "\n".join(out)


def _figure(src: str, caption: str, fig_id: str) -> str:
    return (f'<figure id="{_e(fig_id)}"><img src="{_e(src)}" alt="{_e(caption)}">'
            f"<figcaption>{_e(caption)}</figcaption></figure>")


def _after(iterations: Sequence[IterationRecord], k: int) -> str:
    """Thesis caption wording: "after initial data points" / "after applying a sinusoid at ..."."""
    if k == 1:
        return "after the initial data points"
    prev = next((r for r in iterations if r.k == k - 1), None)
    if prev is not None and prev.next_omega is not None:
        return f"after applying a sinusoid at {prev.next_omega:.4g} rad/s"
    return f"at iteration {k}"


def _interval_rows(rec: IterationRecord) -> list[list[str]]:
    rows = []
    for i in range(rec.lower.shape[0]):
        for j, name in enumerate(PARAM_NAMES):
            key = f"{name}_{i + 1}"
            lo, hi = rec.lower[i, j], rec.upper[i, j]
            sens = rec.sensitivities.get(key)
            rows.append([key, _num(lo), _num(hi), "fixed" if lo == hi else _num(hi - lo), "-" if sens is None else _num(sens)])
    return rows


def write_report(run_dir: str | os.PathLike) -> Path:
    """Write ``run_dir/report.html`` and its figures; returns the HTML path.

    Works on finished and unfinished runs (it shows what the journal holds).

    Raises
    ------
    InputFormatError
        If ``run_dir`` holds no journal.
    """
    jp = journal_path(run_dir)
    if not jp.is_file():  # never the parent's journal (issue 40): a missing directory is named as given
        raise InputFormatError(str(run_dir), "", "no journal here (expected a run directory holding journal.sqlite)")
    out_dir = jp.parent
    run = read_snapshot(out_dir)
    info, its = run.info, run.iterations
    procedure = _stored_procedure(info["procedure_text"])
    target = _mu_target(procedure)
    rig_by_iteration: dict[int, float] = {}
    for row in run.rows:
        rig_by_iteration[int(row["iteration"])] = rig_by_iteration.get(int(row["iteration"]), 0.0) + float(row.get("rig_s") or 0.0)
    parts = [_run_section(run, target, rig_by_iteration), *_progress_section(its, target, run, rig_by_iteration, out_dir),
             *_uncertainty_section(its, run, out_dir), *_intervals_section(its, run, procedure, out_dir)]
    if its and its[-1].outputs:
        parts += _sensors_section(its[-1])
    parts += _records_section(run, its, out_dir)
    title = f"setmem-hil report: {info['procedure_name']}"
    return write_text_atomic(out_dir / REPORT_FILENAME, _page(title, _description(procedure), "\n".join(parts)))


def _run_section(run, target: float, rig_by_iteration: dict[int, float]) -> str:
    """The run's facts: procedure, seed, versions, state, counts, rig time and the summary."""
    info, its = run.info, run.iterations
    summary = info.get("summary") or {}
    state = "finished" if info["finished"] else "not finished (resume with setmem-hil run --resume)"
    run_rows = [
        ["procedure", info["procedure_name"]],
        ["seed", info["seed"]],
        ["software version", info["software_version"]],
        ["backend", info["backend"]],
        ["strategy", info["strategy"]],
        ["started (UTC)", info["created_utc"]],
        ["state", state],
        ["measurements", len(run.measurements)],
        ["iterations", len(its)],
        ["goal", f"mu-bar < {target:g}"],
    ]
    run_rows.append(["rig time (device s)", f"{sum(rig_by_iteration.values()):.1f} "
                     f"(initial points {rig_by_iteration.get(0, 0.0):.1f})"])
    if its:
        run_rows.append(["last peak mu-bar", _num(its[-1].mu_peak)])
    for key in ("reached_goal", "stop_reason", "experiments_added", "final_mu_peak", "wall_s"):
        if key in summary:
            run_rows.append([key.replace("_", " "), summary[key] if not isinstance(summary[key], float) else _num(summary[key])])
    return "<h2 id='run'>Run</h2>" + _table(["item", "value"], run_rows, "table-run")


def _progress_section(its, target: float, run, rig_by_iteration: dict[int, float], out_dir: Path) -> list[str]:
    """Figures 6-12 to 6-14, the intervals' figure, the iterations' table and the delivered compensator."""
    from setmem_hil.report import figures as figs

    parts = ["<h2 id='progress'>Progress of the campaign</h2>"]
    if not its:
        return parts + ["<p>No iteration is stored yet.</p>"]
    figs.mu_peak_figure(its, target, out_dir / FIGURE_FILES["mu_peak"])
    parts.append(_figure(FIGURE_FILES["mu_peak"], "Peak mu-bar per iteration; each point is labelled with the frequency chosen for the next experiment (thesis figure 6-12).", "fig-mu-peak"))
    figs.mu_vs_frequency_figure(its, target, out_dir / FIGURE_FILES["mu_vs_omega"])
    parts.append(_figure(FIGURE_FILES["mu_vs_omega"], "mu-bar against frequency for each iteration (thesis figure 6-13).", "fig-mu-vs-omega"))
    figs.improvement_figure(its, out_dir / FIGURE_FILES["improvement"], exact=_exact_resolves(run.events))
    parts.append(_figure(FIGURE_FILES["improvement"], "Estimated improvement of mu-bar for each candidate frequency (line); "
                         "the best candidates re-identified exactly (circles) and the chosen one, the highest exact value "
                         "(star) (thesis figure 6-14).", "fig-improvement"))
    figs.interval_figure(its, out_dir / FIGURE_FILES["intervals"])
    parts.append(_figure(FIGURE_FILES["intervals"], "Parameter intervals per iteration: natural frequency, damping ratio and "
                         "residue of every mode shrinking as experiments are added.", "fig-intervals"))
    rows = [[r.k, r.n_points, _num(r.mu_peak), _certified_text(r), _num(r.mu_peak_omega, 4), _num(r.mu_lower_peak), _num(r.next_omega, 6),
             "-" if r.next_omega is None else _num(r.next_omega / (2 * math.pi), 5),
             r.safeguard, r.design or "h2", ", ".join(str(m) for m in r.floor_modes or ()) or "-",
             r.controller_order, f"{r.wall_s:.2f}", f"{rig_by_iteration.get(r.k, 0.0):.1f}"] for r in its]
    parts.append(_table(["k", "points", "peak mu-bar", "certified on the band", "at omega (rad/s)", "lower bound peak", "next omega (rad/s)",
                         "next (Hz)", "eq. 5.12 branch", "design", "floor modes", "controller order", "compute (s)", "rig (s)"],
                        rows, "table-iterations",
                        "Iterations (the numbers behind figure 6-12). 'certified on the band': mu-bar is proved "
                        "below the peak (within 1e-4; 3e-3 for the robust design) at every frequency of the analysis band, "
                        "not only at grid points, by that many frequency intervals; the campaign stops only on a certified "
                        "value. 'design': what made the compensator the safeguard kept (robust: tuned to the mixed-mu bound; "
                        "h2: the thesis). 'floor modes': modes whose box holds an undamped mode with zero residue, so that no "
                        "compensator can reach mu-bar < 1 until an experiment bounds a1 or b0 away from 0."))
    final = its[-1]
    if math.isfinite(final.mu_peak) and final.mu_peak > 0:
        parts.append(f"<p id='delivered'>Delivered compensator: iteration {final.k}, {html.escape(final.design or 'h2')} design, "
                     f"order {final.controller_order}, mu-bar {_num(final.mu_peak)}: margin {_num(1.0 / final.mu_peak)} "
                     "(the box could grow by that factor before robust performance is lost).</p>")
    return parts


def _uncertainty_section(its, run, out_dir: Path) -> list[str]:
    """Sample transfer functions and pole-zero patterns of the chosen iterations (Table 6-6)."""
    from setmem_hil.report import figures as figs

    parts = ["<h2 id='uncertainty'>Data and model uncertainty</h2>",
             "<p>Nine sample transfer functions from the parameter intervals (thesis Table 6-6: parameter value "
             "= midpoint + x (upper - midpoint)); they illustrate, but do not bound, the uncertainty. "
             "Points: the data used by the identification, with their error bounds.</p>"]
    for k in figure_iterations(its):
        rec = next(r for r in its if r.k == k)
        model = IntervalModel(rec.lower, rec.upper)
        after = _after(its, k)
        tf = f"fig_tf_k{k}.png"
        pz = f"fig_pz_k{k}.png"
        figs.sample_transfer_functions_figure(model, run.measurements[: rec.n_points], f"Sample transfer functions {after} (k = {k})", out_dir / tf)
        figs.pole_zero_figure(model, f"Open-loop pole-zero pattern {after} (k = {k})", out_dir / pz)
        parts.append(f"<h3>Iteration {k}: {_e(after)}</h3>")
        parts.append(_figure(tf, f"Transfer functions {after} ({rec.n_points} points).", f"fig-tf-k{k}"))
        parts.append(_figure(pz, f"Open-loop pole-zero pattern {after}.", f"fig-pz-k{k}"))
    return parts


def _identified_with(rec: IterationRecord, i: int) -> str:
    """How mode ``i`` was identified: alone (thesis chapter 3's split) or with the closely spaced
    modes of its group (issue 47); "-" where the journal predates recorded groups."""
    if rec.groups is None:
        return "-"
    group = next((g for g in rec.groups if i in g), None)
    return "alone" if group is None else "with modes " + " + ".join(str(m + 1) for m in group)


def _exact_ratio_cells(run, rec: IterationRecord, procedure) -> list[str]:
    """Per mode, the largest of its intervals' widths over the linearised exact feasible set's
    (``modes[i].exact_ratio`` of identify's RESULT.json, issue 47) and the parameter it is on, for
    the data the iteration was identified from with their recorded bounds; "-" where it is not
    computable (several outputs, a fixed parameter only, a linearised set that is empty)."""
    from setmem_hil.identification.exact_ratio import exact_ratios
    from setmem_hil.model.frequency_data import FrequencyData

    n_modes = np.asarray(rec.lower).shape[0]
    if procedure is None:
        return ["-"] * n_modes
    try:
        data = FrequencyData.from_measurements(run.measurements[: rec.n_points])
        box = procedure.prior.initial_bounds()
        if rec.outputs or not data.omega_rad_s.size or box.lower.shape != np.asarray(rec.lower).shape:
            return ["-"] * n_modes
        ratios = exact_ratios(data.omega_rad_s, data.response, data.bound, np.asarray(rec.lower), np.asarray(rec.upper),
                              box.lower, box.upper)
    except ValueError:
        return ["-"] * n_modes
    cells = []
    for ratio in ratios:
        if not ratio:
            cells.append("-")
            continue
        name = max(ratio, key=ratio.get)
        cells.append(f"{ratio[name]:.2f} ({name})")
    return cells


def _intervals_section(its, run, procedure, out_dir: Path | None = None) -> list[str]:
    """Appendix B's tables per iteration: bounds, widths, mu-sensitivities, and the conservatism per mode."""
    parts = ["<h2 id='intervals'>Parameter intervals and mu-sensitivities</h2>",
             "<p>Per iteration, as in the thesis's appendix B: the lower and upper bound of each parameter of "
             "G(s) = sum_i (b1_i s + b0_i) / (s^2 + a1_i s + a0_i) and its mu-sensitivity. Also the "
             "identification's conservatism (embedding gamma, mismatch ratio) per mode, and whether it was identified alone or "
             "with the closely spaced modes of its group (docs/closely-spaced-modes.md). For the last iteration, each mode's "
             "widest interval over the linearised exact feasible set's extent (1: at the data's limit; larger: where the "
             "method is conservative, thesis 3.6). Under each table, the iteration's witness (a parameter point checked to fit "
             "every point) and its widest interval over the witnesses' reach (points checked to fit: an upper bound of its width "
             "over the exact set's extent; issue 62).</p>"]
    witnesses = _witnesses(run.events)
    for n, rec in enumerate(its, start=1):
        parts.append(_table(["parameter", "lower bound", "upper bound", "width", "mu-sensitivity"], _interval_rows(rec),
                            f"table-intervals-k{rec.k}",
                            f"Table {n}: the lower bounds, upper bounds and mu-sensitivities {_after(its, rec.k)} (k = {rec.k}, {rec.n_points} points)."))
        cons = [[i + 1, _num(g), _num(m), _identified_with(rec, i)]
                for i, (g, m) in enumerate(zip(np.atleast_1d(rec.embedding_gamma), np.atleast_1d(rec.mismatch_ratio)))]
        if cons:
            header = ["mode", "embedding gamma", "mismatch ratio", "identified"]
            reach = witnesses.get(rec.k, {}).get("reach_ratio_per_mode")
            if reach is not None and len(reach) == len(cons):
                header.append("widest interval / witnesses' reach")
                for row, r in zip(cons, reach):
                    row.append("-" if r is None else f"{r:.3f}")
            if n == len(its):
                header.append("widest interval / exact set")
                for row, cell in zip(cons, _exact_ratio_cells(run, rec, procedure)):
                    row.append(cell)
            parts.append(_table(header, cons, f"table-conservatism-k{rec.k}"))
        if rec.k in witnesses:
            parts.append(f"<p class='witness' id='witness-k{rec.k}'>{_e(_witness_sentence(witnesses[rec.k]))}</p>")
    parts += _exact_ratio_figure(its, witnesses, out_dir)
    return parts


def _exact_ratio_figure(its, witnesses: dict, out_dir: Path | None) -> list[str]:
    """Each mode's widest interval over the witnesses' reach, per iteration (issue 62 item 6):
    the figure where a reader sees whether the box sits at the data's limit (1) or above it."""
    per_k = {k: doc.get("reach_ratio_per_mode") for k, doc in witnesses.items() if doc.get("reach_ratio_per_mode")}
    if out_dir is None or not per_k:
        return []
    from setmem_hil.report import figures as figs

    figs.exact_ratio_figure(per_k, out_dir / EXACT_RATIO_FIGURE)
    return [_figure(EXACT_RATIO_FIGURE, "Each mode's widest interval over the witnesses' reach, per iteration: "
                    "the reach is spanned by parameter points checked to fit every measured point, so the ratio is an "
                    "upper bound of the box's width over the exact feasible set's (1: the box is at the data's limit; "
                    "issue 62's goal: within 1.1).", "fig-exact-ratio")]


def _witness_sentence(doc: dict) -> str:
    if not doc.get("fits"):
        return doc.get("warning") or f"No parameter point of the box was found to fit every point (best misfit {doc.get('misfit')})."
    reach = doc.get("reach_ratio_max")
    tail = "" if reach is None else f"; widest interval / witnesses' reach {reach:.3f}"
    return f"Witness: misfit {doc['misfit']:.3f} (at most 1: fits every point){tail}."


def _records_section(run, its, out_dir: Path) -> list[str]:
    """Discrepancy checks, the validation, events, every measurement and the procedure's text."""
    parts = ["<h2 id='discrepancy'>Discrepancy checks</h2>"]
    if run.discrepancies:
        for n, (k, report) in enumerate(run.discrepancies, start=1):
            parts.append(_table(["item", "value"], _discrepancy_rows(report), f"table-discrepancy-{n}",
                                f"Discrepancy check at iteration {k} ({_after(its, k)})."))
    else:
        parts.append("<p>No discrepancy check was run.</p>")
    parts.append(_validation_section(out_dir))
    from setmem_hil.report.verification_section import verification_section

    parts.append(verification_section(out_dir))
    parts.append("<h2 id='events'>Events</h2>")
    shown = [row for row in (_shown_event(e) for e in run.events) if row is not None]
    parts.append(_table(["time (UTC)", "kind", "message"], shown, "table-events") if shown else "<p>None.</p>")
    parts.append("<h2 id='measurements'>Measurements</h2>")
    mrows = [[r["seq"], r["iteration"], r["role"], _num(r["omega_rad_s"], 6), _num(abs(complex(r["re"], r["im"]))),
              _num(math.degrees(math.atan2(r["im"], r["re"])), 4), _num(r["bound"]), r["utc"]] for r in run.rows]
    parts.append(_table(["#", "iteration", "role", "omega (rad/s)", "|G|", "phase (deg)", "bound", "time (UTC)"], mrows, "table-measurements"))
    parts.append("<h2 id='procedure'>Procedure</h2><pre>" + _e(run.info["procedure_text"]) + "</pre>")
    return parts


def _page(title: str, description: str, body: str) -> str:
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>
<style>
body {{ font-family: sans-serif; max-width: 1000px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }}
th, td {{ border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: right; }}
th {{ background: #eee; }} caption {{ text-align: left; font-style: italic; padding: 0.3em 0; }}
figure {{ margin: 1.5em 0; }} img {{ max-width: 100%; }} figcaption {{ font-style: italic; }}
pre {{ background: #f6f6f6; padding: 1em; overflow-x: auto; }}
</style></head>
<body>
<h1>{_e(title)}</h1>
<p>{_e(description)}</p>
{body}
</body></html>
"""


VALIDATION_FILENAME = "validate.json"


def _validation_section(out_dir: Path) -> str:
    """What ``setmem-hil validate`` found (when it wrote ``validate.json`` into the run directory)."""
    import json

    head = "<h2 id='validation'>Validation of the compensator</h2>"
    path = Path(out_dir) / VALIDATION_FILENAME
    if not path.is_file():
        return head + "<p>Not validated yet: <code>setmem-hil validate RUN_DIR</code> checks the kept compensator against the " \
                      "truth and plants sampled from the interval box.</p>"
    doc = json.loads(path.read_text(encoding="utf-8"))
    rows = [["iteration", doc["iteration"]], ["claimed mu-bar", _num(doc["claimed_mu_peak"])]]
    truth = doc.get("truth")
    if truth:
        rows += [["truth: closed loop", "stable" if truth["stable"] else "UNSTABLE"],
                 ["truth: peak |W2 S| + |W1 K S|", f"{_num(truth['rp_peak'])} at {_num(truth['rp_peak_omega'])} rad/s"]]
    samples = doc["samples"]
    rows += [["sampled plants", f"{samples['n']} ({samples['drawn']})"],
             ["worst sampled peak", f"{_num(samples['worst_rp_peak'])} at {_num(samples['worst_omega'])} rad/s"],
             ["plants violating the claim", samples["violations"]]]
    sim = doc.get("closed_loop_sim")
    if sim and sim.get("stable"):
        rows += [["closed-loop simulation", f"{_num(sim['measured'])} measured, {_num(sim['predicted'])} predicted at "
                                            f"{_num(sim['omega_rad_s'])} rad/s, {_num(sim['fs_hz'])} Hz"]]
    out = head + _table(["item", "value"], rows, "table-validation", "The exact one-plant test of robust performance "
                        "for the truth and for plants of the interval box (setmem-hil validate).")
    figure = Path(doc.get("figure") or "")
    if figure.is_file():
        try:
            src = str(figure.resolve().relative_to(Path(out_dir).resolve()))
        except ValueError:
            src = str(figure)
        out += _figure(src, "|W2 S| and |W1 K S| of the truth and of the worst sampled plant against 1.", "fig-validation")
    return out


def _discrepancy_rows(report: dict) -> list[list[str]]:
    """Key facts of a discrepancy report first (decision, effects, worst normalised residual
    before and after, disagreement bands), then any other item, shortened."""
    rows: list[list[str]] = []
    shown = set()
    if "decision" in report:
        rows.append(["decision", str(report["decision"])])
        shown.add("decision")
    if isinstance(report.get("effects"), list):
        names = [str(e.get("name", e)) if isinstance(e, dict) else str(e) for e in report["effects"]]
        rows.append(["effects found", ", ".join(names) or "none"])
        shown.add("effects")
    for key in ("before", "after"):
        part = report.get(key)
        if isinstance(part, dict) and "max_normalized_residual" in part:
            rows.append([f"worst normalised residual {key}", _num(part["max_normalized_residual"], 4)])
            shown.add(key)
    if "disagreement_bands" in report:
        bands = report["disagreement_bands"] or []
        text = ", ".join(f"{_num(b[0], 4)}-{_num(b[1], 4)} rad/s" if isinstance(b, (list, tuple)) and len(b) >= 2 else str(b) for b in bands)
        rows.append(["disagreement bands", text or "none"])
        shown.add("disagreement_bands")
    for key, value in report.items():
        if key in shown:
            continue
        text = value if isinstance(value, str) else json.dumps(value, default=str)
        rows.append([key, text if len(text) <= 300 else text[:297] + "..."])
    return rows


def _description(procedure) -> str:
    return "" if procedure is None else procedure.description


def _certified_text(record) -> str:
    """``yes (N intervals)``, ``NO`` or ``-`` (journals from before the certificate)."""
    if record.mu_peak_certified is None:
        return "-"
    return f"yes ({record.mu_certified_intervals} intervals)" if record.mu_peak_certified else "NO"


def _sensors_section(rec) -> list[str]:
    """Several sensors (issue 25): every output's residues of the last iteration, and the
    shared poles, as the control output's tables above give its own."""
    outputs = rec.outputs
    rows = []
    for i in range(len(outputs["lower"][0])):
        lo0, hi0 = outputs["lower"][0][i], outputs["upper"][0][i]
        rows.append([f"mode {i + 1}", "a1, a0 (shared)", f"[{_num(lo0[0])}, {_num(hi0[0])}], [{_num(lo0[1])}, {_num(hi0[1])}]"])
        for name, lo, hi in zip(outputs["names"], outputs["lower"], outputs["upper"]):
            rows.append(["", f"b0 at {name}", f"[{_num(lo[i][3])}, {_num(hi[i][3])}]"])
    return ["<h2 id='sensors'>Sensors</h2>",
            f"<p>{len(outputs['names'])} sensors share the poles; the first, {_e(outputs['names'][0])}, is the control output whose "
            "model the analysis, the compensator and the input design use. Intervals after the last iteration "
            f"(k = {rec.k}).</p>",
            _table(["mode", "parameter", "interval"], rows, "table-sensors", "Every sensor's residue intervals and the shared poles.")]
