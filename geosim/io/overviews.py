"""Overview levels of an in-memory raster, averaged as GDAL's COG driver averages them.

GDAL builds a COG's overviews by reading the written raster back; with an internal mask its
``AVERAGE`` takes a generic per-pixel path and the mask's own overviews are built and
stored in temporary files (compressed, then decompressed again): about 0.65 of the 1.96
CPU-s of writing a 5000 px RGB tile with its mask (benchmarks/bench_tile_write.py). A writer
that already holds the whole array (a tile, a degraded tile) computes the levels here
instead, with OpenCV's area averaging, and hands them to the COG copy
(:func:`geosim.io.cog.cog_writer`).

The levels follow GDAL's rules (tested against GDAL's own overviews in
``tests/test_cog_overviews.py``: same sizes and masks, pixels within 1 DN on whole rasters):

* sizes: halve (integer division, at least 1 px) until both sides fit in one block;
* pixels: the mean of the *valid* pixels the overview pixel covers (area weights where the
  ratio is not 2), rounded half up for integer types; 0 (or nodata) where none is valid;
* mask: valid wherever any covered pixel is valid.

Each level is computed from the previous level's unrounded sums (pixel × valid, and
valid), so no rounding accumulates down the pyramid and a level-k pixel weighs every valid
base pixel alike. GDAL's levels, each made from the previous rounded level, drift by up to
1.3 DN on a whole raster and by tens of DN along the edge of a partial raster's data.

One exception, asked for by the writer (``binomial_level1``, the UAV tiles): the *first*
level of an all-valid 8-bit raster of even sides is the binomial level
``[1, 5, 10, 10, 5, 1]/32`` per axis on each 2 × 2 block
(:func:`geosim.physics.pyramid.halve_binomial6_exact_uint8`, exact in float32, rounded half
up) instead of the 2 × 2 mean, and the raster carries the tag :data:`LEVEL1_TAG`. It is the
first level of the degradation's band-limited pyramid, so ``geosim degrade`` reads it (a
quarter of the pixels to decode) instead of full resolution (docs/degradation.md); for
display it is a softer, less aliased 2× view (transfer cos⁵(πf) instead of cos(πf)).
Deeper levels are area means of its unrounded values, as above.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from geosim.physics.pyramid import halve_binomial6_exact_uint8

#: Metadata tag of a raster whose first overview level is the binomial level (its value
#: :data:`LEVEL1_BINOMIAL`); absent otherwise.
LEVEL1_TAG = "GEOSIM_OVERVIEW_LEVEL1"
LEVEL1_BINOMIAL = "binomial [1 5 10 10 5 1]/32 per axis on 2x2 blocks, rounded half up"


@dataclass(frozen=True)
class OverviewLevel:
    """One overview level.

    Attributes
    ----------
    array
        ``(bands, rows, cols)`` pixels, in the raster's dtype.
    valid
        ``(rows, cols)`` bool mask (True = valid).
    """

    array: np.ndarray
    valid: np.ndarray


def overview_shapes(rows: int, cols: int, block_px: int) -> list[tuple[int, int]]:
    """``(rows, cols)`` of each overview level GDAL's COG driver makes (``OVERVIEWS=AUTO``).

    Halve both sides (integer division, at least 1 px) until both fit in ``block_px``; a
    raster that already fits gets none.
    """
    shapes: list[tuple[int, int]] = []
    while rows > block_px or cols > block_px:
        rows, cols = max(rows // 2, 1), max(cols // 2, 1)
        shapes.append((rows, cols))
    return shapes


def _area_mean(plane: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Area-weighted mean of a float32 plane onto ``shape`` (rows, cols)."""
    return cv2.resize(plane, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


def _to_dtype(mean: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Round half up and clip to an integer dtype's range; floats are kept."""
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        return np.clip(np.floor(mean + 0.5), info.min, info.max).astype(dtype)
    return mean.astype(dtype)


def binomial_level1_applies(array: np.ndarray, valid: np.ndarray | None, block_px: int
                            ) -> bool:
    """Whether :func:`average_overviews` makes the first level of ``array`` (bands, rows,
    cols) binomial when asked: 8-bit, every pixel valid, both sides even and ≥ 16, and at
    least one overview level (whose size is then exactly half)."""
    rows, cols = array.shape[1:]
    return (array.dtype == np.uint8 and rows % 2 == 0 and cols % 2 == 0
            and min(rows, cols) >= 16 and bool(overview_shapes(rows, cols, block_px))
            and (valid is None or bool(valid.all())))


def average_overviews(array: np.ndarray, valid: np.ndarray | None, block_px: int, *,
                      fill: float = 0, binomial_level1: bool = False) -> list[OverviewLevel]:
    """Masked-average overview levels of a ``(bands, rows, cols)`` array.

    Parameters
    ----------
    array
        The full-resolution pixels (any numeric dtype).
    valid
        ``(rows, cols)`` bool mask (True = valid), or None when every pixel is valid.
    block_px
        The COG's internal tile size in pixels (sets how many levels there are).
    fill
        Value of overview pixels with no valid pixel under them (nodata, or 0).
    binomial_level1
        Make the first level the binomial one where :func:`binomial_level1_applies`
        (module docstring); otherwise ignored.

    Returns
    -------
    list of OverviewLevel
        Largest level first; empty when the raster fits in one block.
    """
    shapes = overview_shapes(array.shape[1], array.shape[2], block_px)
    if not shapes:
        return []
    all_valid = valid is None or bool(valid.all())
    # The area mean of (pixel × valid) and of valid, carried unrounded from level to level:
    # their ratio is the mean of the valid pixels under each overview pixel.
    weight = None if all_valid else valid.astype(np.float32)
    weights: list[np.ndarray | None] = []
    for shape in shapes:
        weight = None if weight is None else _area_mean(weight, shape)
        weights.append(weight)
    out = [OverviewLevel(np.empty((array.shape[0], *shape), array.dtype),
                         np.ones(shape, bool) if w is None else w > 0)
           for shape, w in zip(shapes, weights, strict=True)]
    binomial = binomial_level1 and binomial_level1_applies(array, valid, block_px)
    for b, band in enumerate(array):
        if binomial:  # the first level from the 8-bit band itself, no float copy of it
            plane, first = halve_binomial6_exact_uint8(band), 1
        else:
            plane, first = band.astype(np.float32), 0
            if not all_valid:
                plane *= valid
        for i, (level, w) in enumerate(zip(out, weights, strict=True)):
            if i >= first:
                plane = _area_mean(plane, level.valid.shape)
            # no valid pixel under it: the fill value (rounds to itself)
            mean = plane if w is None else np.divide(plane, w, out=np.full_like(plane, fill),
                                                     where=level.valid)
            level.array[b] = _to_dtype(mean, array.dtype)
    return out
