"""The robust design (issue 38): a compensator tuned to the mixed-mu bound of the box, and the
floor no compensator can go below.

Truth used here: finite differences (the tuning's analytic gradient), the H2 design on the same
box (the tuned compensator must do better), plants sampled from the box checked one by one with
the exact single-plant robust-performance test of :mod:`setmem_hil.robust.validation` (a
certified mu-bar below 1 must hold for each of them), the closed loop of the floor plant itself
(an imaginary-axis pole whatever the compensator), and the simulated beam's true parameters.
"""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from setmem_hil.cli.main import main
from setmem_hil.model.modal_model import A0, A1, B0, B1, IntervalModel
from setmem_hil.model.mu_floor import floor_message, floor_modes
from setmem_hil.model.weights import THESIS_WEIGHTS
from setmem_hil.robust.analysis import ROBUST_CERTIFICATE_RTOL, analyze_robust_performance, default_grid_for
from setmem_hil.robust.augmented_plant import augmented_plant
from setmem_hil.robust.h2_design import h2_controller_for_plant
from setmem_hil.robust.mixed_mu import MuStructure, mixed_mu_upper
from setmem_hil.robust.robust_design import TuningSettings, _Objective, _OpenLoopResponse, balanced_realisation, tune_compensator
from setmem_hil.robust.uncertain_plant import uncertain_plant
from setmem_hil.sim_backends.beam import beam_parameters

REPO = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_campaign_helpers", Path(__file__).with_name("_campaign_helpers.py"))
H = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(H)
_shared_spec = importlib.util.spec_from_file_location("_shared_runs", Path(__file__).with_name("_shared_runs.py"))
shared_runs = importlib.util.module_from_spec(_shared_spec)
_shared_spec.loader.exec_module(shared_runs)


def _box(relative_half_width: float, floor_mode: int | None = None) -> IntervalModel:
    """A box around the beam's first three modes (``b1`` fixed at 0 as in the thesis prior); with
    ``floor_mode`` that mode's ``a1`` reaches 0 and its ``b0`` interval holds 0."""
    truth = beam_parameters().truncated(3).values
    half = relative_half_width * np.abs(truth)
    lower, upper = truth - half, truth + half
    lower[:, B1] = upper[:, B1] = 0.0
    if floor_mode is not None:
        i = floor_mode - 1
        lower[i, A1] = 0.0
        lower[i, B0] = -0.5 * truth[i, B0]
    return IntervalModel(lower, upper)


# -- the floor ---------------------------------------------------------------------------------

def test_the_floor_is_named_where_the_box_holds_an_undamped_zero_residue_mode():
    assert floor_modes(_box(0.2)) == ()
    assert floor_modes(_box(0.2, floor_mode=3)) == (3,)
    box = _box(0.2, floor_mode=2)
    assert floor_modes(IntervalModel(np.vstack([box.lower[:2], _box(0.2, 3).lower[2:]]),
                                     np.vstack([box.upper[:2], _box(0.2, 3).upper[2:]]))) == (2, 3)
    assert "mode 3: the box holds an undamped mode with zero residue" in floor_message((3,))
    assert floor_message(()) == ""


@pytest.mark.parametrize("edit, expected", [
    (lambda lo, hi: lo.__setitem__((2, A1), 1e-12), ()),          # damped by a hair: no floor
    (lambda lo, hi: lo.__setitem__((2, B0), 0.0), (3,)),          # b0's interval ends at 0: it holds 0
    (lambda lo, hi: (lo.__setitem__((2, B0), 1e-9)), ()),         # b0 bounded away from 0
    (lambda lo, hi: (lo.__setitem__((2, B1), 0.1), hi.__setitem__((2, B1), 0.2)), ()),  # a residue in s
    (lambda lo, hi: (lo.__setitem__((2, B1), -0.1), hi.__setitem__((2, B1), 0.0)), (3,)),
])
def test_the_floor_at_the_edges_of_its_condition(edit, expected):
    box = _box(0.2, floor_mode=3)
    lower, upper = box.lower.copy(), box.upper.copy()
    edit(lower, upper)
    assert floor_modes(IntervalModel(lower, upper)) == expected


