"""Which effects does the evidence carry?

Blur effects are chosen by forward selection on the measured transfer function,
judged by **out-of-sample prediction**: neighbouring pixels (and neighbouring
frequency bins of a windowed spectrum) are not independent, so a likelihood that
counts them as independent overstates every effect. The scene's Welch blocks are
grouped into spatial folds (quadrants); a model is fitted on all folds but one and
scored (χ² of the transfer) on the held-out fold, for every fold in turn. At each step
every remaining candidate is fitted jointly with Q, the gain and the effects already
chosen; the best is accepted only when

* it lowers the cross-validated χ² by at least ``MIN_CV_GAIN`` (relative),
* its parameter is clearly away from its null (``EFFECT_SIZE``: e.g. a smear of at least
  0.8 px, a detector at least 0.5 px wide) and not pinned at a bound, and
* its ΔBIC on all blocks is at least ``MIN_DELTA_BIC`` (reported as evidence).

Effects of one family (isotropic roll-offs: ``detector_integration`` and
``atmospheric_blur``; anisotropic: ``motion_smear`` and ``off_nadir_anisotropy``) are never
claimed together: the best is claimed and those of its family that predict the held-out
blocks within ``AMBIGUITY_CV`` of it are listed as alternatives with their scores.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from geosim.diagnose.effects import BLUR_EFFECTS, get_effect
from geosim.diagnose.fit import (
    RadiometryFit,
    SpectralData,
    TransferFit,
    evaluate_chi2,
    fit_transfer,
)
from geosim.diagnose.model import RadiometryChoice

__all__ = ["BlurSelection", "Alternative", "AcceptedEffect", "select_blur", "delta_bic",
           "replace_step",
           "bic_evidence",
           "select_radiometry", "cv_chi2", "at_bound", "clearly_present", "plausible",
           "MIN_DELTA_BIC", "MIN_CV_GAIN", "AMBIGUITY_CV", "EFFECT_SIZE", "EFFECT_MAX",
           "BLUR_FAMILY"]

MIN_DELTA_BIC = 10.0
#: smallest radiometric correction worth claiming: RMS change of the image in some band, DN
MIN_RADIOMETRIC_DN = 1.0
#: effect size of a radiometric name (round 5): a per-band gain (or transmission) at least
#: this far from 1 in some band. A white-balance or exposure difference this small is
#: within what two cameras' calibrations leave, and the gain fitted on a model that lacks
#: a blur or noise moves by ~1 % (a 0.8 % colour response was claimed for a motion smear)
COLOUR_MIN_GAIN_DEV = 0.03
#: ... or an offset (path radiance, dark level) at least this many DN
RADIOMETRIC_MIN_OFFSET_DN = 2.0
#: haze over colour response when the two tie: mean z of the (positive) offsets
HAZE_OFFSET_Z = 3.0
#: largest per-band gain still called haze (white-balance differences between the UAV camera
#: and the satellite can lift one band slightly above 1 while path radiance adds offsets)
HAZE_MAX_GAIN = 1.05
#: relative drop of the cross-validated χ² an effect must bring (set on the development half
#: and the sample site, where changed content lowers the coherence and a real 0.9 px smear
#: gains 2–4 %)
MIN_CV_GAIN = 0.02
#: alternatives: same-family effects whose CV gain is within this fraction of the winner's
AMBIGUITY_CV = 0.25
#: (parameter, smallest or largest value that is clearly away from the effect's null)
EFFECT_SIZE: dict[str, tuple[str, str, float]] = {
    "detector_integration": ("pitch_px", ">=", 0.5),
    # f0 0.65 leaves half the contrast at Nyquist (0.52). Set on the development half:
    # atmospheres found right were fitted at f0 0.42-0.55; weaker ones (0.75-0.79) stood in
    # for what the model missed elsewhere (a JPEG quality estimated too high, resampling, a
    # short smear), never for a real atmosphere
    "atmospheric_blur": ("f0_cyc_per_px", "<=", 0.65),
    "motion_smear": ("length_px", ">=", 0.8),
    # the σ of a 0.8 px box (0.8/√12): the same size limit as the smear's
    "off_nadir_anisotropy": ("sigma_px", ">=", 0.23),
    "resampling": ("native_pitch_px", ">=", 1.15),
}
#: (parameter, largest physically plausible value): beyond it the effect stands in for
#: another. A detector integrates over its own element, which cannot be wider than the
#: native sampling pitch; an aperture wider than two product pixels means the product grid
#: is finer than the native sampling, i.e. ``resampling`` (whose signature, the roll-off
#: above the native Nyquist, such a wide sinc imitates)
EFFECT_MAX: dict[str, tuple[str, float]] = {
    "detector_integration": ("pitch_px", 2.0),
}
#: blur families: effects one measured transfer function cannot tell apart reliably
BLUR_FAMILY: dict[str, str] = {
    "detector_integration": "isotropic", "atmospheric_blur": "isotropic",
    "motion_smear": "anisotropic", "off_nadir_anisotropy": "anisotropic",
    "resampling": "sampling",
}


def delta_bic(without: TransferFit, with_: TransferFit, n_values: int) -> float:
    """BIC(without) − BIC(with), residual variance scale estimated from the larger model."""
    dof = max(n_values - with_.n_params, 1)
    scale = max(1.0, with_.chi2 / (dof * 1.0))
    return float(without.bic(scale) - with_.bic(scale))


@dataclass
class Alternative:
    """A same-family effect that predicts the held-out blocks about as well.

    ``delta_bic``: its exact fit's BIC on all blocks minus the claimed member's (≥ 0; the
    member with the lower one is claimed), where the exact duel named the claim; else None.
    """

    name: str
    cv_gain: float
    params: dict[str, float]
    delta_bic: float | None = None


def bic_evidence(delta_bic: float) -> str:
    """How strongly a BIC difference favours one model (Kass & Raftery, 1995, §3.2)."""
    if delta_bic < 2.0:
        return "not worth more than a bare mention"
    if delta_bic < 6.0:
        return "positive"
    return "strong" if delta_bic < 10.0 else "very strong"


@dataclass
class AcceptedEffect:
    """One accepted effect with its evidence (``heldout_gain`` = relative CV χ² drop)."""

    name: str
    delta_bic: float
    heldout_gain: float
    alternatives: list[Alternative]
    fit: TransferFit
    #: statistics of a test that renamed the effect after the selection (the claim's
    #: ``test`` in diagnosis.json); None: named by the selection
    test: dict[str, Any] | None = None


@dataclass
class BlurSelection:
    """Outcome of :func:`select_blur`."""

    null: TransferFit
    final: TransferFit
    steps: list[AcceptedEffect] = field(default_factory=list)
    tried: dict[str, float] = field(default_factory=dict)   # last ΔBIC of each candidate
    cv_gain: dict[str, float] = field(default_factory=dict)  # last CV gain of each candidate
    at_bound: set[str] = field(default_factory=set)          # fits pinned at a bound
    too_small: set[str] = field(default_factory=set)         # fits too close to the null
    implausible: set[str] = field(default_factory=set)       # fits beyond EFFECT_MAX


def replace_step(sel: BlurSelection, k: int, step: AcceptedEffect,
                 final: TransferFit | None = None) -> None:
    """Put ``step`` in place of step ``k`` of ``sel`` (a member of the same family named
    instead): later steps' fits hold it under its name and with its parameters in place of
    the replaced one's; ``final``: the selection's final fit (None: the replaced member
    renamed in the current one, or ``step.fit`` where step ``k`` is the last)."""
    old = sel.steps[k].name
    new = dict(step.fit.effects[step.name])

    def renamed(fit: TransferFit) -> TransferFit:
        return replace(fit, effects={(step.name if n == old else n): (new if n == old else p)
                                     for n, p in fit.effects.items()})

    sel.steps[k] = step
    for j in range(k + 1, len(sel.steps)):
        sel.steps[j] = replace(sel.steps[j], fit=renamed(sel.steps[j].fit))
    if final is not None:
        sel.final = final
    else:
        sel.final = step.fit if k == len(sel.steps) - 1 else renamed(sel.final)


def at_bound(name: str, params: dict[str, float], rel: float = 0.01) -> bool:
    for spec in get_effect(name).params:
        if spec.periodic or spec.nuisance or spec.name not in params:
            continue
        span = spec.upper - spec.lower
        v = params[spec.name]
        if v - spec.lower < rel * span or spec.upper - v < rel * span:
            return True
    return False


def clearly_present(name: str, params: dict[str, float]) -> bool:
    """The effect-size rule: the fitted parameter is clearly away from the null."""
    rule = EFFECT_SIZE.get(name)
    if rule is None or rule[0] not in params:
        return True
    key, op, limit = rule
    return params[key] >= limit if op == ">=" else params[key] <= limit


def plausible(name: str, params: dict[str, float]) -> bool:
    """The fitted parameter is within the effect's physical range (:data:`EFFECT_MAX`)."""
    rule = EFFECT_MAX.get(name)
    return rule is None or rule[0] not in params or params[rule[0]] <= rule[1]


