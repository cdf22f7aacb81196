"""Which effects does the evidence carry?

Blur effects are chosen by forward selection on the measured transfer function:
at each step every remaining candidate is fitted jointly with Q, the gain and
the effects already chosen; the best is accepted only when

* its ΔBIC (BIC without − BIC with, residual scale from the larger model) is at
  least ``MIN_DELTA_BIC`` = 10 ("very strong" on the Kass & Raftery scale), and
* it improves the fit on data held out from fitting: fitted on the left half of
  the scene and scored on the right half and vice versa, the χ² must drop by at
  least ``MIN_HELDOUT_GAIN`` (relative).

Candidates whose ΔBIC is within ``AMBIGUITY_BIC`` = 6 of the winner's explain the
data about as well; they are reported as indistinguishable alternatives instead
of being silently dropped (typical pair: ``detector_integration`` and
``atmospheric_blur``, both isotropic roll-offs that also trade off against Q).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from geosim.diagnose.effects import BLUR_EFFECTS, get_effect
from geosim.diagnose.fit import (
    RadiometryFit,
    SpectralData,
    TransferFit,
    evaluate_chi2,
    fit_transfer,
)

__all__ = ["BlurSelection", "select_blur", "delta_bic", "select_radiometry",
           "MIN_DELTA_BIC", "MIN_HELDOUT_GAIN", "AMBIGUITY_BIC"]

MIN_DELTA_BIC = 10.0
#: smallest radiometric correction worth claiming: RMS change of the image in some band, DN
MIN_RADIOMETRIC_DN = 1.0
#: largest per-band gain still called haze (white-balance differences between the UAV camera
#: and the satellite can lift one band slightly above 1 while path radiance adds offsets)
HAZE_MAX_GAIN = 1.05
MIN_HELDOUT_GAIN = 0.01
AMBIGUITY_BIC = 6.0


def delta_bic(without: TransferFit, with_: TransferFit, n_values: int) -> float:
    """BIC(without) − BIC(with), residual variance scale estimated from the larger model."""
    dof = max(n_values - with_.n_params, 1)
    scale = max(1.0, with_.chi2 / (dof * 1.0))
    return float(without.bic(scale) - with_.bic(scale))


@dataclass
class Step:
    """One accepted effect with its evidence."""

    name: str
    delta_bic: float
    heldout_gain: float
    alternatives: list[str]
    fit: TransferFit


@dataclass
class BlurSelection:
    """Outcome of :func:`select_blur`."""

    null: TransferFit
    final: TransferFit
    steps: list[Step] = field(default_factory=list)
    tried: dict[str, float] = field(default_factory=dict)   # last ΔBIC of each candidate
    at_bound: set[str] = field(default_factory=set)          # fits pinned at a bound


def _at_bound(name: str, params: dict[str, float], rel: float = 0.01) -> bool:
    for spec in get_effect(name).params:
        if spec.periodic or spec.name not in params:
            continue
        span = spec.upper - spec.lower
        v = params[spec.name]
        if v - spec.lower < rel * span or spec.upper - v < rel * span:
            return True
    return False


def _heldout_gain(a: SpectralData, b: SpectralData, base: Sequence[str], cand: Sequence[str],
                  q_starts: Sequence[float]) -> float:
    def score(names: Sequence[str]) -> float:
        fa = fit_transfer(a, names, q_starts=q_starts)
        fb = fit_transfer(b, names, q_starts=q_starts)
        return (evaluate_chi2(b, q=fa.q, gain=fa.gain, effects=fa.effects)
                + evaluate_chi2(a, q=fb.q, gain=fb.gain, effects=fb.effects))
    s0 = score(base)
    s1 = score(cand)
    return float(1.0 - s1 / max(s0, 1e-300))


def select_blur(full: SpectralData, half_a: SpectralData | None, half_b: SpectralData | None, *,
                candidates: Sequence[str] = BLUR_EFFECTS, q_starts: Sequence[float] = (1.5,),
                max_effects: int = 3, min_delta_bic: float = MIN_DELTA_BIC,
                min_heldout_gain: float = MIN_HELDOUT_GAIN) -> BlurSelection:
    """Forward selection of blur effects on the measured transfer function.

    Parameters
    ----------
    full
        Spectra over all usable blocks.
    half_a, half_b
        Spectra of the two halves of the scene for held-out validation (``None``: skip
        the held-out test, e.g. on a scene too small to split).
    q_starts
        Starting values of Q for the fits.
    """
    n_values = 2 * full.t_real.size
    null = fit_transfer(full, [], q_starts=q_starts)
    current: list[str] = []
    cur_fit = null
    sel = BlurSelection(null=null, final=null)
    while len(current) < max_effects:
        remaining = [c for c in candidates if c not in current]
        if not remaining:
            break
        fits = {c: fit_transfer(full, current + [c], q_starts=(cur_fit.q, *q_starts))
                for c in remaining}
        dbics = {c: delta_bic(cur_fit, f, n_values) for c, f in fits.items()}
        sel.tried.update(dbics)
        for c, f in fits.items():
            # a parameter pinned at a bound means the effect is standing in for a shape it
            # does not have: never claim it under its name
            if _at_bound(c, f.effects.get(c, {})):
                sel.at_bound.add(c)
                dbics[c] = -np.inf
        best = max(dbics, key=dbics.__getitem__)
        if dbics[best] < min_delta_bic:
            break
        gain = (_heldout_gain(half_a, half_b, current, current + [best], (cur_fit.q,))
                if half_a is not None and half_b is not None else float("nan"))
        if np.isfinite(gain) and gain < min_heldout_gain:
            break
        alts = [c for c, d in dbics.items()
                if c != best and d >= min_delta_bic and dbics[best] - d < AMBIGUITY_BIC]
        current.append(best)
        cur_fit = fits[best]
        sel.steps.append(Step(best, dbics[best], gain, alts, cur_fit))
    sel.final = cur_fit
    return sel


def select_radiometry(rad: RadiometryFit, *, corr_px2: float = 4.0) -> dict[str, object]:
    """Choose between no radiometric effect, ``colour_response`` and ``haze``.

    BIC on the image-domain residuals with n/corr_px2 independent samples:
    identity (0 parameters), per-band gain (3), per-band gain and offset (6). The
    affine model is called ``haze`` when the offsets are positive and gains ≤ HAZE_MAX_GAIN
    (path radiance, contrast loss); otherwise it is a ``colour_response`` with an
    offset.

    Returns
    -------
    dict
        ``{"name": None | "haze" | "colour_response", "params": {...}, "delta_bic": float,
        "bic": {"identity":…, "gain":…, "affine":…}}``
    """
    n = rad.n
    n_ind = max(n / corr_px2, 3.0)
    bands = rad.gain.size

    def bic(rss: np.ndarray, k: int) -> float:
        return float(n_ind * np.log(max(rss.sum(), 1e-12) / n) + k * np.log(n_ind))

    b_id = bic(rad.rss_identity, 0)
    b_g = bic(rad.rss_gain_only, bands)
    b_a = bic(rad.rss_affine, 2 * bands)
    out: dict[str, object] = {"bic": {"identity": b_id, "gain": b_g, "affine": b_a}}
    best = min(("identity", b_id), ("gain", b_g), ("affine", b_a), key=lambda t: t[1])[0]
    material_affine = bool(np.max(rad.correction_rms(rad.gain, rad.offset_dn))
                           >= MIN_RADIOMETRIC_DN)
    material_gain = bool(np.max(rad.correction_rms(rad.gain_only, np.zeros_like(rad.gain)))
                         >= MIN_RADIOMETRIC_DN)
    if best == "affine" and not material_affine:
        best = "gain" if b_g < b_id else "identity"
    if best == "gain" and not material_gain:
        best = "identity"
    if best == "identity" or b_id - min(b_g, b_a) < MIN_DELTA_BIC:
        out.update(name=None, params={}, delta_bic=float(b_id - min(b_g, b_a)))
        return out
    if best == "affine" and b_g - b_a >= MIN_DELTA_BIC:
        haze_like = bool(np.all(rad.offset_dn > -2 * rad.offset_sigma)
                         and np.mean(rad.offset_dn) > 0 and np.all(rad.gain <= HAZE_MAX_GAIN))
        if haze_like:
            out.update(name="haze", params={
                "transmission": [float(v) for v in rad.gain],
                "path_radiance_dn": [float(v) for v in rad.offset_dn]},
                sigmas={"transmission": [float(v) for v in rad.gain_sigma],
                        "path_radiance_dn": [float(v) for v in rad.offset_sigma]},
                delta_bic=float(b_id - b_a))
        else:
            out.update(name="colour_response", params={
                "gain": [float(v) for v in rad.gain],
                "offset_dn": [float(v) for v in rad.offset_dn]},
                sigmas={"gain": [float(v) for v in rad.gain_sigma],
                        "offset_dn": [float(v) for v in rad.offset_sigma]},
                delta_bic=float(b_id - b_a))
        return out
    out.update(name="colour_response", params={"gain": [float(v) for v in rad.gain_only]},
               sigmas={"gain": [float(v) for v in rad.gain_sigma]},
               delta_bic=float(b_id - b_g))
    return out

