"""The run report renders headless and holds every figure and table; the figure numerics are
checked against independent formulations (state-space eigenvalues, G(zero) = 0, the thesis text)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.model.experiment import Measurement
from setmem_hil.io.journal import IterationRecord, Journal
from setmem_hil.model.modal_model import IntervalModel, ModalParameters
from setmem_hil.io.procedure import default_procedure
from setmem_hil.io.procedure_file import format_procedure
from setmem_hil.report.document import FIGURE_FILES, figure_iterations, write_report
from setmem_hil.report.figures import TABLE_6_6, modal_poles_zeros, table_6_6_offsets

THESIS = Path("/work/shared/reference/thesis.txt")
TRUTH = ModalParameters.from_modal([1.0, 6.267, 17.547], [0.02, 0.02, 0.02], [4.0, 3.5, 3.0], b1=[0.0, 0.0, 0.0])


def _journal(tmp_path, n_iterations=5, discrepancy=True):
    """A journal as a campaign on the beam would leave it: bounds shrinking about the truth."""
    rng = np.random.default_rng(11)
    run = tmp_path / "run"
    j = Journal.create(run / "journal.sqlite", procedure_text=format_procedure(default_procedure()), procedure_name="beam-6.3.2",
                       seed=1, software_version="t", backend="sim", strategy="mu")
    omegas = list(default_procedure().initial_omegas_rad_s)
    ms = []
    for w in omegas:
        g = complex(TRUTH.frequency_response(np.array([w]))[0])
        m = Measurement(w, g + 0.01 * complex(*rng.normal(size=2)), 0.05)
        ms.append(m)
        j.add_measurement(m, iteration=0, role="initial")
    for k in range(1, n_iterations + 1):
        half = np.abs(TRUTH.values) * 0.3 / k + 1e-3
        half[:, 2] = 0.0
        last = k == n_iterations
        nxt = None if last else float([6.48, 1.15, 16.96, 6.2][(k - 1) % 4])
        cand = np.geomspace(0.1, 1000, 60)
        j.add_iteration(IterationRecord(
            k=k, n_points=len(ms), lower=TRUTH.values - half, upper=TRUTH.values + half, mu_peak=2.5 / k, mu_peak_omega=4.4,
            mu_lower_peak=2.0 / k, omega=np.geomspace(0.1, 100, 80), mu=(2.5 / k) * np.exp(-np.log(np.geomspace(0.1, 100, 80) / 4.4) ** 2),
            sensitivities={f"{p}_{i}": 0.8 / (i * k) for i in (1, 2, 3) for p in ("a1", "a0", "b0")}, next_omega=nxt,
            candidate_omega=np.zeros(0) if last else cand, estimated_improvement=np.zeros(0) if last else np.exp(-np.log(cand / nxt) ** 2),
            controller_order=6, safeguard="new-design" if k != 3 else "expanded", wall_s=1.0,
            embedding_gamma=np.array([1.05, 1.08, 1.02]), mismatch_ratio=np.array([0.1, 0.2, 0.05]),
        ))
        if not last:
            g = complex(TRUTH.frequency_response(np.array([nxt]))[0])
            m = Measurement(nxt, g, 0.05)
            ms.append(m)
            j.add_measurement(m, iteration=k, role="added")
    if discrepancy:
        j.add_discrepancy(2, {"disagreement_bands": [[20.5, 31.0]], "effects": [{"name": "time-delay"}], "decision": "time-delay",
                              "before": {"max_normalized_residual": 3.2}, "after": {"max_normalized_residual": 0.8}, "rule": "x" * 400})
    j.add_event("interrupted", "Ctrl-C <script>alert(1)</script>")
    j.finish({"reached_goal": True, "final_mu_peak": 0.5, "experiments_added": n_iterations - 1, "stop_reason": "goal"})
    j.close()
    return run


def test_report_holds_every_figure_and_table(tmp_path):  # a contract: in the default tier (issue 46)
    run = _journal(tmp_path)
    path = write_report(run)
    assert path == run / "report.html"
    text = path.read_text()
    srcs = re.findall(r'<img src="([^"]+)"', text)
    expected = set(FIGURE_FILES.values()) | {f"fig_tf_k{k}.png" for k in (1, 2, 3, 5)} | {f"fig_pz_k{k}.png" for k in (1, 2, 3, 5)}
    assert set(srcs) == expected
    for src in srcs:
        png = run / src
        assert png.stat().st_size > 5000
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    ids = set(re.findall(r'<table id="([^"]+)"', text))
    assert {"table-run", "table-iterations", "table-events", "table-measurements", "table-discrepancy-1"} <= ids
    assert {f"table-intervals-k{k}" for k in range(1, 6)} <= ids
    disc = text[text.index('id="table-discrepancy-1"'):].split("</table>")[0]
    for cell in ("time-delay", "20.5-31 rad/s", "<td>3.2</td>", "<td>0.8</td>", "x" * 297 + "..."):
        assert cell in disc, cell
    # appendix B wording and content: the bounds of iteration 2 appear with their sensitivities
    assert "after applying a sinusoid at 6.48 rad/s" in text
    assert "after the initial data points" in text
    k2 = text[text.index('id="table-intervals-k2"'):].split("</table>")[0]
    rows = re.findall(r"<tr><td>([ab][01]_\d)</td><td>([^<]+)</td><td>([^<]+)</td><td>([^<]+)</td><td>([^<]+)</td></tr>", k2)
    assert len(rows) == 12
    a0_1 = next(r for r in rows if r[0] == "a0_1")  # one name per parameter (issue 17), as in RESULT.json
    half = abs(TRUTH.values[0, 1]) * 0.3 / 2 + 1e-3
    assert float(a0_1[1]) == pytest.approx(TRUTH.values[0, 1] - half, rel=1e-4)
    assert float(a0_1[2]) == pytest.approx(TRUTH.values[0, 1] + half, rel=1e-4)
    assert float(a0_1[4]) == pytest.approx(0.8 / 2, rel=1e-4)
    assert next(r for r in rows if r[0] == "b1_1")[3] == "fixed"
    # headless and self-contained: no script, nothing from the network, text escaped
    assert "<script" not in text and "http://" not in text and "https://" not in text
    assert "&lt;script&gt;" in text
    # the measurements table has every measurement
    meas = text[text.index('id="table-measurements"'):].split("</table>")[0]
    assert meas.count("<tr><td>") == 19


def test_report_of_a_run_without_iterations(tmp_path):
    j = Journal.create(tmp_path / "r" / "journal.sqlite", procedure_text="", procedure_name="empty", seed=1, software_version="t", backend="sim", strategy="mu")
    j.add_measurement(Measurement(1.0, 1 + 1j, 0.1), iteration=0, role="initial")
    j.close()
    text = write_report(tmp_path / "r").read_text()
    assert "No iteration is stored yet." in text and "not finished" in text
    assert "No discrepancy check was run." in text


def test_report_command(tmp_path, capsys):
    run = _journal(tmp_path, n_iterations=1, discrepancy=False)
    assert main(["report", str(run)]) == 0
    assert capsys.readouterr().out.strip().endswith("report.html")
    assert main(["report", str(tmp_path / "none")]) == 2


def test_figure_iterations_follow_the_thesis():
    recs = [type("R", (), {"k": k})() for k in range(1, 9)]
    assert figure_iterations(recs) == [1, 2, 3, 8]
    assert figure_iterations(recs[:2]) == [1, 2]
    assert figure_iterations([]) == []


def test_poles_and_zeros_against_state_space_and_the_transfer_function():
    rng = np.random.default_rng(4)
    params = ModalParameters(np.column_stack([rng.uniform(0.01, 0.5, 3), rng.uniform(1, 400, 3), rng.normal(size=3), rng.uniform(1, 5, 3)]))
    poles, zeros = modal_poles_zeros(params)
    A = params.state_space_matrices()[0]
    np.testing.assert_allclose(np.sort_complex(poles), np.sort_complex(np.linalg.eigvals(A)), rtol=1e-8)
    assert zeros.size == 5  # numerator degree 2 (n - 1) + 1 with b1 != 0
    g = np.array([sum((b1 * z + b0) / (z * z + a1 * z + a0) for a1, a0, b1, b0 in params.values) for z in zeros])
    scale = np.array([sum(abs(b1 * z + b0) / abs(z * z + a1 * z + a0) for a1, a0, b1, b0 in params.values) for z in zeros])
    assert np.all(np.abs(g) < 1e-8 * scale)


def test_table_6_6_offsets_shape_and_nominal():
    x = table_6_6_offsets(3)
    assert x.shape == (9, 3, 4)
    assert np.all(x[:, :, 2] == 0.0)  # b1 at its midpoint (fixed at 0 in the thesis)
    assert np.all(x[8] == 0.0)  # transfer function 9 is the nominal model
    model = IntervalModel(TRUTH.values - 1.0, TRUTH.values + 1.0)
    np.testing.assert_allclose(model.sample(x[6]).values[:, 0], TRUTH.values[:, 0] - 0.5)  # TF 7: a1 = mid - .5 half-width
    assert table_6_6_offsets(4)[:, 3].tolist() == table_6_6_offsets(4)[:, 0].tolist()


@pytest.mark.skipif(not THESIS.exists(), reason="thesis text not available")
def test_table_6_6_matches_the_thesis_text():
    lines = THESIS.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("Transfer Function 1\t"))
    rows = []
    for n, line in enumerate(lines[start:start + 9]):
        cells = line.split("\t")[1:]
        cells += [""] * (9 - len(cells))
        row = []
        for c in cells[:9]:
            c = c.replace("$", "").replace("\\,", "").replace(" ", "").replace("\\mathbf{0}", "0")
            if c in ("Ω", "O", "0"):
                row.append(0.0)
            elif c == "":
                row.append(0.0 if n == 8 else 1.0)  # the documented transcription rule
            else:
                v = float(c if not c.startswith(".") else "0" + c)
                row.append(v / 10 if abs(v) == 5 else v)  # "- 5" in TF 7 is the OCR of "-.5"
        rows.append(row)
    np.testing.assert_array_equal(np.array(rows), TABLE_6_6)


def test_report_needs_no_display(tmp_path):
    """In a process whose matplotlib backend would need a display, the report still renders."""
    import os
    import subprocess
    import sys

    run = _journal(tmp_path, n_iterations=1, discrepancy=False)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MPLBACKEND"] = "TkAgg"
    code = "import sys; from setmem_hil.report.document import write_report; write_report(sys.argv[1]); print('matplotlib.pyplot' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code, str(run)],
                          capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"
    assert (run / "fig_tf_k1.png").stat().st_size > 5000


def test_the_report_says_which_modes_were_identified_together(tmp_path):
    """Issue 47, item 5: per mode, alone or with its group (from the journal's iteration record)."""
    import importlib.util

    from setmem_hil.report.document import write_report

    spec = importlib.util.spec_from_file_location("_synthetic_run", Path(__file__).with_name("_synthetic_run.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    run_dir = module.one_iteration_run(tmp_path / "run", groups=((1, 2),))[0]
    page = write_report(run_dir).read_text()
    table = page[page.index("table-conservatism-k1"):]
    table = table[: table.index("</table>")]
    assert table.count("with modes 2 + 3") == 2 and table.count("alone") == 1


def test_the_report_gives_each_modes_widest_interval_over_the_exact_set(tmp_path):
    """Issue 47, item 6: the last iteration's conservatism table gives, per mode, the widest interval
    over the linearised exact feasible set, held against that set's extent computed here with
    inscribed 64-gons, as the report uses."""
    import importlib.util

    from setmem_hil.identification.exact_set import linearised_extent
    from setmem_hil.io.procedure_file import load_procedure
    from setmem_hil.report.document import write_report

    spec = importlib.util.spec_from_file_location("_synthetic_run", Path(__file__).with_name("_synthetic_run.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    run_dir, box, _ = module.one_iteration_run(tmp_path / "run", half_width=0.05, measured=True)
    page = write_report(run_dir).read_text()
    table = page[page.index("table-conservatism-k1"):]
    table = table[: table.index("</table>")]
    assert "widest interval / exact set" in table
    cells = re.findall(r"([0-9.]+) \((a0|a1|b0|b1)\)", table)
    assert len(cells) == 3
    from setmem_hil.sim_backends.beam import beam_parameters

    truth = beam_parameters().truncated(3).values
    w = np.geomspace(0.3, 30.0, 15)
    G = ModalParameters(truth).frequency_response(w)
    prior = load_procedure(module.REPO / "procedures" / "beam_6_3_2.toml").prior.initial_bounds()
    centre = 0.5 * (box.lower + box.upper)
    lo, hi = linearised_extent(w, G, 0.01 * np.abs(G) + 1e-4, centre, prior.lower, prior.upper, sides=64)
    with np.errstate(invalid="ignore"):  # fixed parameters: no width on either side
        expected = (box.upper - box.lower) / (hi - lo)
    names = {"a1": 0, "a0": 1, "b1": 2, "b0": 3}
    for i, (value, name) in enumerate(cells):
        assert abs(float(value) - expected[i, names[name]]) <= 0.03 * expected[i, names[name]] + 0.01
        assert float(value) >= 0.97 * np.max(expected[i][np.isfinite(expected[i])])
