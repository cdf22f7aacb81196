"""The anisotropic member the transfer named, checked in the pixels (:func:`pixel_member`).

The measured transfer tells an off-nadir elongation (a Gaussian along one direction) from a
motion smear (a box along one direction) only by the shape of its roll-off beyond the
second moment, which at high Q and modest SNR it barely sees: on the development half
(round 44) swapped members were 48 of the 69 false claims (27 smears named off-nadir, 21
the reverse), some where the ideal observer names the member with Δχ² of 100–900 (c679,
c932, c1029, c1121, c1146).

In the pixels the two shapes differ in the image itself. Where the model holds one
anisotropic member and no JPEG (whose quantisation is not independent of the image), both
members are fitted on each checkerboard half of the evaluation pixels (ln Q, width,
direction by Nelder–Mead, the model's other blurs held, each started from the claimed
blur's second moment and direction and the model's Q; :func:`member_check`) and each
half's pair is scored on the other half: the drop of its residual sum of squares when the
other member replaces the claimed one, in units of its residual variance per pixel. Only
where that reaches :data:`MEMBER_MIN_DCHI2` both ways round is the other member named; the
claim keeps the transfer's held-out gain (the family's presence) and records, as its
``test``, the member the transfer named and the pixels' evidence.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from geosim.diagnose.context import EvalContext
from geosim.diagnose.fit import fit_transfer
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.select import (
    AcceptedEffect,
    Alternative,
    BlurSelection,
    delta_bic,
    replace_step,
)
from geosim.diagnose.stage_anisotropic_pixels import SHAPES, claimable, fit_on_half
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs
from geosim.diagnose.stage_resampling_coherent import checker_halves, rss_on_halves
from geosim.diagnose.stage_withdraw import no_worse_than_baseline

__all__ = ["pixel_member", "member_check", "MemberCheck", "MEMBER_MIN_DCHI2", "MEMBERS"]

#: the anisotropic family's members, as :data:`~geosim.diagnose.stage_anisotropic_pixels.SHAPES`
MEMBERS = tuple(SHAPES)
#: held-out drop (units of the other half's residual variance per pixel) the other member
#: must bring on each checkerboard half before it is named instead. Set on the development
#: half (round 45, all 206 rows of the domain probed): on rows the transfer named right the
#: smaller of the two drops reached at most 18 (c1062 84 / 18, c416 19 / 17, c1057 20 / 16),
#: on wrongly named ones 42 and 54 (c679, c1029) and else at most 17 (c1146 21 / 17); 25
#: lies in that gap. See ``docs/diagnosis.md``, round 45
MEMBER_MIN_DCHI2 = 25.0


@dataclass(frozen=True)
class MemberCheck:
    """Both members fitted on each checkerboard half (:func:`member_check`).

    Attributes
    ----------
    claimed, other
        The member the model holds and the other one.
    models
        Per member, the model fitted on half 0 and on half 1 (only half 0 where the check
        stopped early).
    rss
        Per member and fit, [RSS on half 0, RSS on half 1], DN².
    naming_dchi2
        Per half fitted on, the other half's drop of the residual sum of squares when the
        other member replaces the claimed one, in units of that half's residual variance
        per pixel under the claimed member (positive: the other member predicts better).
    """

    claimed: str
    other: str
    models: dict[str, list[ForwardModel]]
    rss: dict[str, list[list[float]]]
    naming_dchi2: list[float]

    def best_other(self) -> ForwardModel:
        """The other member's fit of lowest RSS over both halves."""
        rss = self.rss[self.other]
        return self.models[self.other][int(np.argmin([sum(r) for r in rss]))]


