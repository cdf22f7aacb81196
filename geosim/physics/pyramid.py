"""Halving pyramid levels with binomial filters centred on 2 × 2 blocks (pure kernels).

A level keeps one value per 2 × 2 block of its input: the input filtered with the binomial
kernel [1, 3, 3, 1]/8 (p = 3) or [1, 5, 10, 10, 5, 1]/32 (p = 5) per axis, centred on the
block's middle, ``BORDER_REFLECT`` at the edges. Its transfer is cos^p(π f), and since the
blocks' centres keep the half-sample symmetry of the DCT-II, the level's DCT-II coefficient
k is exactly ``(G(k/2N) X_k − G((N − k)/2N) X_{N−k}) / √2`` for a length-N input with
coefficients X (:func:`level_gain` is the first factor). The degradation's fast path
(:func:`geosim.degrade.core.reduce_band_limited`) builds its levels with these, and the
tiles' first overview level is the p = 5 level (:mod:`geosim.io.overviews`), so the
degradation can read it from the tile instead of decoding full resolution.
"""

from __future__ import annotations

from collections.abc import Iterator

import cv2
import numpy as np

# Binomial kernels of the levels, centred between samples 1 and 2 (anchor 1 / 2): sampled at
# even outputs they are the block-centre filters [1, 3, 3, 1]/8 and [1, 5, 10, 10, 5, 1]/32.
_BINOMIAL_6 = np.array([1, 5, 10, 10, 5, 1], np.float32) / 32
_BINOMIAL_5 = np.array([1, 4, 6, 4, 1], np.float32) / 16  # ⊛ [1, 1] = _BINOMIAL_6
#: [1, 2, 1] and 4 × [1, 2, 1]: with a 2 × 2 block sum they make [1, 3, 3, 1] per axis.
_TAPS_121 = np.array([1, 2, 1], np.float32)
_TAPS_121_X4 = np.array([4, 8, 4], np.float32)
#: Output rows per strip of the pyramid levels (their temporaries stay in cache).
STRIP_ROWS = 64


def row_strips(n_out: int, rows: int, reach: int) -> Iterator[tuple[int, int, int, int]]:
    """The strips of a halving level of a ``rows``-row band: output rows ``j0:j1``
    (:data:`STRIP_ROWS` at a time) and the input rows ``s0:s1`` they need — their 2 × 2
    blocks and the ``reach`` rows above and below that a filter reads, clipped to the band
    (so only the band's own edges are reflected)."""
    for j0 in range(0, n_out, STRIP_ROWS):
        j1 = min(j0 + STRIP_ROWS, n_out)
        yield j0, j1, max(2 * j0 - reach, 0), min(2 * j1 + reach, rows)