Folds = Sequence[tuple[SpectralData, SpectralData]]


def cv_chi2(folds: Folds, names: Sequence[str], start: TransferFit) -> float:
    """Σ over folds of the held-out χ² of a model fitted on the other folds."""
    total = 0.0
    for train, test in folds:
        f = fit_transfer(train, names, q_starts=(start.q,), start=start)
        total += evaluate_chi2(test, q=f.q, gain=f.gain, effects=f.effects)
    return total


def select_blur(full: SpectralData, folds: Folds | None = None, *,
                candidates: Sequence[str] = BLUR_EFFECTS, q_starts: Sequence[float] = (1.5,),
                max_effects: int = 3, min_delta_bic: float = MIN_DELTA_BIC,
                min_cv_gain: float = MIN_CV_GAIN) -> BlurSelection:
    """Forward selection of blur effects on the measured transfer function.

    Parameters
    ----------
    full
        Spectra over all usable blocks.
    folds
        (training, held-out) spectra of a block cross-validation; ``None`` or empty: the
        out-of-sample test is skipped (e.g. a scene too small to split) and only ΔBIC
        and the effect-size rule decide.
    q_starts
        Starting values of Q for the fits.
    """
    folds = list(folds or [])
    n_values = 2 * full.t_real.size
    null = fit_transfer(full, [], q_starts=q_starts)
    current: list[str] = []
    cur_fit = null
    cur_cv = cv_chi2(folds, [], null) if folds else float("nan")
    sel = BlurSelection(null=null, final=null)
    while len(current) < max_effects:
        taken = {BLUR_FAMILY.get(c, c) for c in current}
        remaining = [c for c in candidates
                     if c not in current and BLUR_FAMILY.get(c, c) not in taken]
        if not remaining:
            break
        fits = {c: fit_transfer(full, current + [c], q_starts=(cur_fit.q, *q_starts))
                for c in remaining}
        dbics = {c: delta_bic(cur_fit, f, n_values) for c, f in fits.items()}
        sel.tried.update(dbics)
        ok = {}
        for c, f in fits.items():
            # a parameter pinned at a bound means the effect is standing in for a shape it
            # does not have; one at its null is no effect: never claim either by name
            if at_bound(c, f.effects.get(c, {})):
                sel.at_bound.add(c)
            elif not clearly_present(c, f.effects.get(c, {})):
                sel.too_small.add(c)
            elif not plausible(c, f.effects.get(c, {})):
                sel.implausible.add(c)
            elif dbics[c] >= min_delta_bic:
                ok[c] = f
        if not ok:
            break
        gains = {c: (1.0 - cv_chi2(folds, current + [c], f) / max(cur_cv, 1e-300)
                     if folds else float("nan")) for c, f in ok.items()}
        sel.cv_gain.update(gains)
        best = (max(gains, key=gains.__getitem__) if folds
                else max(ok, key=dbics.__getitem__))
        if folds and gains[best] < min_cv_gain:
            break
        fam = BLUR_FAMILY.get(best, best)
        alts = [Alternative(c, float(gains[c]), dict(ok[c].effects[c])) for c in ok
                if c != best and BLUR_FAMILY.get(c, c) == fam and folds
                and gains[c] >= min_cv_gain and gains[best] - gains[c]
                <= AMBIGUITY_CV * gains[best]]
        current.append(best)
        cur_fit = fits[best]
        if folds:
            cur_cv = cur_cv * (1.0 - gains[best])
        sel.steps.append(AcceptedEffect(best, dbics[best], float(gains[best]), alts, cur_fit))
    sel.final = cur_fit
    return sel