@pytest.mark.slow
def test_the_floor_plant_puts_a_closed_loop_pole_on_the_axis_for_any_compensator():
    """Why the floor holds: the box's plant with a1 = b1 = b0 = 0 has the mode in its state but
    not in its transfer function, so the closed loop keeps its poles at +-j sqrt(a0)."""
    box = _box(0.2, floor_mode=3)
    plant = uncertain_plant(box)
    q = np.zeros(plant.n_real)
    half = dict(zip(plant.names, plant.half_widths))
    mid = box.midpoint.values
    q[plant.names.index("a1_3")] = (0.0 - mid[2, A1]) / half["a1_3"]
    q[plant.names.index("b0_3")] = (0.0 - mid[2, B0]) / half["b0_3"]
    assert np.all(np.abs(q) <= 1.0)
    A, C = plant.perturbed_matrices(q)
    P = augmented_plant(plant, THESIS_WEIGHTS)
    for K in (h2_controller_for_plant(P), tune_compensator(P, h2_controller_for_plant(P), default_grid_for(box),
                                                           TuningSettings(max_outer=2)).controller):
        Ak, Bk, Ck, Dk = (np.atleast_2d(np.asarray(getattr(K, n), dtype=float)) for n in "ABCD")
        B = plant.B.reshape(-1, 1)
        Acl = np.block([[A + B @ Dk @ C, B @ Ck], [Bk @ C, Ak]])
        poles = np.linalg.eigvals(Acl)
        assert np.min(np.abs(poles - 1j * np.sqrt(mid[2, A0]))) < 1e-6 * np.sqrt(mid[2, A0])


# -- the tuning ---------------------------------------------------------------------------------

def test_the_tuning_gradient_matches_finite_differences():
    box = _box(0.1)
    P = augmented_plant(uncertain_plant(box), THESIS_WEIGHTS)
    K = balanced_realisation(h2_controller_for_plant(P))
    omega = np.geomspace(0.5, 30.0, 25)
    bound = mixed_mu_upper(P.closed_loop(K).frequency_response(omega), MuStructure(P.n_real, P.n_complex), tol=1e-3)
    rng = np.random.default_rng(3)
    d = bound.d * np.exp(0.2 * rng.standard_normal(bound.d.shape))  # generic scalings: simple eigenvalues
    objective = _Objective(_OpenLoopResponse(P, omega), d, 0.8 * bound.g, K.n_states, tau=0.05)
    theta = np.concatenate([K.A.ravel(), K.B.ravel(), K.C.ravel(), K.D.ravel()])
    _, _, grad = objective(theta)
    for _ in range(4):
        v = rng.standard_normal(theta.size)
        v /= np.linalg.norm(v)
        h = 1e-6 * np.linalg.norm(theta)
        fd = (objective(theta + h * v)[0] - objective(theta - h * v)[0]) / (2 * h)
        assert fd == pytest.approx(grad @ v, rel=1e-4, abs=1e-9 * np.abs(grad).sum())


@pytest.mark.slow
def test_the_tuned_compensator_beats_h2_and_its_claim_holds_for_plants_of_the_box():
    from setmem_hil.robust.validation import box_plants, closed_loop_stable, rp_peak
    from setmem_hil.model.modal_model import ModalParameters

    box = _box(0.02)
    h2 = analyze_robust_performance(box, design="h2")
    robust = analyze_robust_performance(box, design="robust", certificate_rtol=ROBUST_CERTIFICATE_RTOL)
    assert robust.design == "robust" and robust.mu_peak_certified
    assert robust.certified_mu < 0.97 * h2.certified_mu
    assert robust.controller_order == h2.controller_order  # the same order as the H2 design
    plants, _ = box_plants(box, 300, seed=2)
    grid = np.geomspace(0.1, 1000.0, 600)
    for values in plants[:300]:
        plant = ModalParameters(values.reshape(-1, 4))
        assert closed_loop_stable(plant, robust.controller)
        assert rp_peak(plant, robust.controller, THESIS_WEIGHTS, grid)[0] <= robust.certified_mu * (1 + 1e-9)


def test_the_tuning_never_returns_a_worse_compensator_than_its_best_start():
    box = _box(0.1, floor_mode=3)
    P = augmented_plant(uncertain_plant(box), THESIS_WEIGHTS)
    K = h2_controller_for_plant(P)
    result = tune_compensator(P, [K], default_grid_for(box), TuningSettings(max_outer=3))
    assert result.peak <= result.start_peak
    # a floor holds: nothing gets the bound below 1
    assert result.peak >= 1.0 - 1e-9


# -- the campaign -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def robust_run(tmp_path_factory):
    """The demo's own run, made once per session in a fresh process (tests/_shared_runs.py)."""
    return shared_runs.demo_run(tmp_path_factory, tmp_path_factory.mktemp("robust") / "run")