def halve_binomial4_uint8(band: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """One pyramid level of an even-sized uint8 band: [1, 3, 3, 1]/8 per axis, float32.

    The filter is centred on each 2 × 2 block (``BORDER_REFLECT``: x[−1] = x[0],
    x[N] = x[N−1]) and evaluated only there: the result is
    ``sepFilter2D(band, [1, 3, 3, 1], anchor 1)[::2, ::2] / 64``. Since
    [1, 3, 3, 1] = [1, 2, 1] ⊛ [1, 1], it is OpenCV's [1, 2, 1] filter on every pixel
    (times 4: ≤ 16320, exact in int16) followed by the exact 2 × 2 block mean of
    ``INTER_AREA`` (which rounds (4 s + 2) >> 2 = s, the block sum s of the [1, 2, 1]
    sums, exactly), in strips of rows (each with the row above and below that the
    filter reaches) whose int16 temporaries stay in cache.
    ``out``: a float32 (rows / 2, cols / 2) array to write into (default: a new one).
    """
    rows, cols = band.shape
    n_out = rows // 2
    if out is None:
        out = np.empty((n_out, cols // 2), np.float32)
    for j0, j1, s0, s1 in row_strips(n_out, rows, reach=1):
        sums4 = cv2.sepFilter2D(band[s0:s1], cv2.CV_16S, _TAPS_121, _TAPS_121_X4,
                                borderType=cv2.BORDER_REFLECT)[2 * j0 - s0:2 * j1 - s0]
        block = cv2.resize(sums4, (cols // 2, j1 - j0), interpolation=cv2.INTER_AREA)
        np.multiply(block, np.float32(1.0 / 64.0), out=out[j0:j1])
    return out


def halve_binomial6(band: np.ndarray, out: np.ndarray | None = None, *,
                    exact_sums: bool = False) -> np.ndarray:
    """One pyramid level of an even-sized band: [1, 5, 10, 10, 5, 1]/32 per axis, float32.

    ``sepFilter2D(band, [1, 5, 10, 10, 5, 1]/32, anchor 2, BORDER_REFLECT)[::2, ::2]``,
    filtered in strips of rows (each with the two rows above and below it that the
    kernel reaches, so only the image's own edges are reflected): the filtered strip
    stays in cache instead of a full-size filtered band going through memory.
    ``out``: a float32 (rows / 2, cols / 2) array to write into (default: a new one).
    ``exact_sums``: the band holds multiples of 1/64 in [0, 255] (the first level of a
    uint8 band), so every weighted sum of the filter is exact in float32 (≤ 24 bits);
    then [1, 5, 10, 10, 5, 1] = [1, 4, 6, 4, 1] ⊛ [1, 1] is computed as OpenCV's 5-tap
    filter followed by the 2 × 2 block mean of ``INTER_AREA`` (also exact): the same
    numbers for less work.
    """
    data = band.astype(np.float32, copy=False)
    rows, cols = data.shape
    n_out = rows // 2
    if out is None:
        out = np.empty((n_out, cols // 2), np.float32)
    for j0, j1, s0, s1 in row_strips(n_out, rows, reach=2):
        if exact_sums:
            smooth = cv2.sepFilter2D(data[s0:s1], cv2.CV_32F, _BINOMIAL_5, _BINOMIAL_5,
                                     borderType=cv2.BORDER_REFLECT)[2 * j0 - s0:2 * j1 - s0]
            dst = out[j0:j1]
            block = cv2.resize(smooth, (cols // 2, j1 - j0), dst=dst,
                               interpolation=cv2.INTER_AREA)
            if block.ctypes.data != dst.ctypes.data:  # OpenCV did not write in place
                dst[...] = block
        else:
            smooth = cv2.sepFilter2D(data[s0:s1], cv2.CV_32F, _BINOMIAL_6, _BINOMIAL_6,
                                     anchor=(2, 2), borderType=cv2.BORDER_REFLECT)
            out[j0:j1] = smooth[2 * j0 - s0:2 * j1 - s0:2, ::2]
    return out


def level_gain(n: int, power: int) -> np.ndarray:
    """Per DCT-II coefficient k < n // 2 of a length-``n`` axis: the factor cos^p(πk/2n)/√2
    by which one level of filter power ``power`` scales it (the level's own coefficient k
    is this times the input's, less the alias term)."""
    k = np.arange(n // 2)
    return np.cos(np.pi * k / (2.0 * n)) ** power / np.sqrt(2.0)


def halve_binomial6_exact_uint8(band: np.ndarray, out: np.ndarray | None = None
                                ) -> np.ndarray:
    """The p = 5 level of an even-sized uint8 band, exactly: every value is a multiple of
    1/1024 in [0, 255], computed without rounding in float32 (:func:`halve_binomial6` with
    ``exact_sums``: 8-bit values are multiples of 1/64). Bit-identical on every machine, so
    a stored, rounded copy of it is too."""
    if band.dtype != np.uint8:
        raise TypeError(f"a uint8 band is needed, got {band.dtype}")
    if band.shape[0] % 2 or band.shape[1] % 2:
        raise ValueError(f"both sides must be even, got {band.shape}")
    return halve_binomial6(band, out=out, exact_sums=True)
