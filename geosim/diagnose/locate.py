"""Where do simulation and reality differ? Maps and regions on the 0.5 m grid.

* ``residual_energy_map`` – Gaussian-smoothed squared residual (DN²), the local
  mismatch power;
* ``local_blur_ratio`` – per block, Laplacian variance (the paper's sharpness
  metric) of the real scene over that of the simulation: < 1 where reality is
  blurrier than the model, > 1 where it is sharper or noisier;
* ``local_gain_offset`` – per block least-squares grey-level gain and offset of
  real on simulated;
* ``find_regions`` – connected areas of significant residual energy, ranked by
  excess energy and classified as ``scene_change`` (object-sized, compact,
  localised: cattle that moved, shadows, water) or ``global`` (large areas, the
  signature of physics that acts everywhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from geosim.degrade.blur import laplacian_variance as lv

__all__ = ["Region", "residual_energy_map", "local_blur_ratio", "local_gain_offset",
           "find_regions", "regions_mask", "laplacian_variance"]

_LAPLACIAN = np.array([[1 / 6, 2 / 3, 1 / 6], [2 / 3, -10 / 3, 2 / 3], [1 / 6, 2 / 3, 1 / 6]])


def laplacian_variance(grey: np.ndarray, valid: np.ndarray | None = None) -> float:
    """The paper's blur metric: variance of the 3×3 Laplacian response over valid pixels.

    The project's one implementation, :func:`geosim.degrade.blur.laplacian_variance`.
    """
    return float(lv(grey, valid))


def residual_energy_map(residual_grey: np.ndarray, *, sigma_px: float = 1.5) -> np.ndarray:
    """Local mean of the squared residual (DN²), Gaussian window of ``sigma_px``."""
    return ndimage.gaussian_filter(np.asarray(residual_grey, float) ** 2, sigma_px)


def _block_view(a: np.ndarray, block_px: int) -> np.ndarray:
    r = a.shape[0] // block_px * block_px
    c = a.shape[1] // block_px * block_px
    return a[:r, :c].reshape(r // block_px, block_px, c // block_px, block_px).swapaxes(1, 2)


def _expand(blocks: np.ndarray, block_px: int, shape: tuple[int, int]) -> np.ndarray:
    out = np.full(shape, np.nan)
    big = np.repeat(np.repeat(blocks, block_px, 0), block_px, 1)
    out[:big.shape[0], :big.shape[1]] = big
    return out


def local_blur_ratio(sim_grey: np.ndarray, real_grey: np.ndarray, *, block_px: int = 16,
                     valid: np.ndarray | None = None) -> np.ndarray:
    """Per-block LV(real) / LV(sim), expanded to the grid (NaN where invalid or where a
    block is not wholly valid). ``sim_grey`` should be co-registered with ``real_grey``."""
    ls = ndimage.convolve(np.asarray(sim_grey, float), _LAPLACIAN, mode="reflect")
    lr = ndimage.convolve(np.asarray(real_grey, float), _LAPLACIAN, mode="reflect")
    vs = _block_view(ls, block_px).var(axis=(2, 3))
    vr = _block_view(lr, block_px).var(axis=(2, 3))
    ratio = vr / np.maximum(vs, 1e-9)
    if valid is not None:  # blocks that reach outside the valid area mean nothing
        ratio[~_block_view(np.asarray(valid), block_px).all(axis=(2, 3))] = np.nan
    out = _expand(ratio, block_px, sim_grey.shape)
    if valid is not None:
        out[~valid] = np.nan
    return out


def local_gain_offset(sim_grey: np.ndarray, real_grey: np.ndarray, *, block_px: int = 16,
                      valid: np.ndarray | None = None, min_rho: float = 0.5
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Per-block least-squares gain and offset (DN) of real on simulated grey levels (NaN
    where a block is not wholly valid). ``sim_grey`` should be co-registered with
    ``real_grey``: a shift decorrelates blocks and drags the gain toward 0. Blocks whose
    correlation coefficient is below ``min_rho`` are NaN too: there the two images do not
    show the same content (other shadows, moved cattle) or too little contrast, and a
    regression slope is dominated by what they do not share (regression dilution)."""
    s = _block_view(np.asarray(sim_grey, float), block_px)
    r = _block_view(np.asarray(real_grey, float), block_px)
    sm = s.mean(axis=(2, 3), keepdims=True)
    rm = r.mean(axis=(2, 3), keepdims=True)
    cov = ((s - sm) * (r - rm)).mean(axis=(2, 3))
    var = ((s - sm) ** 2).mean(axis=(2, 3))
    gain = cov / np.maximum(var, 1e-9)
    offset = rm[..., 0, 0] - gain * sm[..., 0, 0]
    rho = cov / np.sqrt(np.maximum(var * ((r - rm) ** 2).mean(axis=(2, 3)), 1e-18))
    gain[rho < min_rho] = np.nan
    offset[rho < min_rho] = np.nan
    if valid is not None:  # blocks that reach outside the valid area mean nothing
        whole = _block_view(np.asarray(valid), block_px).all(axis=(2, 3))
        gain[~whole] = np.nan
        offset[~whole] = np.nan
    g = _expand(gain, block_px, sim_grey.shape)
    o = _expand(offset, block_px, sim_grey.shape)
    if valid is not None:
        g[~valid] = np.nan
        o[~valid] = np.nan
    return g, o


