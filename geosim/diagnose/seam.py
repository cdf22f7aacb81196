"""Exposure seams: a straight line across which the UAV mosaic's brightness steps.

Orthomosaics blend frames taken with different exposures; where the blending leaves a
seam, one side of a line is brighter by a constant factor in every band. Against the
satellite scene this gives *two* radiometric relations, ``real = t·x + L`` on one side
and ``real = t·k·x + L`` on the other. A single global gain/offset regression cannot
fit both: its robust consensus line threads between the two clusters and returns a
transmission that is far too low and a path radiance that is far too high (on the
sample site's flight PA2, a 7 % seam across half of the window turned t = 0.94 and
L = 9.9 DN in green into t = 0.63 and L = 44 DN).

:func:`find_gain_step` finds the line and the factor from the relative residual of a
global robust fit, so the haze fit can be done on a model corrected for the seam and the
seam is reported as a flight artefact instead of being absorbed into the satellite's haze.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from geosim.diagnose.fit import RadiometryFit, fit_radiometry
from geosim.physics.geometry import step_side

__all__ = ["GainStep", "find_gain_step", "step_side", "MIN_STEP", "MIN_SIDE_FRACTION",
           "MIN_EXPLAINED"]

#: smallest exposure step worth claiming (|factor − 1|), dimensionless (2 % ≈ 2 DN at 100 DN)
MIN_STEP = 0.02
#: smallest share of the fit pixels on either side of the line
MIN_SIDE_FRACTION = 0.1
#: smallest share of the robust relative-residual variance the step must explain (the true
#: seams of the sample site explain 0.29–0.53; scenes without a seam 0.03–0.09)
MIN_EXPLAINED = 0.15


@dataclass
class GainStep:
    """A straight seam with a gain step.

    Attributes
    ----------
    normal_deg
        Direction of the line's normal, degrees from the column axis toward the row axis
        (image axes, row down), in [0, 360).
    offset_px
        Signed distance of the line from the image centre along the normal, pixels.
    factor
        Multiply the model by this (≥ 1) on the stepped side (``side``) to match the rest:
        the stepped side is the darker one, so the haze fitted on the corrected model is
        relative to the brighter side of the seam (which side is the camera's nominal
        exposure cannot be told from the data; this choice keeps the transmission the lower
        of the two possible values, i.e. ≤ 1 when the haze is real).
    fraction
        Share of the fit pixels on the stepped side.
    delta_bic
        Evidence for the step: BIC without − BIC with (3 parameters).
    explained
        Share of the (robust) relative-residual variance the step explains.
    side
        Bool (rows, cols), True on the stepped side.
    """

    normal_deg: float
    offset_px: float
    factor: float
    fraction: float
    delta_bic: float
    explained: float
    side: np.ndarray

    def endpoints_px(self) -> list[list[float]]:
        """Two points (col, row) of the line where it meets the image's bounding circle."""
        rows, cols = self.side.shape
        th = np.radians(self.normal_deg)
        n = np.array([np.cos(th), np.sin(th)])
        c = np.array([cols / 2.0, rows / 2.0]) + self.offset_px * n
        d = np.array([-n[1], n[0]]) * 0.5 * float(np.hypot(rows, cols))
        return [list(map(float, c - d)), list(map(float, c + d))]


def _tukey(r: np.ndarray, scale: float, c: float = 4.685) -> np.ndarray:
    u = r / (c * scale)
    return np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)


def _line_search(rel: np.ndarray, mask: np.ndarray, *, n_angles: int, min_fraction: float
                 ) -> tuple[float, float, float, float]:
    """Best two-level split of ``rel`` (robust weights) by a straight line.

    Returns (normal angle rad, offset px, between-side weighted SS, total weighted SS).
    """
    rows, cols = mask.shape
    rr, cc = np.nonzero(mask)
    r = rel[rr, cc]
    loc = float(np.median(r))
    w = _tukey(r - loc, 1.4826 * float(np.median(np.abs(r - loc))) + 1e-9)
    yc, xc = rr + 0.5 - rows / 2.0, cc + 0.5 - cols / 2.0
    n = r.size
    lo, hi = int(min_fraction * n), n - int(min_fraction * n)
    best = (-np.inf, 0.0, 0.0)
    wr = w * r
    for th in np.linspace(0.0, np.pi, n_angles, endpoint=False):
        proj = xc * np.cos(th) + yc * np.sin(th)
        o = np.argsort(proj, kind="stable")
        cw, cwr = np.cumsum(w[o]), np.cumsum(wr[o])
        tw, twr = cw[-1], cwr[-1]
        ma = cwr / np.maximum(cw, 1e-12)
        mb = (twr - cwr) / np.maximum(tw - cw, 1e-12)
        ssb = cw * (tw - cw) / max(tw, 1e-12) * (ma - mb) ** 2
        k = lo + int(np.argmax(ssb[lo:hi]))
        if ssb[k] > best[0]:
            ps = proj[o]
            best = (float(ssb[k]), float(th), float(0.5 * (ps[k] + ps[min(k + 1, n - 1)])))
    mean = float(np.sum(wr) / max(np.sum(w), 1e-12))
    sst = float(np.sum(w * (r - mean) ** 2))
    return best[1], best[2], best[0], sst


