"""Radiometric matching: per-band and grey-level affine fits, exposure seam and haze /
colour response of the blurred model (:func:`fit_scene_radiometry`)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from geosim.diagnose.fit import fit_radiometry
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.seam import find_gain_step
from geosim.diagnose.select import select_radiometry
from geosim.diagnose.stage_inputs import Inputs

__all__ = ["band_affine", "affine_residual", "fit_scene_radiometry", "RADIOMETRY_SIGMA_PX"]

#: low-pass σ (px) of the images used for the per-band gain/offset regression
RADIOMETRY_SIGMA_PX = 2.0


def band_affine(model: np.ndarray, real: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``model`` with each band's least-squares gain and offset to ``real`` over ``mask``."""
    out = np.empty_like(model)
    for b in range(model.shape[0]):
        a = np.column_stack([model[b][mask], np.ones(mask.sum())])
        sol, *_ = np.linalg.lstsq(a, real[b][mask], rcond=None)
        out[b] = sol[0] * model[b] + sol[1]
    return out


def affine_residual(model_g: np.ndarray, real_g: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``real_g`` minus the least-squares gain and offset of ``model_g`` over ``mask``."""
    a = np.column_stack([model_g[mask], np.ones(mask.sum())])
    sol, *_ = np.linalg.lstsq(a, real_g[mask], rcond=None)
    return real_g - (sol[0] * model_g + sol[1])


def fit_scene_radiometry(inp: Inputs, model: ForwardModel, fit_mask: np.ndarray) -> ForwardModel:
    """Exposure seam, then haze / colour response, on the blurred model as delivered.

    Where a JPEG re-encoding was found, the blurred model is re-encoded at its fitted
    quality before the regression: JPEG keeps luma but coarsens chroma (4:2:0 subsampling,
    coarse chroma quantisation), so a per-band regression of the scene on an unencoded
    model reads the lost colour contrast as band gains below 1 with positive offsets,
    i.e. as haze (round 24: three development scenes with a JPEG and no radiometric
    effect were given a haze, c153, c644, c752). Fitting T·JPEG(m) + P rather than
    JPEG(T·m + P) is the linear part of the forward model's order (radiometry, then
    compression).
    """
    m_blur = model.without(seam=None).blurred(inp.simulate)
    if model.compression is not None:
        m_blur = model.compression.apply(m_blur)

    # gains/offsets from large-scale brightness (σ = 2 px low-pass): a model that carries
    # aliasing or noise the scene does not share would otherwise bias the slope low
    def lowpass(img: np.ndarray) -> np.ndarray:
        return np.stack([ndimage.gaussian_filter(b, RADIOMETRY_SIGMA_PX) for b in img])

    corr = 4.0 * np.pi * RADIOMETRY_SIGMA_PX**2
    # an exposure seam of the UAV mosaic gives two radiometric relations; one regression
    # would thread between them and absorb the seam into the haze
    lp_blur, lp_real = lowpass(m_blur), lowpass(inp.real)
    seam = find_gain_step(lp_blur, lp_real, fit_mask, corr_px2=corr)
    if seam is not None:
        lp_blur = lp_blur * np.where(seam.side, seam.factor, 1.0)
    rad = select_radiometry(fit_radiometry(lp_blur, lp_real, fit_mask, corr_px2=corr),
                            corr_px2=corr)
    return model.without(seam=seam, radiometry=rad)