def _colour_size(gain: np.ndarray, offset_dn: np.ndarray | None = None) -> bool:
    """Effect-size rule of ``colour_response``: some band's gain ≥ COLOUR_MIN_GAIN_DEV from 1
    (or, affine, some offset ≥ RADIOMETRIC_MIN_OFFSET_DN from 0)."""
    big_offset = offset_dn is not None and float(np.max(np.abs(offset_dn))) \
        >= RADIOMETRIC_MIN_OFFSET_DN
    return bool(float(np.max(np.abs(np.asarray(gain) - 1.0))) >= COLOUR_MIN_GAIN_DEV
                or big_offset)


def _offsets_significant(rad: RadiometryFit) -> bool:
    """Haze's own trace: path radiance, offsets positive in every band and jointly
    HAZE_OFFSET_Z standard errors above zero (one-sided mean of the per-band z)."""
    z = rad.offset_dn / np.maximum(rad.offset_sigma, 1e-9)
    return bool(np.all(z > 0) and float(np.mean(z)) >= HAZE_OFFSET_Z)


def select_radiometry(rad: RadiometryFit, *, corr_px2: float = 4.0) -> RadiometryChoice:
    """Choose between no radiometric effect, ``colour_response`` and ``haze``.

    BIC on the image-domain residuals with n/corr_px2 independent samples:
    identity (0 parameters), per-band gain (3), per-band gain and offset (6). The
    affine model is called ``haze`` when the offsets are positive, some band's is at least
    RADIOMETRIC_MIN_OFFSET_DN (path radiance measured, its effect size; since round 31) and
    gains ≤ HAZE_MAX_GAIN (contrast loss); otherwise it is a ``colour_response`` with an
    offset. A name is claimed only when its parameters are clearly away from the null
    (effect size: a gain ≥ 3 % from 1, or an offset ≥ 2 DN; round 5).

    Over a narrow brightness range a per-band gain and a transmission + path radiance
    describe the same pixels (T·x + P ≈ (T + P/x̄)·x): when the gain-only and the affine
    models are within MIN_DELTA_BIC of each other, both names are listed, the one claimed
    being haze only where the affine fit's offsets are significantly positive (path
    radiance measured, not just allowed) and the other under ``alternatives``.

    Parameters
    ----------
    rad : RadiometryFit
        Gain-only, affine and identity fits of the model to the scene (residuals in DN²).
    corr_px2 : float
        Area of one independent sample, px² (pixels per independent residual).

    Returns
    -------
    RadiometryChoice
        ``name`` None, ``"haze"`` or ``"colour_response"``; ``params`` and ``sigmas`` per
        band (gain / transmission unitless, offsets in DN; both empty when nothing is
        claimed); ``delta_bic`` of the claimed (or best) model over the identity; ``bic``
        of ``"identity"``, ``"gain"`` and ``"affine"``; ``alternatives`` the tied other
        name (``name``, ``params``, ``delta_bic``), listed, never claimed.
    """
    n = rad.n
    n_ind = max(n / corr_px2, 3.0)
    bands = rad.gain.size

    def bic(rss: np.ndarray, k: int) -> float:
        return float(n_ind * np.log(max(rss.sum(), 1e-12) / n) + k * np.log(n_ind))

    b_id = bic(rad.rss_identity, 0)
    b_g = bic(rad.rss_gain_only, bands)
    b_a = bic(rad.rss_affine, 2 * bands)
    bics = {"identity": b_id, "gain": b_g, "affine": b_a}
    # haze is told from a colour response by its path radiance alone: the affine fit is
    # haze only where that is clearly away from its null (RADIOMETRIC_MIN_OFFSET_DN in
    # some band); gains below 1 with offsets of a fraction of a DN are a colour response
    # (development c263, c937: per-band gains 0.82-0.95 claimed as haze with path
    # radiance 0.1-0.5 DN; a haze adds several DN, 7.8-15 on the sample site)
    haze_like = bool(np.all(rad.offset_dn > -2 * rad.offset_sigma)
                     and np.mean(rad.offset_dn) > 0 and np.all(rad.gain <= HAZE_MAX_GAIN)
                     and float(np.max(rad.offset_dn)) >= RADIOMETRIC_MIN_OFFSET_DN)
    # each model on its own: better than the identity by MIN_DELTA_BIC, a material change
    # of the image, and its name's effect size
    ok_g = bool(b_id - b_g >= MIN_DELTA_BIC
                and np.max(rad.correction_rms(rad.gain_only, np.zeros_like(rad.gain)))
                >= MIN_RADIOMETRIC_DN and _colour_size(rad.gain_only))
    ok_a = bool(b_id - b_a >= MIN_DELTA_BIC
                and np.max(rad.correction_rms(rad.gain, rad.offset_dn)) >= MIN_RADIOMETRIC_DN
                # haze's effect size (path radiance ≥ RADIOMETRIC_MIN_OFFSET_DN) is part
                # of haze_like; a colour response with an offset has its own
                and (haze_like or _colour_size(rad.gain, rad.offset_dn)))
    # the affine fit is haze (transmission, path radiance) or a colour response with an
    # offset (gain, offset): the same numbers under the name's own parameter names
    name_a, gain_key, offset_key = (("haze", "transmission", "path_radiance_dn") if haze_like
                                    else ("colour_response", "gain", "offset_dn"))
    affine: dict[str, Any] = {
        "name": name_a,
        "params": {gain_key: [float(v) for v in rad.gain],
                   offset_key: [float(v) for v in rad.offset_dn]},
        "sigmas": {gain_key: [float(v) for v in rad.gain_sigma],
                   offset_key: [float(v) for v in rad.offset_sigma]},
        "delta_bic": float(b_id - b_a)}
    gain_only: dict[str, Any] = {"name": "colour_response",
                                 "params": {"gain": [float(v) for v in rad.gain_only]},
                                 "sigmas": {"gain": [float(v) for v in rad.gain_sigma]},
                                 "delta_bic": float(b_id - b_g)}
    # which model the data prefer: decisively (MIN_DELTA_BIC) or a tie, where haze is
    # preferred only with its path radiance measured; the preferred one is claimed if it
    # passes its own checks (no fallback to the other: the data did not prefer it)
    if b_g - b_a >= MIN_DELTA_BIC:
        first, second, ok_first, ok_second = affine, None, ok_a, False
    elif b_a - b_g >= MIN_DELTA_BIC:
        first, second, ok_first, ok_second = gain_only, None, ok_g, False
    elif haze_like and _offsets_significant(rad):
        first, second, ok_first, ok_second = affine, gain_only, ok_a, ok_g
    else:
        first, second, ok_first, ok_second = gain_only, affine, ok_g, ok_a
    if not ok_first:
        return RadiometryChoice(name=None, params={}, sigmas={},
                                delta_bic=float(b_id - min(b_g, b_a)), bic=bics)
    alternatives: list[dict[str, Any]] = []
    if second is not None and ok_second and second["name"] != first["name"]:
        alternatives = [{"name": second["name"], "params": second["params"],
                         "delta_bic": second["delta_bic"]}]
    return RadiometryChoice(name=first["name"], params=first["params"], sigmas=first["sigmas"],
                            delta_bic=first["delta_bic"], bic=bics, alternatives=alternatives)
