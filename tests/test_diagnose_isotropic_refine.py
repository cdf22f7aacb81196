"""The lone isotropic blur's refinement on the power spectrum: the bounded search on
analytic scores (a bowl with a known minimum), its bounds and its "strictly lower" rule."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from geosim.diagnose.stage_isotropic_refine import refined_inside

LO = np.array([0.6, np.log(1.0)])
HI = np.array([2.0, np.log(6.0)])
STEP = np.array([0.1, 0.05])


def _bowl(centre: tuple[float, float], scale: tuple[float, float] = (0.3, 0.2)
          ) -> Callable[[np.ndarray], float]:
    """A smooth score with its minimum (0.01) at ``centre`` (pitch px, ln Q): an
    elongated, tilted valley, as pitch and Q trade against each other."""
    c = np.asarray(centre, float)
    s = np.asarray(scale, float)

    def score(x: np.ndarray) -> float:
        d = (np.asarray(x, float) - c) / s
        return 0.01 + 0.05 * float(d[0] ** 2 + d[1] ** 2 + 1.6 * d[0] * d[1])
    return score


def test_minimum_inside_the_box_is_found():
    truth = (1.42, np.log(3.3))
    x = refined_inside(_bowl(truth), np.array([1.1, np.log(3.9)]), LO, HI, STEP)
    assert x is not None
    assert abs(x[0] - truth[0]) < 0.03 and abs(x[1] - truth[1]) < 0.02, x


def test_minimum_beyond_the_box_is_not_taken():
    # the score keeps falling towards a pitch beyond the scan's end (2.0 px): the search
    # stops at the end, which stands in for a shape beyond it
    x = refined_inside(_bowl((2.6, np.log(3.0))), np.array([1.5, np.log(3.0)]), LO, HI, STEP)
    assert x is None


def test_start_at_the_minimum_is_not_replaced():
    truth = np.array([1.3, np.log(2.5)])
    assert refined_inside(_bowl(tuple(truth)), truth.copy(), LO, HI, STEP) is None


def test_start_outside_the_box_is_left():
    score_calls: list[np.ndarray] = []

    def score(x: np.ndarray) -> float:
        score_calls.append(x)
        return 0.0

    assert refined_inside(score, np.array([2.3, np.log(3.0)]), LO, HI, STEP) is None
    assert refined_inside(score, np.array([1.2, np.log(0.9)]), LO, HI, STEP) is None
    assert not score_calls