def member_check(inp: Inputs, model: ForwardModel, halves: list[np.ndarray],
                 stop_below: float | None = None) -> MemberCheck:
    """The model's anisotropic member and the other one, each fitted on each half
    (:func:`~geosim.diagnose.stage_anisotropic_pixels.fit_on_half`: the model's other
    blurs held, started from the claimed blur's second moment and direction and the
    model's Q), scored on the other half. ``stop_below``: after half 0, stop where its
    ``naming_dchi2`` is below this (None: both halves)."""
    claimed = next(n for n in MEMBERS if n in model.blur)
    other = next(n for n in MEMBERS if n != claimed)
    was = SHAPES[claimed]
    params = model.blur[claimed]
    variance = float(params[was.width_key]) ** 2 * was.variance_per_width2
    direction = float(params[was.direction_key])
    held = {n: p for n, p in model.blur.items() if n != claimed}
    models: dict[str, list[ForwardModel]] = {claimed: [], other: []}
    rss: dict[str, list[list[float]]] = {claimed: [], other: []}
    naming: list[float] = []
    for k in (0, 1):
        for name in (claimed, other):
            m = fit_on_half(inp, model, halves[k], name, variance, direction, model.q, held)
            models[name].append(m)
            rss[name].append(rss_on_halves(inp, halves, m))
        o = 1 - k
        rss_claimed, rss_other = rss[claimed][k][o], rss[other][k][o]
        naming.append((rss_claimed - rss_other)
                      / max(rss_claimed / int(halves[o].sum()), 1e-12))
        if stop_below is not None and naming[-1] < stop_below:
            break
    return MemberCheck(claimed=claimed, other=other, models=models, rss=rss,
                       naming_dchi2=naming)


def pixel_member(inp: Inputs, model: ForwardModel, sel: BlurSelection, setup: SpectralSetup,
                 ev: EvalContext, candidates: tuple[str, ...]) -> ForwardModel:
    """The other anisotropic member named in place of the model's where the pixels want it
    (:func:`member_check`, :data:`MEMBER_MIN_DCHI2` on both halves), fits clearly and not
    at a bound of its widths, and leaves the refined simulation no worse than the
    baseline. The selection's step is replaced: its fit is the transfer fit with the
    renamed blurs held at the fitted Q, its ΔBIC against the previous step's fit."""
    held_members = [n for n in MEMBERS if n in model.blur]
    if (len(held_members) != 1 or model.compression is not None
            or any(n not in candidates for n in MEMBERS)):
        return model
    k = next((i for i, st in enumerate(sel.steps) if st.name == held_members[0]), None)
    halves = checker_halves(ev)
    if k is None or halves is None:
        return model
    check = member_check(inp, model, halves, stop_below=MEMBER_MIN_DCHI2)
    if len(check.naming_dchi2) < 2 or min(check.naming_dchi2) < MEMBER_MIN_DCHI2:
        return model
    chosen = check.best_other()
    x, y = check.claimed, check.other
    if not claimable(y, chosen) or not no_worse_than_baseline(inp, ev)(chosen):
        return model
    old = sel.steps[k]
    # the blurs of steps up to k (renamed), held at the fitted Q: the step's own fit
    upto = [y if n == x else n for n in old.fit.effects]
    fit = fit_transfer(setup.full, [], fix_q=chosen.q,
                       fixed={n: dict(chosen.blur[n]) for n in upto if n in chosen.blur})
    key = SHAPES[y].width_key
    widths = [float(m.blur[y][key]) for m in check.models[y]]
    sigmas = {n: s for n, s in old.fit.sigmas.items() if n != x}
    fit = replace(fit, sigmas={**sigmas, y: {key: abs(widths[0] - widths[1]) / 2.0}},
                  n_params=old.fit.n_params)
    prev = sel.steps[k - 1].fit if k else sel.null
    transfer_params = {n: float(v) for n, v in model.blur[x].items()}
    test = {"transfer_named": x, "transfer_params": transfer_params,
            "naming_dchi2": [float(v) for v in check.naming_dchi2],
            "min_dchi2": MEMBER_MIN_DCHI2}
    # the transfer's member stays on record as the alternative (flights that named it vote
    # with this one)
    alternatives = [a for a in old.alternatives if a.name != y] + [Alternative(
        x, old.heldout_gain, transfer_params)]
    replace_step(sel, k, AcceptedEffect(
        y, delta_bic(prev, fit, 2 * setup.full.t_real.size), old.heldout_gain,
        alternatives, fit, test=test))
    return chosen
