"""Issue 63 item 2: only informative checks count.

A prediction of ``|S|`` that is unbounded (``0..inf``: a plant disc that reaches the loop's
critical point) or spans more than a decade cannot be contradicted by any measurement. Such a
point is reported as uninformative: it is neither inside nor outside, and ``verified`` needs
informative points. Truth: the discs' own geometry, written out here.
"""

from __future__ import annotations

import math

import numpy as np

from setmem_hil.estimation.closed_loop_point import ClosedLoopPoint
from setmem_hil.robust.closed_loop_prediction import Disc, PredictedSensitivity
from setmem_hil.verify.plan import INFORMATIVE_SPAN, VerifiedPoint, VerifyResult, informative


def _prediction(center: complex | None, radius: float = 0.0) -> PredictedSensitivity:
    return PredictedSensitivity(3.0, None, None if center is None else Disc(complex(center), radius))


def _point(S: complex, prediction: PredictedSensitivity, gain: float = 1.0) -> VerifiedPoint:
    measured = ClosedLoopPoint(3.0, complex(S), 0.01, 1.0 + 0j, 0.01, 0.1, 0.2, 0.3)
    useful = informative(prediction)
    return VerifiedPoint(gain, measured, prediction, useful and prediction.holds(S, 0.01), 0.0, useful)


def test_an_unbounded_or_decade_wide_prediction_is_not_informative():
    assert not informative(_prediction(None))  # 0..inf
    assert _prediction(None).abs_range == (0.0, math.inf)
    assert not informative(_prediction(1.0, 1.0))  # |S| in 0..2: any small |S| fits
    m = 1.0
    r = m * (INFORMATIVE_SPAN - 1) / (INFORMATIVE_SPAN + 1)  # |S| in [m - r, m + r], max / min = SPAN exactly
    assert informative(_prediction(m, 0.999 * r)) and not informative(_prediction(m, 1.001 * r))
    assert informative(_prediction(2.0 + 1.0j, 0.5))


def test_an_uninformative_point_counts_neither_inside_nor_outside_and_verified_needs_informative_ones():
    blind = _point(50.0, _prediction(None))  # a measurement far from anything: still no contradiction possible
    assert not blind.informative and not blind.inside and not blind.outside
    good = _point(1.0, _prediction(1.0, 0.2))
    bad = _point(3.0, _prediction(1.0, 0.2))
    assert good.inside and not good.outside and bad.outside and not bad.inside
    result = VerifyResult(points=[blind, good])
    assert result.first_outside is None
    result.points.append(bad)
    assert result.first_outside is bad
    # verified needs an informative point in every gain step
    result.steps = [{"gain": 0.5, "points": [{"informative": False}]}, {"gain": 1.0, "points": [{"informative": True}]}]
    assert not result.informative_in_every_step()
    result.steps[0]["points"].append({"informative": True})
    assert result.informative_in_every_step()
    assert np.isfinite(good.prediction.abs_range[1])


def test_every_target_file_key_is_in_the_procedures_page():
    """docs/procedures.md's table of ``[target]`` / ``[verify]`` keys holds every key of the schema
    the file is read with (issue 63 item 5: they were in no table)."""
    from pathlib import Path

    from setmem_hil.io.target_file import SCHEMA

    page = (Path(__file__).resolve().parents[1] / "docs" / "procedures.md").read_text(encoding="utf-8")
    section = page[page.index("## The verification's target file"):]
    for spec in SCHEMA:
        where = f"`[{spec.table}]` | `{spec.key}`" if spec.table else f"top level | `{spec.key}`"
        assert where in section, f"{spec.table}.{spec.key} is not in docs/procedures.md"
