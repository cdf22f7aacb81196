"""An anisotropic blur, alone or beside the model's other blurs, by its trace in the pixels
(:func:`pixel_anisotropic`).

Where the model holds no blur and no JPEG, a small anisotropic blur (an off-nadir
elongation, a motion smear) at high Q changes the measured transfer by less than a claim
needs along one direction and by nothing across it; Q takes up its mean and the rest is
left. On the development half (round 41's rows) 23 lone anisotropic blurs at Q 2.0–4.5,
noise-free and without JPEG, were missed (12) or named as the other member (11) although
the ideal observer's Δχ² was 900–7.5e4 (c979: the transfer's limit at its Q 0.57 px, the
blur 0.56 px).

In the pixels the blur's second moment is an anisotropic term the model cannot make with
Q: to second order a blur of covariance Σ (px²) adds ½ Σ : ∇∇I to the image, and the
traceless part of Σ is independent of any isotropic change (Q). So the test is first a
linear one (:func:`anisotropy_screen`): the residual against the model regressed on the
rendered image's second differences (the Laplacian with Q's change, then (∂xx − ∂yy) and
2∂xy), fitted on one half of the evaluation pixels and scored on the other, for three
splits (a checkerboard, left / right, top / bottom: a blur acts the same everywhere, while
a misfit that happens to take this shape — development c169's moved objects at Q 4.46 —
sits in some places, and one half's fit then fails the other: −333 top / bottom). Only
where all six held-out Δχ² reach :data:`SCREEN_MIN_DCHI2` is the blur fitted
(:func:`shape_fit`: Q, width and direction, Nelder–Mead from the screen's estimate, on one
half) and judged by its held-out drop of the other half's residual, which must reach
:data:`ANISO_PIXEL_MIN_DCHI2` both ways round against Q alone (scanned on the same half).
The two shapes agree to second order, so the member claimed is the one of lower residual
over both halves that can be claimed (:func:`first_claimable`) and the other is listed as
an alternative where it passes the same test.

Since round 46 the same test runs where the model holds other blurs (a resampling, a
detector, an atmosphere; still no anisotropic member and no JPEG): beside them the
transfer's limit is higher still (fresh c1441: a 1.95 px smear beside a resampling at Q
3.86 stated untestable, limit 2.31 px, ideal Δχ² 1.2e4). Their isotropic second moments
leave the traceless terms alone, so the screen is the same, rendered with them; the fits
hold them at the transfer's values, and the test runs there only at Q ≥
:data:`BESIDE_MIN_Q`. On the development half's 290 rows of that domain (round 46) the
screen's smallest drop reached at most 4.5 at Q ≥ 2 where no anisotropic blur was in the
scene, so the thresholds stay the lone test's (``docs/diagnosis.md``, round 46).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from geosim.diagnose.context import EvalContext
from geosim.diagnose.fit import fit_transfer
from geosim.diagnose.grey_render import grey_expected
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.select import Alternative, BlurSelection, clearly_present
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs
from geosim.diagnose.stage_resampling_coherent import (
    append_pixel_step,
    checker_halves,
    eval_halves,
    heldout_drop,
    heldout_gain,
    rss_on_halves,
    top_bottom_halves,
)
from geosim.diagnose.stage_withdraw import no_worse_than_baseline

__all__ = ["pixel_anisotropic", "anisotropy_screen", "second_differences", "shape_fit",
           "fit_on_half", "claimable", "first_claimable", "screen_splits", "in_domain",
           "Screen", "ShapeFit", "SHAPES", "SCREEN_MIN_DCHI2", "ANISO_PIXEL_MIN_DCHI2",
           "Q_FACTORS", "MAX_EVALUATIONS", "BESIDE_MIN_Q"]

#: held-out drop of the residual sum of squares the linear screen must show on each half
#: of each split before the blur is fitted, in units of that half's residual variance per
#: pixel. Set on the development half (round 42; 307 scenes of the stage's domain, every
#: one at Q ≥ 3.32, checkerboard split): of the 276 without an anisotropic blur (124
#: controls, at most 2.8) the highest were c169 85 (moved objects at Q 4.46; −333 top /
#: bottom) and c107 5.3; of the 31 with one, 14 reached 25 (c293 1250 … c1314 26), the
#: noisy ones 26–38
SCREEN_MIN_DCHI2 = 25.0
#: held-out drop the fitted blur must bring on each checkerboard colour, in the same units
#: (as :data:`~geosim.diagnose.stage_isotropic_pixels.ISO_PIXEL_MIN_DCHI2`). Development:
#: c169's fit (had it passed the screen) 159; of the 14 blurs through the screen 10 reached
#: it (c337 154 the lowest), c1266 80 and the three beside noise 34–35 did not
ANISO_PIXEL_MIN_DCHI2 = 100.0


@dataclass(frozen=True)
class Shape:
    """A member of the anisotropic family as the pixel test fits it.

    Attributes
    ----------
    width_key, direction_key
        Its width parameter (px on the product grid) and direction parameter (degrees
        clockwise from grid north) in the model's blur dictionary.
    bounds_px
        The widths fitted; a fit at either bound is not claimed.
    variance_per_width2
        Its second moment along the direction per squared width (1 for a Gaussian's σ,
        1/12 for a box's length).
    """

    width_key: str
    direction_key: str
    bounds_px: tuple[float, float]
    variance_per_width2: float


SHAPES: dict[str, Shape] = {
    "off_nadir_anisotropy": Shape("sigma_px", "azimuth_deg", (0.05, 1.5), 1.0),
    "motion_smear": Shape("length_px", "direction_deg", (0.2, 4.0), 1.0 / 12.0),
}
#: factors on the model's Q scanned in the pixels for the model without the blur
Q_FACTORS = tuple(float(f) for f in np.round(np.arange(0.80, 1.2001, 0.02), 2))
#: renders of one shape's Nelder–Mead fit on one half
MAX_EVALUATIONS = 60
#: the model's lowest Q at which the test runs beside its other blurs: from Q 2 the optics
#: cut off below the product grid's Nyquist frequency, so the rendered image's second
#: differences are its derivatives; below it a resampling's aliasing misfit can take the
#: traceless shape (development c906: beside a resampling at Q 1.15, the screen's smallest
#: drop 22 and a smear's fits 107 / 112 with no anisotropic blur in the scene). Round 46,
#: 290 development rows of the domain: the 161 at Q ≥ 2 without an anisotropic blur reach
#: at most 4.5, the three blurs the screen flagged there 41–1136; below Q 2 none passed
BESIDE_MIN_Q = 2.0


@dataclass(frozen=True)
class Screen:
    """The linear screen of :func:`anisotropy_screen`.

    Attributes
    ----------
    dchi2
        Held-out drop on each half of each split (fitted on the other half), in units of
        that half's residual variance per pixel.
    variance_px2
        The anisotropic blur's second moment along its direction (px², product grid),
        from the fit on both halves of the first split.
    direction_deg
        Its direction, clockwise from grid north, in [0, 180).
    """

    dchi2: list[float]
    variance_px2: float
    direction_deg: float


@dataclass(frozen=True)
class ShapeFit:
    """One shape fitted on each half: the fitted models, their [RSS on each half, DN²],
    and the held-out drop against Q alone on each half (fitted on the other)."""

    name: str
    models: list[ForwardModel]
    rss: list[list[float]]
    dchi2: list[float]

    def best(self) -> tuple[ForwardModel, float]:
        """The fitted model of lowest RSS over both halves and that RSS (DN²)."""
        k = int(np.argmin([sum(r) for r in self.rss]))
        return self.models[k], float(sum(self.rss[k]))


def second_differences(image: np.ndarray) -> np.ndarray:
    """(∂xx + ∂yy, ∂xx − ∂yy, 2∂xy) of ``image`` (rows × cols) by central differences,
    x along columns, y along rows; the outermost pixels take their neighbours' values."""
    p = np.pad(image, 1, mode="edge")
    dxx = p[1:-1, 2:] - 2.0 * p[1:-1, 1:-1] + p[1:-1, :-2]
    dyy = p[2:, 1:-1] - 2.0 * p[1:-1, 1:-1] + p[:-2, 1:-1]
    dxy = (p[2:, 2:] - p[2:, :-2] - p[:-2, 2:] + p[:-2, :-2]) / 4.0
    return np.stack([dxx + dyy, dxx - dyy, 2.0 * dxy])


def anisotropy_screen(residual: np.ndarray, rendered: np.ndarray,
                      splits: list[list[np.ndarray]]) -> Screen:
    """The held-out evidence for an anisotropic second moment in ``residual`` (real − model,
    DN) given the model's ``rendered`` image (DN), on each split of the pixels into two
    disjoint halves (each fitted on one half, scored on the other, both ways round).

    To second order a blur of covariance Σ adds ½ Σ : ∇∇I: with Σ = s·1 + traceless part,
    ½ s ∇²I (which a change of Q also makes) + d/2 (∂xx − ∂yy) + Σxy/2 · 2∂xy, where
    d = (Σxx − Σyy)/2. The base regression holds a constant and the Laplacian, the
    alternative also the two traceless terms. For a blur of variance v² along the unit
    vector (col, row) = (sin θ, −cos θ) (:mod:`geosim.physics.otf`'s convention),
    d = −v² cos 2θ / 2 and Σxy = −v² sin 2θ / 2."""
    d2 = second_differences(rendered)
    ones = np.ones_like(rendered)
    columns = np.stack([ones, d2[0], d2[1], d2[2]])

    def coefficients(mask: np.ndarray, n: int) -> np.ndarray:
        a = columns[:n, mask].T
        return np.linalg.lstsq(a, residual[mask], rcond=None)[0]

    def rss(mask: np.ndarray, coef: np.ndarray) -> float:
        fitted = np.tensordot(coef, columns[:len(coef), mask], axes=1)
        return float(np.sum((residual[mask] - fitted) ** 2))

    dchi2 = []
    for halves in splits:
        for k in (0, 1):
            fit, test = halves[k], halves[1 - k]
            base = rss(test, coefficients(fit, 2))
            alt = rss(test, coefficients(fit, 4))
            dchi2.append((base - alt) / max(base / int(test.sum()), 1e-12))
    both = splits[0][0] | splits[0][1]
    c = coefficients(both, 4)
    d, sxy = 2.0 * c[2], 2.0 * c[3]
    variance = 2.0 * float(np.hypot(d, sxy))
    direction = 0.5 * float(np.degrees(np.arctan2(-sxy, -d))) % 180.0
    return Screen(dchi2=dchi2, variance_px2=variance, direction_deg=direction)


def _q_scan(inp: Inputs, model: ForwardModel, halves: list[np.ndarray]) -> list[list[float]]:
    """[RSS on each half, DN²] of ``model`` at each of :data:`Q_FACTORS` on its Q."""
    return [rss_on_halves(inp, halves, model.without(q=model.q * f)) for f in Q_FACTORS]


def fit_on_half(inp: Inputs, model: ForwardModel, half: np.ndarray, name: str,
                variance_px2: float, direction_deg: float, q0: float,
                held: dict[str, dict[str, float]] | None = None) -> ForwardModel:
    """``name`` (a key of :data:`SHAPES`) fitted on the pixels ``half`` by Nelder–Mead on
    ln Q, its width (px) and its direction (degrees), started from Q ``q0``, the second
    moment ``variance_px2`` (px²) along ``direction_deg``; ``held``: the other blurs of the
    fitted model, held as they are (None: none). At most :data:`MAX_EVALUATIONS` renders."""
    shape = SHAPES[name]
    lo, hi = shape.bounds_px
    others = dict(held or {})

    def build(x: np.ndarray) -> ForwardModel:
        return model.without(q=float(np.exp(x[0])), blur={**others, name: {
            shape.width_key: float(np.clip(x[1], lo, hi)),
            shape.direction_key: float(x[2]) % 180.0}})

    width0 = float(np.clip(np.sqrt(max(variance_px2, 0.0) / shape.variance_per_width2),
                           lo, hi))
    x0 = np.array([np.log(q0), width0, direction_deg])
    simplex = np.vstack([x0, x0 + np.diag([0.05, 0.25 * width0 + 0.1, 20.0])])
    res = minimize(lambda x: rss_on_halves(inp, [half], build(x))[0], x0,
                   method="Nelder-Mead",
                   options={"maxfev": MAX_EVALUATIONS, "initial_simplex": simplex})
    return build(res.x)


def shape_fit(inp: Inputs, model: ForwardModel, halves: list[np.ndarray], name: str,
              screen: Screen, base: list[list[float]]) -> ShapeFit:
    """``name`` (a key of :data:`SHAPES`) fitted alone on each half (:func:`fit_on_half`,
    started from the screen's second moment and direction and from the Q of ``base`` best
    on that half; the model's other blurs held as they are), and its held-out drop against
    the best of ``base`` (Q alone, :func:`_q_scan`) chosen on the same half."""
    models, rss, dchi2 = [], [], []
    for k in (0, 1):
        q0 = Q_FACTORS[int(np.argmin([r[k] for r in base]))] * model.q
        m = fit_on_half(inp, model, halves[k], name, screen.variance_px2,
                        screen.direction_deg, q0, held=model.blur)
        r = rss_on_halves(inp, halves, m)
        models.append(m)
        rss.append(r)
        # this half's fit scored on the other half against Q alone chosen on this one
        dchi2.append(heldout_drop(halves, base, [r])[k])
    return ShapeFit(name=name, models=models, rss=rss, dchi2=dchi2)


def screen_splits(ev: EvalContext) -> list[list[np.ndarray]] | None:
    """The screen's three splits of the evaluation pixels (checkerboard first, whose
    colours the fits also use; left / right; top / bottom); None when a half is empty."""
    splits = [checker_halves(ev), eval_halves(ev), top_bottom_halves(ev)]
    return None if any(h is None for h in splits) else splits  # type: ignore[return-value]


def claimable(name: str, m: ForwardModel) -> bool:
    """Clearly away from its null and not at a bound of its fitted widths."""
    shape = SHAPES[name]
    width = float(m.blur[name][shape.width_key])
    lo, hi = shape.bounds_px
    return (clearly_present(name, {shape.width_key: width})
            and not (np.isclose(width, lo) or np.isclose(width, hi)))


def first_claimable(passing: list[ShapeFit], ok: Callable[[ForwardModel], bool]
                    ) -> ShapeFit | None:
    """Of the fits that passed the held-out test, in order of their RSS over both halves,
    the first whose best model is :func:`claimable` and accepted by ``ok`` (the engine's:
    its delivered simulation fits no worse than the baseline); None when none is.

    Both members passed, so the pixels did not tell them apart; a member whose delivered
    simulation fits worse is no refinement, and the other may be (development c136: a
    smear beside a misregistration, whose off-nadir fit had the lower RSS and failed the
    spectrum)."""
    return next((f for f in sorted(passing, key=lambda f: f.best()[1])
                 if claimable(f.name, f.best()[0]) and ok(f.best()[0])), None)


def in_domain(model: ForwardModel) -> bool:
    """Whether :func:`pixel_anisotropic` tests ``model``: no anisotropic member, no JPEG,
    and other blurs only at Q ≥ :data:`BESIDE_MIN_Q`."""
    return not (set(model.blur) & set(SHAPES) or model.compression is not None
                or (model.blur and model.q < BESIDE_MIN_Q))


def pixel_anisotropic(inp: Inputs, model: ForwardModel, sel: BlurSelection,
                      setup: SpectralSetup, ev: EvalContext,
                      candidates: tuple[str, ...]) -> ForwardModel:
    """An anisotropic blur claimed by its trace in the pixels, alone or beside the model's
    other blurs.

    Tested only where the model holds no anisotropic member and no JPEG (whose quantisation
    is not independent of the image); the model's other blurs (a resampling, a detector,
    an atmosphere) are rendered in the screen and held as they are in the fits, and tested
    beside them only at Q ≥ :data:`BESIDE_MIN_Q`. The claim's step records
    ``heldout_gain`` as the weaker half's held-out drop of the residual sum of squares
    (fraction); its fit is the transfer fit with the chosen blur and the others held at the
    chosen Q."""
    members = [n for n in SHAPES if n in candidates]
    if not members or not in_domain(model):
        return model
    splits = screen_splits(ev)
    if splits is None:
        return model
    halves = splits[0]
    rendered = grey_expected(inp, model)
    screen = anisotropy_screen(inp.grey - rendered, rendered, splits)
    if min(screen.dchi2) < SCREEN_MIN_DCHI2:
        return model
    base = _q_scan(inp, model, halves)
    fits = [shape_fit(inp, model, halves, n, screen, base) for n in members]
    passing = [f for f in fits if min(f.dchi2) >= ANISO_PIXEL_MIN_DCHI2]
    if not passing:
        return model
    chosen_fit = first_claimable(passing, no_worse_than_baseline(inp, ev))
    if chosen_fit is None:
        return model
    chosen, _ = chosen_fit.best()
    name = chosen_fit.name
    alternatives = [Alternative(f.name, heldout_gain(halves, f.dchi2),
                                {k: float(v) for k, v in f.best()[0].blur[f.name].items()})
                    for f in passing if f is not chosen_fit]
    # the transfer's χ² at the chosen Q (for the ΔBIC reported; the claim rests on the
    # pixels); the width's uncertainty from the two halves' fits (the split-half spread)
    key = SHAPES[name].width_key
    widths = [float(m.blur[name][key]) for m in chosen_fit.models]
    fit = fit_transfer(setup.full, [], fix_q=chosen.q, fixed=dict(chosen.blur))
    append_pixel_step(sel, setup, name, fit, {name: {key: abs(widths[0] - widths[1]) / 2.0}},
                      2, heldout_gain(halves, chosen_fit.dchi2), alternatives)
    return chosen