@dataclass
class Region:
    """A connected area of significant mismatch.

    Attributes
    ----------
    rank
        1 = largest excess residual energy.
    kind
        ``"scene_change"`` or ``"global"``.
    area_px
        Number of 0.5 m pixels.
    bbox
        (row_min, col_min, row_max, col_max), inclusive-exclusive pixel bounds.
    excess_energy
        Sum over the region of (energy − expected), DN².
    mean_ratio
        Mean residual energy over the expected level.
    """

    rank: int
    kind: str
    area_px: int
    bbox: tuple[int, int, int, int]
    excess_energy: float
    mean_ratio: float
    label: int


def find_regions(energy: np.ndarray, *, valid: np.ndarray, expected_dn2: float | np.ndarray,
                 ratio_threshold: float = 4.0, min_area_px: int = 3,
                 max_object_px: int = 2000, max_regions: int = 100
                 ) -> tuple[list[Region], np.ndarray]:
    """Connected regions where residual energy exceeds ``ratio_threshold`` × expected.

    Parameters
    ----------
    energy
        Residual energy map (DN²), e.g. from :func:`residual_energy_map`.
    expected_dn2
        Energy expected from noise and fit error alone (scalar or map).
    max_object_px
        Largest area (pixels) still called ``scene_change`` (2000 px = 500 m² at 0.5 m:
        a tree with its shadow); larger, or sprawling (fill of bounding box < 0.15),
        regions are ``global``.

    Returns
    -------
    regions, labels
        Ranked regions and the label image (0 = background; label ids as ``Region.label``).
    """
    exp = np.maximum(np.asarray(expected_dn2, float), 1e-6)
    hot = (energy > ratio_threshold * exp) & valid
    hot = ndimage.binary_opening(hot, np.ones((2, 2))) | (hot & ndimage.binary_erosion(hot))
    labels, n = ndimage.label(hot, structure=np.ones((3, 3)))
    regions: list[Region] = []
    if n == 0:
        return regions, labels
    idx = np.arange(1, n + 1)
    areas = ndimage.sum_labels(np.ones_like(energy), labels, idx)
    excess = ndimage.sum_labels(energy - np.broadcast_to(exp, energy.shape), labels, idx)
    ratio = ndimage.mean(energy / np.broadcast_to(exp, energy.shape), labels, idx)
    slices = ndimage.find_objects(labels)
    for lab, area, ex, ra, sl in zip(idx, areas, excess, ratio, slices, strict=True):
        if area < min_area_px:
            labels[labels == lab] = 0
            continue
        h = sl[0].stop - sl[0].start
        w = sl[1].stop - sl[1].start
        fill = area / float(h * w)
        kind = "scene_change" if (area <= max_object_px and fill >= 0.15) else "global"
        regions.append(Region(0, kind, int(area), (sl[0].start, sl[1].start, sl[0].stop,
                                                    sl[1].stop), float(ex), float(ra), int(lab)))
    regions.sort(key=lambda r: -r.excess_energy)
    regions = regions[:max_regions]
    for i, r in enumerate(regions, 1):
        r.rank = i
    return regions, labels


def regions_mask(labels: np.ndarray, regions: list[Region], *,
                 kind: str | None = "scene_change", dilate_px: int = 2) -> np.ndarray:
    """Bool mask of the regions of ``kind`` (None: all), dilated by ``dilate_px``."""
    keep = [r.label for r in regions if kind is None or r.kind == kind]
    m = np.isin(labels, keep) if keep else np.zeros(labels.shape, bool)
    if dilate_px > 0 and m.any():
        m = ndimage.binary_dilation(m, np.ones((2 * dilate_px + 1,) * 2))
    return m
