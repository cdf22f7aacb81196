"""Same-family blurs decided by the exact (window-aware) model.

Forward selection (:mod:`geosim.diagnose.select`) runs on the fast transfer model, which
multiplies the *measured* Welch transfer of the Q-grid simulations by the *analytic*
transfer of an effect at the bin frequency. The Hann window spreads each bin over ±2
bins, weighted towards lower frequencies by the scene's falling spectrum, so a blur
measures weaker and smoother than it is. Where two members of one family differ only by
the shape of their roll-off, that bias decides the name:

* anisotropic: a smear's sinc looks like the off-nadir Gaussian;
* isotropic: the detector's box (sinc, ≈ 1 − (π p f)²/6 in the band) and the atmosphere's
  exp(−(f/f0)^(5/3)) differ only in the power of f below the optical cutoff; the fast fit
  smooths the sinc towards the atmosphere's shape (development extension x5216: a
  1.57 px detector at Q 2.33 called ``atmospheric_blur`` f0 0.62 with held-out gain 0.202
  against the detector's 0.199; the exact model: detector 0.228, atmosphere 0.226).

:func:`exact_duel` refits every member of the family (jointly with Q, the gain and the
other chosen blurs) with :class:`~geosim.diagnose.exact.ExactSimulations` and keeps the
one whose fit on all blocks leaves the lowest χ² (members have equal numbers of
parameters; :func:`~geosim.diagnose.exact.in_sample_best`); members whose held-out gain
is within :data:`~geosim.diagnose.select.AMBIGUITY_CV` of the chosen one's (or above it)
are listed as alternatives. The chosen blur's parameters, Q and gain become the exact
model's.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from geosim.diagnose.alias_cells import AliasPieces
from geosim.diagnose.exact import ExactBlocks, ExactSimulations, duel, exact_fit, in_sample_best
from geosim.diagnose.fit import BinFilter, SpectralData, fit_transfer
from geosim.diagnose.select import (
    AMBIGUITY_CV,
    BLUR_FAMILY,
    MIN_CV_GAIN,
    AcceptedEffect,
    Alternative,
    BlurSelection,
    at_bound,
    clearly_present,
    delta_bic,
    plausible,
    replace_step,
)

__all__ = ["exact_duel", "EXACT_FAMILIES"]

#: families whose members are told apart by the exact model, in the order they are decided
EXACT_FAMILIES = ("anisotropic", "isotropic")


def _members(family: str) -> list[str]:
    return [c for c, fam in BLUR_FAMILY.items() if fam == family]


def exact_duel(grey: np.ndarray, sims_grey: Sequence[np.ndarray], q_grid: np.ndarray,
               full: SpectralData, origins: list[tuple[int, int]],
               fold_groups: Sequence[Sequence[tuple[int, int]]], block_px: int,
               sel: BlurSelection, family: str, q_base: float,
               keep: BinFilter | None = None, *, taper: np.ndarray | None = None,
               pieces: AliasPieces | None = None,
               share: np.ndarray | None = None) -> BlurSelection:
    """Decide the claimed member of ``family`` by the exact model's χ² on all blocks.

    Parameters
    ----------
    grey
        The real scene, grey levels (rows, cols), co-registered with ``sims_grey``.
    sims_grey, q_grid
        The grey Q-grid simulations and their Q (increasing), as the fast fit used them.
    full
        The fast fit's spectral data on all ``origins`` (for the members' starting fits).
    origins, fold_groups, block_px
        Welch block origins (px), their spatial cross-validation groups, block side (px).
    sel
        The forward selection; returned unchanged when no member of ``family`` was chosen
        or no member's exact fit is clearly present, in range and not at a bound.
    family
        A family of :data:`~geosim.diagnose.select.BLUR_FAMILY` (``"anisotropic"``,
        ``"isotropic"``).
    q_base
        The LV baseline Q (a second starting value).
    keep
        The bins the fits may use (as the fast fit's ``full`` was built with); None: all.
    taper
        Weights (rows, cols) with which changed regions were tapered out of ``grey`` and of
        the fast fit's simulations (:func:`~geosim.diagnose.stage_blur.change_taper`): the
        exact model tapers each render after its blur, as the real scene was tapered after
        the real blur. None: no taper.
    pieces
        The simulations' alias-cell parts (as ``full`` was built with), so that the blurs
        act before sampling; None: none.
    share
        Per bin, the share of the incoherent power that is noise (as ``full`` was built
        with, :func:`~geosim.diagnose.fit.alias_unexplained_share`); None: all.

    Returns
    -------
    BlurSelection
        ``sel`` with the family's step replaced by the exact winner (held-out gain,
        alternatives, ΔBIC of the exact fits) and ``final`` the exact joint fit.
    """
    k = next((i for i, st in enumerate(sel.steps) if BLUR_FAMILY.get(st.name) == family),
             None)
    if k is None:
        return sel
    old = sel.steps[k].name
    members = _members(family)
    others = [n for n in sel.final.effects if n != old]
    qs = (sel.final.q, q_base)
    starts = {m: fit_transfer(full, [*others, m], q_starts=qs) for m in members}
    without = fit_transfer(full, others, q_starts=qs) if others else sel.null
    sims = ExactSimulations(sims_grey, q_grid, taper=taper, pieces=pieces)
    blocks = ExactBlocks.build(sims, grey, origins, block_px, keep, share)
    folds = []
    if len(fold_groups) >= 2:
        for j, g in enumerate(fold_groups):
            train = [o for i, gg in enumerate(fold_groups) if i != j for o in gg]
            folds.append((ExactBlocks.build(sims, grey, train, block_px, keep, share),
                          ExactBlocks.build(sims, grey, list(g), block_px, keep, share)))
    res = duel(sims, blocks, folds, starts, without)
    ok = [m for m in members if not at_bound(m, res.fits[m].effects[m])
          and clearly_present(m, res.fits[m].effects[m])
          and plausible(m, res.fits[m].effects[m])]
    if not ok:
        return sel
    best = in_sample_best(res.fits, ok)
    fit = res.fits[best]
    gb = res.gains[best]
    n_values = 2 * full.t_real.size
    # the variance scale of the claimed fit, so that the members' BICs compare as ΔBIC does
    scale = max(1.0, fit.chi2 / max(n_values - fit.n_params, 1))
    alts = [Alternative(m, float(res.gains[m]), dict(res.fits[m].effects[m]),
                        float(res.fits[m].bic(scale) - fit.bic(scale))) for m in ok
            if m != best and res.gains[m] >= MIN_CV_GAIN
            and gb - res.gains[m] <= AMBIGUITY_CV * gb]
    dbic = delta_bic(exact_fit(sims, blocks, without), fit, n_values)
    replace_step(sel, k, AcceptedEffect(best, dbic, float(gb), alts, fit), final=fit)
    sel.cv_gain.update({m: float(v) for m, v in res.gains.items()})
    return sel
