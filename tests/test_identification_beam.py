"""Thesis section 6.2 on the simulated beam: guaranteed containment and Table 6-2/6-4 widths."""

import numpy as np
import pytest

from setmem_hil.identification.algorithm import identify
from setmem_hil.model.modal_model import PARAM_NAMES
from setmem_hil.io.procedure import thesis_beam_prior
from setmem_hil.sim_backends.thesis_cases import TABLE_6_4, section_6_2_data

SEEDS = range(20)


@pytest.fixture(scope="module")
def results_b1_fixed():
    return [(identify(data, thesis_beam_prior(b1_fixed=True)), beam) for data, beam in (section_6_2_data(s) for s in SEEDS)]


@pytest.mark.slow
def test_truth_inside_every_interval_on_20_seeds(results_b1_fixed):
    for result, beam in results_b1_fixed:
        assert result.model.contains(beam.modelled_truth).all()


def test_gamma_within_target_where_partitioned(results_b1_fixed):
    for result, _ in results_b1_fixed:
        for gamma, partitioned in zip(result.embedding_gamma, result.partitioned):
            if partitioned:
                assert gamma <= 1.1 + 1e-9


def test_widths_beside_table_6_4(results_b1_fixed, capsys):
    widths = np.median([r.model.width for r, _ in results_b1_fixed], axis=0)
    lines = ["parameter   ours(median of 20)   thesis Table 6-4   ratio"]
    for key, (lo, hi) in TABLE_6_4.items():
        name, mode = key.split("_")
        ours = widths[int(mode) - 1, PARAM_NAMES.index(name)]
        lines.append(f"{key:8s} {ours:18.4g} {hi - lo:18.4g} {ours / (hi - lo):8.2f}")
        # same order of magnitude as the thesis (grid and noise realisation differ)
        assert 0.2 < ours / (hi - lo) < 3.0, key
    with capsys.disabled():
        print("\n" + "\n".join(lines))


@pytest.mark.slow
def test_b1_free_gives_wider_intervals_and_larger_mismatch(results_b1_fixed):
    """Section 6.2.1 vs 6.2.2: ignoring b1 = 0 widens the intervals and raises the mismatch."""
    free = [identify(section_6_2_data(s)[0], thesis_beam_prior(b1_fixed=False)) for s in range(5)]
    fixed = [r for r, _ in results_b1_fixed[:5]]
    shared = [0, 1, 3]  # a0, a1, b0: b1 is fixed in one of the two
    for f, x in zip(free, fixed):
        # The exact set with b1 free holds the one with b1 = 0, so the free box holds every point
        # checked to fit with b1 = 0: the fixed run's inner extent (its width over its reach ratio).
        # Both boxes are outer bounds shaved to within ~1.08 of their sets, so box against box may
        # differ by that much either way on one interval; the set against the box cannot.
        inner_fixed = x.model.width[:, shared] / x.reach_ratio[:, shared]
        assert np.all(f.model.width[:, shared] >= inner_fixed * (1 - 1e-6))
        # and on the whole the free intervals are wider (the thesis's 6.2.1 against 6.2.2)
        assert np.exp(np.mean(np.log(f.model.width[:, shared] / x.model.width[:, shared]))) > 1.0
    assert np.mean([f.mismatch_ratio for f in free]) > np.mean([x.mismatch_ratio for x in fixed])
    for s, f in zip(range(5), free):
        assert f.model.contains(section_6_2_data(s)[1].modelled_truth).all()


def test_bounds_never_loosen_given_previous(results_b1_fixed):
    result, _ = results_b1_fixed[0]
    data, _ = section_6_2_data(0)
    again = identify(data, thesis_beam_prior(), previous=result.model)
    assert np.all(again.model.lower >= result.model.lower) and np.all(again.model.upper <= result.model.upper)


def test_result_document_has_contract_keys(results_b1_fixed):
    doc = results_b1_fixed[0][0].to_document()
    assert set(doc) >= {"modes", "conservatism", "iterations"}
    assert set(doc["conservatism"]) == {"embedding_gamma", "mismatch_ratio"}
    assert [set(m) - {"verified", "unverified_reason", "group", "reach_ratio"} for m in doc["modes"]] == [set(PARAM_NAMES)] * 3
    assert doc["witness"]["fits"] is True and 0 <= doc["witness"]["misfit"] <= 1  # issue 62: a point checked to fit
    assert [m["group"] for m in doc["modes"]] == [[1], [2], [3]]  # separated modes: each alone (issue 47)
    assert all(isinstance(m["verified"], bool) for m in doc["modes"])