@pytest.mark.slow
def test_the_robust_loop_reaches_the_goal_with_few_experiments_and_names_the_floor(robust_run, tmp_path):
    summary = json.loads((robust_run / "summary.json").read_text())
    assert summary["reached_goal"] and summary["final_mu_peak"] < 1.0
    assert summary["experiments_added"] <= 2  # the H2 loop needs 7 on this seed (issue 38)
    rows = summary["iterations"]
    assert all(r["design"] in ("robust", "h2") for r in rows) and rows[-1]["design"] == "robust"
    assert rows[-1]["floor_modes"] == []
    # the floor's modes are what each iteration's box says (a pure function of it, model/mu_floor.py).
    # Since issue 62 the box is shaved to the data's limit: the undamped zero-residue plants that the
    # split's box held for modes 2 and 3 at iteration 1 (named as the floor until stop 63) do not fit
    # the 15 initial points, and the floor is no longer named where the exact set does not hold it.
    from setmem_hil.io.journal import Journal
    from setmem_hil.model.modal_model import IntervalModel
    from setmem_hil.model.mu_floor import floor_modes

    with Journal.open(robust_run) as journal:
        records, events = journal.iterations(), journal.events()
    assert [r.floor_modes for r in records] == [tuple(r["floor_modes"]) for r in rows]
    assert [r.floor_modes for r in records] == [floor_modes(IntervalModel(r.lower, r.upper)) for r in records]
    named = {m for r in records for m in r.floor_modes}
    assert all(any(e["kind"] == "floor" and f"mode {m}: the box holds an undamped mode" in e["message"] for e in events) for m in named)
    assert main(["export", str(robust_run), "--csv", str(tmp_path / "csv")]) == 0
    with open(tmp_path / "csv" / "iterations.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert [t["design"] for t in table] == [r["design"] for r in rows]
    assert [t["floor_modes"] for t in table] == [";".join(str(m) for m in r["floor_modes"]) for r in rows]


@pytest.mark.slow
def test_the_delivered_robust_compensator_passes_validate(robust_run, tmp_path):
    report = tmp_path / "VALIDATE.json"
    assert main(["validate", str(robust_run), "--samples", "200", "--out", str(report)]) == 0
    doc = json.loads(report.read_text())
    assert doc["truth"]["stable"] and doc["truth"]["rp_peak"] < 1.0
    assert doc["design"] == "robust"
    assert main(["controller", str(robust_run), "--out", str(tmp_path / "K.json")]) == 0
    exported = json.loads((tmp_path / "K.json").read_text())
    assert exported["design"] == "robust" and exported["margin"] == pytest.approx(1.0 / exported["mu_peak"])
    assert main(["report", str(robust_run)]) == 0
    page = (robust_run / "report.html").read_text()
    assert "Delivered compensator" in page and "robust design" in page


# Interrupted on the first added experiment's dwell (the 16th: 15 initial points), then resumed;
# in a fresh process like the reference run (tests/_shared_runs.py says why).
_INTERRUPT_THEN_RESUME = """
import importlib.util, sys
from pathlib import Path
spec = importlib.util.spec_from_file_location("_campaign_helpers", sys.argv[1])
H = importlib.util.module_from_spec(spec)
spec.loader.exec_module(H)
from setmem_hil.campaign.session import start_run, resume_run
from setmem_hil.experiment_factory import open_experiment
from setmem_hil.io.procedure_file import load_procedure
out = Path(sys.argv[3])
opener = lambda p, s: H.InterruptingExperiment(open_experiment(p, s), interrupt_at=16)
try:
    start_run(load_procedure(sys.argv[2]), out, opener=opener, display=None)
except BaseException as stopped:
    print("stopped by", type(stopped).__name__)
else:
    sys.exit("the run was not interrupted")
resume_run(out, opener=open_experiment)
"""


@pytest.mark.slow
def test_a_robust_run_interrupted_and_resumed_equals_the_uninterrupted_one(robust_run, tmp_path):
    """The tuning's effort is counted, never timed: a resume replays the same choices."""
    import subprocess
    import sys

    from setmem_hil.io.journal import Journal

    out = tmp_path / "run"
    done = subprocess.run([sys.executable, "-c", _INTERRUPT_THEN_RESUME, str(Path(H.__file__)),
                           str(REPO / "procedures" / "beam_6_3_2.toml"), str(out)],
                          capture_output=True, text=True, timeout=900, cwd=REPO)
    assert done.returncode == 0 and "stopped by RunInterrupted" in done.stdout, done.stdout[-1000:] + done.stderr[-2000:]
    with Journal.open(out) as a, Journal.open(robust_run) as b:
        got, want = a.iterations(), b.iterations()
        assert [(m["omega_rad_s"], m["re"], m["im"]) for m in a.measurement_rows()] == \
               [(m["omega_rad_s"], m["re"], m["im"]) for m in b.measurement_rows()]
    assert len(want) >= 2  # the interruption fell inside the run, not after it
    assert [(r.k, r.next_omega, r.mu_peak, r.design) for r in got] == [(r.k, r.next_omega, r.mu_peak, r.design) for r in want]


@pytest.mark.slow
def test_design_h2_is_the_thesis_loop(tmp_path):
    """``--design h2``: every kept compensator is the H2 design of its box (the thesis's loop),
    recomputed here from the stored intervals."""
    import control

    out = tmp_path / "h2"
    assert main(["campaign", "--procedure", str(REPO / "procedures" / "beam_6_3_2.toml"), "--out", str(out), "--quiet",
                 "--design", "h2"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert all(r["design"] == "h2" for r in summary["iterations"])
    from setmem_hil.io.journal import Journal
    from setmem_hil.robust.controller_forms import frequency_response, statespace_from_lists

    with Journal.open(out) as journal:
        records = journal.iterations()
    record = next(r for r in records if r.safeguard == "new-design")
    designed = analyze_robust_performance(IntervalModel(record.lower, record.upper)).controller
    stored = statespace_from_lists(record.controller)
    w = np.geomspace(0.1, 100.0, 50)
    theirs = np.array([complex(np.squeeze(designed(1j * x))) for x in w])
    assert np.max(np.abs(frequency_response(stored, w) / theirs - 1.0)) < 1e-8
    assert isinstance(designed, control.StateSpace)


# -- the floor in the input design ---------------------------------------------------------------

def test_candidates_that_remove_a_floor_rank_ahead_of_larger_improvements():
    """Made-up predicted boxes: candidate 0 promises the most improvement but leaves mode 3's
    floor; candidate 1 bounds a1_3 away from 0, candidate 2 bounds b0_3 away from 0."""
    from setmem_hil.design.input_design import _floors_removed, _with_floors_first

    box = _box(0.2, floor_mode=3)
    lower = np.repeat(box.lower[None], 3, axis=0)
    upper = np.repeat(box.upper[None], 3, axis=0)
    lower[1, 2, A1] = 0.05
    lower[2, 2, B0] = 0.5
    removed = _floors_removed(lower, upper, np.array([2]))
    assert removed.tolist() == [0.0, 1.0, 1.0]
    ranking = _with_floors_first(np.array([0.9, 0.1, 0.2]), removed)
    assert np.argsort(-ranking).tolist() == [2, 1, 0]
    # no floor: the scores are untouched (the H2 loop's choices, bit for bit)
    assert _with_floors_first(np.array([0.9, 0.1]), np.zeros(2)).tolist() == [0.9, 0.1]


def test_with_no_score_anywhere_the_next_point_fills_a_floor_modes_band():
    """Every score zero (a close pair's one-mode predictions see nothing): the choice lies in the
    floor mode's band (its sqrt(a0) range) and is the candidate there furthest in log-frequency
    from every measured point, checked by brute force; no floor: the default stands."""
    from setmem_hil.design.input_design import _filling_floor_bands

    box = _box(0.2, floor_mode=2)
    candidates = np.geomspace(0.05, 200.0, 400)
    a0_lo, a0_hi, a1_hi = box.lower[1, A0], box.upper[1, A0], box.upper[1, A1]
    band_lo, band_hi = np.sqrt(a0_lo), np.sqrt(a0_hi)
    measured = np.array([0.5, np.sqrt(a0_lo) * 1.02, np.sqrt(box.upper[1, A0]) * 0.99, 40.0])
    best = _filling_floor_bands(box, candidates, measured, np.array([1]), default=0)
    assert band_lo <= candidates[best] <= band_hi
    gaps = [min(abs(np.log(c / m)) for m in measured) for c in candidates if band_lo <= c <= band_hi]
    assert min(abs(np.log(candidates[best] / m)) for m in measured) == pytest.approx(max(gaps))
    # no candidate in the sqrt(a0) range: the range widened by a1_hi / 2 on each side
    near = np.array([0.01, band_lo - 0.4 * a1_hi, 1000.0])
    assert _filling_floor_bands(box, near, measured, np.array([1]), default=0) == 1
    # a band with no candidate keeps the default
    assert _filling_floor_bands(box, np.array([0.01, 1000.0]), measured, np.array([1]), default=1) == 1


@pytest.mark.slow
def test_the_lower_bound_reaches_one_wherever_the_floor_holds():
    """Inside the floor mode's a0 interval mu >= 1 (the floor plant's closed loop is singular
    there): the reported lower bound says so, and never exceeds the upper bound."""
    box = _box(0.2, floor_mode=3)
    analysis = analyze_robust_performance(box)
    lo, hi = np.sqrt(box.lower[2, A0]), np.sqrt(box.upper[2, A0])
    inside = (analysis.omega >= lo) & (analysis.omega <= hi)
    assert inside.sum() >= 5
    assert np.all(analysis.mu_lower[inside] >= 1.0 - 1e-9)
    assert np.all(analysis.mu_lower <= analysis.mu * (1.0 + 1e-9))
    assert analysis.mu_lower_peak >= 1.0 - 1e-9
