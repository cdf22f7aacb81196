"""A lone isotropic blur's parameter and Q refined together on the power spectrum
(:func:`refine_lone_isotropic`).

Where the model's only blur is a detector box or an atmosphere (no resampling, no
anisotropic member, no JPEG), the claim's parameter came from the transfer fit or from
the pixel scan's grid (0.1 px of pitch, 0.025 cycles/px of f0, Q in 5 % steps), and at
high Q the roll-off and Q trade against each other along a ridge the transfer barely
weighs. The delivered power spectrum, which is what the refined simulation is to match,
then sits away from its minimum: development c127 (a 1.29 px box at Q 2.89, claimed by
the transfer at 1.10 px) was refined to 0.024 against a baseline of 0.032, while the
same model at the true values reaches 0.014 (``benchmarks/diagnose_oracle.py``).

Once the claim is decided (the claim itself is not revisited: it rests on the transfer or
on the held-out pixels), the member's parameter and ln Q are searched together by a
bounded Nelder–Mead (:func:`~geosim.diagnose.resampling_refine.minimise_bounded`) on the
spectral error of the delivered realisation over the evaluation blocks, from the
claimed values. The refinement is kept only where it scores strictly lower, leaves the
parameter inside the member's scan (:data:`~geosim.diagnose.stage_isotropic_pixels.MEMBER_SCAN`,
an end stands in for a shape beyond it) and clearly present, and Q above the bottom of
its grid (where :func:`~geosim.diagnose.stage_withdraw.blur_at_q_floor` would withdraw
the blur).

Round 48, development (the 123 rows whose model's only blur was a claimed detector or
atmosphere, no JPEG, rerun): against the independent generator's truth the claimed
parameter's median relative error fell from 0.038 to 0.015 (122 rightly claimed; closer
in 65, farther in 49) and Q's from 0.0107 to 0.0058; the benchmark's spectral error fell
in 57 rows and rose in 18 (by more than 0.001); 7 more effect cases halved (c33, c198,
c304, c333, c418, c624, c981) and one no longer (c238: 0.031 → 0.034 against 0.062).
Two scenes with moved objects changed claims (c1091 a false smear, c1338 a false shift),
where the pass kept (first or painted second) flipped on whole-extent errors within
0.001 of each other (``docs/diagnosis.md``, round 48).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from geosim.diagnose.context import EvalContext
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.resampling_refine import minimise_bounded
from geosim.diagnose.select import BlurSelection, clearly_present, replace_step
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs
from geosim.diagnose.stage_isotropic_pixels import MEMBER_SCAN, MIN_Q
from geosim.diagnose.stage_noise import realisations
from geosim.diagnose.stage_withdraw import Q_FLOOR_REL

__all__ = ["refine_lone_isotropic", "refined_inside", "REFINE_LONE_ISOTROPIC", "LONE_STEP_LNQ"]

#: refine a lone isotropic blur on the power spectrum (round 48)
REFINE_LONE_ISOTROPIC = True
#: the first simplex's step in ln Q (the parameter's is its scan step)
LONE_STEP_LNQ = 0.05


def _lone_member(model: ForwardModel) -> str | None:
    """The model's one blur where it is a member of :data:`MEMBER_SCAN` and nothing else
    is (no other blur, no JPEG); otherwise None."""
    if model.compression is not None or len(model.blur) != 1:
        return None
    name = next(iter(model.blur))
    return name if name in MEMBER_SCAN else None


def refined_inside(score: Callable[[np.ndarray], float], x0: np.ndarray, lo: np.ndarray,
                   hi: np.ndarray, step: np.ndarray) -> np.ndarray | None:
    """The point of a bounded Nelder–Mead of ``score`` from ``x0``
    (:func:`~geosim.diagnose.resampling_refine.minimise_bounded`, first simplex ``step``)
    where it scores strictly lower than ``x0`` and lies more than half a ``step`` inside
    the box [``lo``, ``hi``] on every axis (an end of the box stands in for a value beyond
    it); None otherwise, and where ``x0`` is not strictly inside the box. Pure: the caller
    renders and scores."""
    if np.any(x0 <= lo) or np.any(x0 >= hi):
        return None
    f0 = score(x0)
    x, fx = minimise_bounded(score, x0, lo, hi, step)
    inside = bool(np.all(x - lo > 0.5 * step) and np.all(hi - x > 0.5 * step))
    return x if fx < f0 and inside else None


def refine_lone_isotropic(inp: Inputs, model: ForwardModel, sel: BlurSelection,
                          setup: SpectralSetup, ev: EvalContext) -> ForwardModel:
    """``model`` with its lone isotropic blur's parameter and Q refined on the power
    spectrum (module docstring); ``model`` itself where it holds no such blur, where the
    claimed value lies outside the member's scan, or where no refinement qualifies.

    Parameters
    ----------
    inp
        The scene's inputs (renderer, real scene, quantisation).
    model
        The forward model as claimed.
    sel
        The selection whose step claimed the blur: that step's fit takes the refined
        value and Q (what the claim reports), in place
        (:func:`~geosim.diagnose.select.replace_step`, which also carries the value into
        later steps' fits and the final one).
    setup
        The spectral setup (its Q grid bounds the search).
    ev
        Evaluation blocks and noise seed: the score is ``ev.spectral_error`` of the
        delivered realisation(s) (:func:`~geosim.diagnose.stage_noise.realisations`).
    """
    name = _lone_member(model) if REFINE_LONE_ISOTROPIC else None
    if name is None:
        return model
    key, grid = MEMBER_SCAN[name]

    def at(x: np.ndarray) -> ForwardModel:
        return model.without(q=float(np.exp(x[1])),
                             blur={name: {**model.blur[name], key: float(x[0])}})

    def score(x: np.ndarray) -> float:
        return ev.spectral_error(realisations(inp, at(x), ev.noise_seed))

    q_floor = max(Q_FLOOR_REL * float(setup.q_grid[0]), MIN_Q)
    x = refined_inside(score, np.array([float(model.blur[name][key]), np.log(model.q)]),
                       np.array([float(grid[0]), np.log(q_floor)]),
                       np.array([float(grid[-1]), np.log(float(setup.q_grid[-1]))]),
                       np.array([float(grid[1] - grid[0]), LONE_STEP_LNQ]))
    if x is None or not clearly_present(name, {key: float(x[0])}):
        return model
    refined = at(x)
    k = next((i for i, st in enumerate(sel.steps) if st.name == name), None)
    if k is not None:
        st = sel.steps[k]
        replace_step(sel, k, replace(st, fit=replace(
            st.fit, q=refined.q, effects={**st.fit.effects, name: dict(refined.blur[name])})))
    return refined
