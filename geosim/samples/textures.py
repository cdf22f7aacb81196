"""Band-limited random fields for procedural textures.

Every field is white noise filtered to a chosen correlation length, so textures
have structure at that scale (grass clumps, grazing patches, soil) instead of
pixel-level white noise. Sums of fields at several scales give multi-scale
texture.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float
                 ) -> np.ndarray:
    """Gaussian-correlated random field with unit standard deviation.

    Parameters
    ----------
    rng
        Random generator.
    shape
        (rows, cols) of the output.
    sigma_px
        Correlation length (Gaussian filter sigma), output pixels. Fields with
        ``sigma_px > 2`` are made on a coarser grid and resized bicubically, so
        large scales stay cheap.

    Returns
    -------
    numpy.ndarray
        float32 field of the given shape, mean ≈ 0, std ≈ 1.
    """
    rows, cols = shape
    factor = max(1.0, sigma_px / 2.0)
    c_rows = int(math.ceil(rows / factor)) + 8
    c_cols = int(math.ceil(cols / factor)) + 8
    sigma_c = sigma_px / factor
    noise = rng.standard_normal((c_rows, c_cols), dtype=np.float32)
    noise = cv2.GaussianBlur(noise, (0, 0), sigmaX=sigma_c, sigmaY=sigma_c,
                             borderType=cv2.BORDER_REFLECT)
    noise = noise[4:-4, 4:-4]
    if noise.shape != (rows, cols):
        noise = cv2.resize(noise, (cols, rows), interpolation=cv2.INTER_CUBIC)
    std = float(noise.std())
    return (noise - float(noise.mean())) / (std if std > 0 else 1.0)


def multiscale_noise(rng: np.random.Generator, shape: tuple[int, int],
                     scales_px: tuple[float, ...], weights: tuple[float, ...]) -> np.ndarray:
    """Weighted sum of :func:`smooth_noise` fields, renormalised to unit std."""
    out = np.zeros(shape, dtype=np.float32)
    for s, w in zip(scales_px, weights, strict=True):
        out += np.float32(w) * smooth_noise(rng, shape, s)
    std = float(out.std())
    return out / (std if std > 0 else 1.0)


def smoothstep(edge0: float, edge1: float, x: np.ndarray) -> np.ndarray:
    """Hermite step from 0 at ``edge0`` to 1 at ``edge1`` (float32)."""
    t = np.clip((x - np.float32(edge0)) / np.float32(edge1 - edge0), 0.0, 1.0)
    return (t * t * (3.0 - 2.0 * t)).astype(np.float32, copy=False)
