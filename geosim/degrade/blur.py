"""The paper's blur metric: variance of the Laplacian of the grey image.

LV = (1/N) Σ (L − L̄)²,  L = 𝓛 ⊛ I,  with the kernel of the paper

    𝓛 = [[1/6, 2/3, 1/6], [2/3, −10/3, 2/3], [1/6, 2/3, 1/6]]

(MATLAB's ``fspecial('laplacian')`` with α = 0.2; the paper prints it rounded
to 0.17, 0.67, −3.33), on grey levels 0–255.

Choices (documented because each changes the number):

* Grey: ITU-R BT.601 luma 0.299 R + 0.587 G + 0.114 B as float (not rounded),
  via :func:`geosim.physics.radiometry.luma` (what OpenCV's RGB2GRAY and
  MATLAB's rgb2gray compute before rounding). Integer images other than 8-bit
  are scaled to 0–255 by their dtype's maximum unless ``dn_max`` is given.
* Valid pixels only, and no padding: a pixel counts only when its whole 3 × 3
  neighbourhood is valid and inside the image (the valid mask, eroded by the
  kernel's reach of 1 pixel, with everything outside the image invalid). So the
  result does not depend on any border rule.
* Variance with 1/N (the paper's formula), in float64.
* ``matlab_compatible=True`` reproduces ``var(double(imfilter(I, fspecial('laplacian'))))``
  on a uint8 grey image: the grey is rounded to uint8, the filtered image is
  rounded and saturated to 0–255 (so negative responses become 0: uint8
  filtering clips them) and, without a mask, MATLAB's zero padding is used and
  all pixels count. It is lower than the default for any textured image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geosim.physics.radiometry import luma

#: The paper's Laplacian kernel (MATLAB fspecial('laplacian', 0.2)), exactly.
PAPER_LAPLACIAN = np.array([[1 / 6, 2 / 3, 1 / 6],
                            [2 / 3, -10 / 3, 2 / 3],
                            [1 / 6, 2 / 3, 1 / 6]], dtype=np.float64)
PAPER_LAPLACIAN.setflags(write=False)

_CHUNK_ROWS = 1024


def to_grey(image: np.ndarray, *, dn_max: float | None = None) -> np.ndarray:
    """Grey levels 0–255 (float64) of a bands-first image.

    Parameters
    ----------
    image
        (bands, rows, cols) with R, G, B first (further bands such as NIR are
        ignored), or a single band (1, rows, cols) / (rows, cols).
    dn_max
        Digital number that maps to grey 255. Default: 255 for uint8 and float
        images (assumed to be 0–255 already), the dtype's maximum for other
        integer types (e.g. 65535 for uint16).

    Returns
    -------
    numpy.ndarray
        (rows, cols) float64 luma on a 0–255 scale.
    """
    arr = np.asarray(image)
    if arr.ndim not in (2, 3):
        raise ValueError(f"image must be (rows, cols) or (bands, rows, cols), got {arr.shape}")
    if arr.ndim == 3 and arr.shape[0] == 2:
        raise ValueError("a 2-band image has no luma: give R, G, B (first) or one grey band")
    if dn_max is None:
        if np.issubdtype(arr.dtype, np.integer) and arr.dtype != np.uint8:
            dn_max = float(np.iinfo(arr.dtype).max)
        else:
            dn_max = 255.0
    if not dn_max > 0:
        raise ValueError(f"dn_max must be > 0, got {dn_max!r}")
    rgb = arr if arr.ndim == 2 else arr[:3]
    grey = np.empty(arr.shape[-2:], np.float64)
    for r0 in range(0, grey.shape[0], _CHUNK_ROWS):  # luma in row chunks: bounded memory
        grey[r0:r0 + _CHUNK_ROWS] = luma(rgb[..., r0:r0 + _CHUNK_ROWS, :])
    if dn_max != 255.0:
        grey *= 255.0 / dn_max
    return grey


def laplacian(grey: np.ndarray, *, zero_padding: bool = False) -> np.ndarray:
    """Paper-Laplacian response of a grey image (float64, same shape).

    Border pixels use OpenCV's BORDER_REFLECT_101 (or zeros with
    ``zero_padding``, as MATLAB's ``imfilter``); :func:`laplacian_variance`
    excludes them unless asked to mimic MATLAB.
    """
    g = np.asarray(grey, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError(f"grey must be a 2-D array, got shape {g.shape}")
    border = cv2.BORDER_CONSTANT if zero_padding else cv2.BORDER_REFLECT_101
    return cv2.filter2D(g, cv2.CV_64F, np.asarray(PAPER_LAPLACIAN), borderType=border)


def interior_mask(valid: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Pixels whose whole 3 × 3 neighbourhood is valid and inside the image."""
    v = np.ones(shape, bool) if valid is None else np.asarray(valid, dtype=bool)
    if v.shape != tuple(shape):
        raise ValueError(f"valid mask shape {v.shape} does not match the image's {tuple(shape)}")
    out = np.zeros(shape, bool)
    if shape[0] < 3 or shape[1] < 3:
        return out
    out[1:-1, 1:-1] = cv2.erode(v.astype(np.uint8), np.ones((3, 3), np.uint8),
                                borderType=cv2.BORDER_CONSTANT, borderValue=0)[1:-1, 1:-1] > 0
    return out


