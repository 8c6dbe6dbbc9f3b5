"""Thesis section 6.3.4's trap: a region chosen again and again although it delivers little.

Truth: the rule written out by hand on made-up histories, and a campaign on the simulated beam
whose added points carry no information (their bound is a hundred times the response), so
every prediction fails: the region the design keeps choosing is left out after
``RUN`` iterations and never chosen again.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from setmem_hil.design import unproductive_region as ur
from setmem_hil.design.unproductive_region import Outcome, outside_regions, predicted_improvement, unproductive_region

REPO = Path(__file__).resolve().parents[1]


def _failing(omega, predicted=0.01):
    return Outcome(omega, predicted, 0.1 * predicted)


def test_three_failed_predictions_in_one_region_leave_it_out():
    lo, hi = unproductive_region([_failing(13.87), _failing(13.70), _failing(13.76)])
    assert lo == pytest.approx(13.70 / (1 + ur.REGION)) and hi == pytest.approx(13.87 * (1 + ur.REGION))


@pytest.mark.parametrize("history", [
    [_failing(13.87), _failing(13.70)],  # too few
    [_failing(13.87), Outcome(13.70, 0.01, 0.004), _failing(13.76)],  # one delivered its share
    [_failing(13.87), _failing(6.3), _failing(13.76)],  # not one region
    [_failing(13.87), Outcome(None, 0.01, 0.0), _failing(13.76)],  # a record of several frequencies between
    [_failing(13.87), Outcome(13.70, math.nan, 0.0), _failing(13.76)],  # nothing was predicted
    [_failing(13.87), Outcome(13.70, 0.0, 0.0), _failing(13.76)],
])
def test_anything_less_is_not_a_trap(history):
    assert unproductive_region(history) is None


def test_only_the_last_run_counts():
    assert unproductive_region([_failing(1.0), _failing(13.87), _failing(13.70), _failing(13.76)]) is not None
    assert unproductive_region([_failing(13.87), _failing(13.70), _failing(13.76), Outcome(13.7, 0.01, 0.01)]) is None


def test_candidates_inside_a_region_are_dropped_unless_none_would_be_left():
    w = np.array([1.0, 5.0, 13.6, 13.8, 20.0])
    assert outside_regions(w, [(13.0, 14.0)]).tolist() == [True, True, False, False, True]
    assert outside_regions(w, [(13.0, 14.0), (0.5, 6.0)]).tolist() == [False, False, False, False, True]
    assert outside_regions(w, [(0.1, 100.0)]).all()


def test_the_prediction_is_the_exact_resolve_where_there_was_one():
    choice = SimpleNamespace(next_omega_rad_s=2.0, basis="estimate", candidate_omega_rad_s=np.array([1.0, 2.0, 3.0]),
                             estimated_improvement=np.array([0.1, 0.2, 0.3]), resolved_omega_rad_s=np.array([2.0]),
                             resolved_improvement=np.array([0.05]))
    assert predicted_improvement(choice) == 0.05
    assert predicted_improvement(SimpleNamespace(**{**vars(choice), "resolved_improvement": np.array([np.nan])})) == 0.2
    assert math.isnan(predicted_improvement(SimpleNamespace(**{**vars(choice), "basis": "closeness"})))


class _Uninformative:
    """The simulated beam, but every added point's bound is a hundred times its response."""

    def __init__(self, inner, n_initial):
        self.inner, self.n_initial, self.count, self.chosen = inner, n_initial, 0, []

    def measure(self, omega_rad_s):
        m = self.inner.measure(omega_rad_s)
        self.count += 1
        if self.count <= self.n_initial:
            return m
        self.chosen.append(omega_rad_s)
        return dataclasses.replace(m, bound=100.0 * abs(m.response))

    def total_bound(self, omega_rad_s):
        return self.inner.total_bound(omega_rad_s)


@pytest.mark.slow
def test_a_campaign_whose_points_carry_nothing_leaves_the_region_and_never_returns(tmp_path):
    from setmem_hil.campaign.runner import UNPRODUCTIVE_REGION_EVENT, run_campaign
    from setmem_hil.experiment_factory import open_experiment
    from setmem_hil.io.journal import Journal
    from setmem_hil.io.procedure_file import parse_procedure_text

    text = (REPO / "procedures" / "beam_6_3_2.toml").read_text().replace("max_experiments = 30", "max_experiments = 6")
    procedure = parse_procedure_text(text, "p.toml")
    journal = Journal.create(tmp_path / "journal.sqlite", procedure_text=text, procedure_name="p", seed=1,
                             software_version="test", backend="sim", strategy="mu")
    events = []
    with open_experiment(procedure, seed=1) as inner:
        exp = _Uninformative(inner, len(procedure.initial_omegas_rad_s))
        # the H2 loop: with the robust design each iteration's further tuning also lowers mu-bar,
        # which the rule credits to the experiment (noted in docs/robust-design.md)
        summary = run_campaign(procedure, exp, journal, seed=1, progress=lambda e, **info: events.append((e, info)), design="h2")
    left_out = [info["region"] for e, info in events if e == "note" and info["kind"] == UNPRODUCTIVE_REGION_EVENT]
    assert not summary.reached_goal and len(exp.chosen) == 6
    assert left_out, f"the design kept choosing {exp.chosen} and nothing was left out"
    lo, hi = left_out[0]
    assert all(lo <= w <= hi for w in exp.chosen[: ur.RUN])  # what the rule saw
    assert not any(lo <= w <= hi for w in exp.chosen[ur.RUN:])  # never chosen again
    stored = [e for e in journal.events() if e["kind"] == UNPRODUCTIVE_REGION_EVENT]
    assert len(stored) == len(left_out) and "left out of the candidates" in stored[0]["message"]
    journal.close()
