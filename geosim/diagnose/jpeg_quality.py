"""The JPEG quality of the real scene, read from its own quantisation lattice.

A JPEG stores each 8×8 block's DCT coefficient k as a whole multiple of its step t_k; the
decoded scene's coefficients therefore lie on that lattice (up to the rounding of the
decoded pixels, ≈ 0.5 in coefficient units: the JPEG DCT is orthonormal). An IJG encoder
(libjpeg, libjpeg-turbo: Pillow, OpenCV, GDAL) scales the standard luminance table of the
JPEG standard (ITU-T T.81, Annex K.1) by the quality, so the quality that best explains
the lattices of all 63 AC coefficients at once is read from the scene alone, whatever the
blur, noise or radiometry before the encoder: it does not depend on any model of the scene.

The likelihood of a coefficient's values under step t: the pre-quantisation coefficient is
Laplacian of scale b (profiled out per coefficient), quantised to t·round(x / t), decoded
with Gaussian jitter; a Laplacian gives the lattice's first points more weight than the
next ones, so a lattice of half the true step (which passes through every value too) is
penalised by its empty odd points, and a coefficient that holds only zeros tells nothing
(its likelihood is the same for every coarse step).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geosim.diagnose.jpeg_noise import LATTICE_JITTER, block_dct, jitter_density

__all__ = ["IJG_LUMA_TABLE", "ijg_luma_steps", "lattice_quality", "LatticeQuality",
           "QUALITIES"]

#: the JPEG standard's luminance quantisation table (ITU-T T.81 Annex K.1), natural order
#: (row = vertical frequency), as block_dct's 64 coefficients
IJG_LUMA_TABLE = np.array([
    16, 11, 10, 16, 24, 40, 51, 61,
    12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56,
    14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77,
    24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101,
    72, 92, 95, 98, 112, 100, 103, 99], dtype=np.int64)
#: qualities searched (IJG's 1–100)
QUALITIES = np.arange(1, 101)
#: Laplacian scales profiled per coefficient (coefficient units)
LAPLACE_SCALES = np.geomspace(0.3, 300.0, 40)


@dataclass(frozen=True)
class LatticeQuality:
    """The IJG quality read from the scene's quantisation lattice.

    ``quality``: the best quality (1–100); ``log_lik_margin``: its log-likelihood above the
    best quality whose step table differs (0 when no other table was possible; small:
    neighbouring qualities explain the lattice about as well); ``n_blocks``: 8×8 blocks
    read."""

    quality: int
    log_lik_margin: float
    n_blocks: int


def ijg_luma_steps(quality: int) -> np.ndarray:
    """The 64 luminance quantisation steps an IJG encoder uses at ``quality`` (1–100):
    the standard table scaled by 5000 / quality (below 50, integer division) or
    200 − 2 · quality, rounded, clamped to 1–255 (baseline JPEG), as libjpeg's
    ``jpeg_quality_scaling`` and ``jpeg_add_quant_table``."""
    q = int(np.clip(quality, 1, 100))
    scale = 5000 // q if q < 50 else 200 - 2 * q
    return np.clip((IJG_LUMA_TABLE * scale + 50) // 100, 1, 255)


def _step_log_lik(values: np.ndarray, step: int, jitter: float = LATTICE_JITTER) -> float:
    """Log-likelihood of one coefficient's ``values`` under a lattice of ``step``, with a
    Laplacian pre-quantisation coefficient whose scale is profiled out (nearest lattice
    point's bin; the jitter's density summed over the neighbouring points)."""
    s = float(step)
    m = np.rint(values / s)
    d = values - m * s
    dens = jitter_density(d, s, jitter)
    d_term = float(np.sum(np.log(np.maximum(dens / (jitter * np.sqrt(2 * np.pi)), 1e-300))))
    bins, counts = np.unique(np.abs(m), return_counts=True)
    b = LAPLACE_SCALES[:, None]
    p_zero = 1.0 - np.exp(-s / (2.0 * b))
    p_bin = 0.5 * (np.exp(-(bins - 0.5) * s / b) - np.exp(-(bins + 0.5) * s / b))
    p = np.where(bins == 0, p_zero, p_bin)
    return d_term + float(np.max(np.sum(counts * np.log(np.maximum(p, 1e-300)), axis=1)))


def lattice_quality(grey: np.ndarray, offset_px: tuple[int, int], mask: np.ndarray
                    ) -> LatticeQuality:
    """The IJG quality whose luminance steps best explain the lattice of the AC
    coefficients of the 8×8 blocks at ``offset_px`` (row, col) wholly inside ``mask``.

    Parameters
    ----------
    grey
        The real scene's luma (BT.601, as the JPEG's Y), DN.
    offset_px
        Phase of the JPEG block grid (row, col), px.
    mask
        Bool, True where the scene is valid.

    Returns
    -------
    LatticeQuality
    """
    coef = block_dct(grey, offset_px, mask)
    cache: dict[tuple[int, int], float] = {}
    tables = [ijg_luma_steps(int(q)) for q in QUALITIES]
    scores = np.empty(QUALITIES.size)
    for i, steps in enumerate(tables):
        total = 0.0
        for k in range(1, 64):      # AC only: the DC's lattice is offset by the level shift
            key = (k, int(steps[k]))
            if key not in cache:
                cache[key] = _step_log_lik(coef[:, k], int(steps[k]))
            total += cache[key]
        scores[i] = total
    best = int(np.argmax(scores))
    other = [scores[i] for i, t in enumerate(tables) if not np.array_equal(t, tables[best])]
    margin = float(scores[best] - max(other)) if other else 0.0
    return LatticeQuality(int(QUALITIES[best]), margin, int(coef.shape[0]))