def find_gain_step(model: np.ndarray, real: np.ndarray, mask: np.ndarray, *,
                   corr_px2: float, n_angles: int = 120, iterations: int = 4,
                   min_fraction: float = MIN_SIDE_FRACTION, min_step: float = MIN_STEP,
                   min_delta_bic: float = 10.0,
                   fit: Callable[..., RadiometryFit] = fit_radiometry) -> GainStep | None:
    """Look for a straight exposure seam between a (blurred) model and the real scene.

    The relative residual ``(real − g·model − o) / (g·model)`` of a robust per-band fit
    (median over bands: a seam scales every band alike) is split by the straight line that
    explains most of its robust variance (exhaustive over ``n_angles`` directions and all
    offsets leaving ``min_fraction`` of the pixels on each side). The factor is then refined
    by refitting the radiometry on the corrected model; it is reported for the darker side
    (factor ≥ 1, so the radiometry is relative to the brighter side).

    Parameters
    ----------
    model, real
        Bands-first low-passed model and real scene, DN.
    mask
        Pixels to use (valid, outside scene-change regions).
    corr_px2
        Area (px²) over which residuals are correlated (independent samples = Σw / corr_px2).

    Returns
    -------
    GainStep or None
        None unless ΔBIC ≥ ``min_delta_bic``, |factor − 1| ≥ ``min_step``, the step explains
        at least ``MIN_EXPLAINED`` of the robust residual variance and each side holds at
        least ``min_fraction`` of the pixels.
    """
    if mask.sum() < 200:
        return None
    fr = fit(model, real, mask, corr_px2=corr_px2)
    side = None
    factor = 1.0
    th = rho = ssb = sst = 0.0
    for _ in range(iterations):
        # the line from the residual of the *uncorrected* model under the current g, o
        pred = fr.gain[:, None, None] * model + fr.offset_dn[:, None, None]
        den = np.maximum(np.abs(fr.gain)[:, None, None] * model, 1.0)
        rel = np.median((real - pred) / den, axis=0)
        th, rho, ssb, sst = _line_search(rel, mask, n_angles=n_angles,
                                         min_fraction=min_fraction)
        side = step_side(mask.shape, normal_deg=float(np.degrees(th)), offset_px=rho)
        if side[mask].mean() > 0.5:  # correct the smaller side
            th, rho = th + np.pi, -rho
            side = step_side(mask.shape, normal_deg=float(np.degrees(th)), offset_px=rho)
        # the factor from the corrected model's residual on each side (robust means)
        corrected = np.where(side[None], model * factor, model)
        fr_c = fit(corrected, real, mask, corr_px2=corr_px2)
        pred_c = fr_c.gain[:, None, None] * corrected + fr_c.offset_dn[:, None, None]
        rel_c = np.median((real - pred_c) / np.maximum(
            np.abs(fr_c.gain)[:, None, None] * corrected, 1.0), axis=0)
        ra, rb = rel_c[mask & ~side], rel_c[mask & side]
        factor *= (1.0 + _robust_mean(rb)) / (1.0 + _robust_mean(ra))
        fr = fit(np.where(side[None], model * factor, model), real, mask, corr_px2=corr_px2)
    assert side is not None
    if factor < 1.0:  # report relative to the brighter side: the correction brightens
        th, rho, factor = th + np.pi, -rho, 1.0 / factor
        side = step_side(mask.shape, normal_deg=float(np.degrees(th)), offset_px=rho)
    fraction = float(side[mask].mean())
    n_ind = max(float(mask.sum()) / corr_px2, 2.0)
    explained = ssb / max(sst, 1e-12)
    dbic = float(n_ind * np.log(1.0 / max(1.0 - explained, 1e-12)) - 3.0 * np.log(n_ind))
    if (dbic < min_delta_bic or abs(factor - 1.0) < min_step
            or min(fraction, 1.0 - fraction) < min_fraction or explained < MIN_EXPLAINED):
        return None
    return GainStep(normal_deg=float(np.mod(np.degrees(th), 360.0)), offset_px=float(rho),
                    factor=float(factor), fraction=fraction, delta_bic=dbic,
                    explained=float(explained), side=side)


def _robust_mean(r: np.ndarray) -> float:
    loc = float(np.median(r))
    scale = 1.4826 * float(np.median(np.abs(r - loc))) + 1e-9
    for _ in range(5):
        w = _tukey(r - loc, scale)
        loc = float(np.sum(w * r) / max(np.sum(w), 1e-12))
    return loc