@dataclass(frozen=True)
class MomentSums:
    """Count, sum and sum of squares of Laplacian responses (to pool blocks)."""

    n: int
    total: float
    total_sq: float

    def __add__(self, other: MomentSums) -> MomentSums:
        return MomentSums(self.n + other.n, self.total + other.total,
                          self.total_sq + other.total_sq)

    @property
    def variance(self) -> float:
        """Population variance (1/N), or NaN when empty."""
        if self.n == 0:
            return float("nan")
        mean = self.total / self.n
        return max(self.total_sq / self.n - mean * mean, 0.0)


def laplacian_moments(grey: np.ndarray, mask: np.ndarray) -> MomentSums:
    """Moment sums of the Laplacian over ``mask`` (used as is: erode it beforehand)."""
    values = laplacian(grey)[np.asarray(mask, dtype=bool)]
    return MomentSums(int(values.size), float(values.sum()), float(np.dot(values, values)))


def laplacian_variance(grey: np.ndarray, valid: np.ndarray | None = None, *,
                       matlab_compatible: bool = False) -> float:
    """Laplacian variance (the paper's LV) of a grey image over valid pixels.

    Parameters
    ----------
    grey
        (rows, cols) grey levels on a 0–255 scale (see :func:`to_grey`).
    valid
        Bool mask, True = valid; None = all pixels valid. It is eroded by the
        kernel's reach, so only pixels whose 3 × 3 neighbourhood is entirely
        valid (and inside the image) count: no padding value enters the result.
    matlab_compatible
        Mimic MATLAB on a uint8 image: round the grey to uint8, round and clip
        the response to 0–255 (negative responses become 0). Without ``valid``,
        MATLAB's zero padding is used and every pixel counts.

    Returns
    -------
    float
        LV in grey levels² (NaN when no pixel counts).
    """
    g = np.asarray(grey, dtype=np.float64)
    if g.ndim != 2:
        raise ValueError(f"grey must be a 2-D array, got shape {g.shape}")
    if not matlab_compatible:
        return laplacian_moments(g, interior_mask(valid, g.shape)).variance
    g = np.clip(np.floor(g + 0.5), 0, 255)  # MATLAB rounds halves away from zero
    # On integer grey levels every response is a multiple of 1/6 and halves are common;
    # snap to sixths first so ties round as in exact arithmetic, not by float noise.
    sixths = np.rint(laplacian(g, zero_padding=True) * 6.0)
    response = np.clip(np.floor((sixths + 3.0) / 6.0), 0, 255)
    mask = np.ones(g.shape, bool) if valid is None else interior_mask(valid, g.shape)
    values = response[mask]
    return float(values.var()) if values.size else float("nan")
