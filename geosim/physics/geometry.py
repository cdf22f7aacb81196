"""Pure geometric image helpers shared by forward models and fits.

``fourier_shift`` moves an image by a sub-pixel offset; ``step_side`` gives the pixels
on one side of a straight line. They live here (not in :mod:`geosim.diagnose`) so that
the effect catalogue, the seam finder and the fitters can all use them without importing
each other.
"""

from __future__ import annotations

import numpy as np
import scipy.fft

__all__ = ["fourier_shift", "step_side"]


def fourier_shift(image: np.ndarray, shift_px: tuple[float, float], *,
                  pad_px: int = 16) -> np.ndarray:
    """Move an image (2-D or bands-first) by a sub-pixel offset, reflect-padded.

    Parameters
    ----------
    image
        (rows, cols) or (bands, rows, cols).
    shift_px
        (d_col, d_row) in pixels; positive moves content right (east) / down (south).
    pad_px
        Reflect padding in pixels around the image (limits wrap-around of the FFT).

    Returns
    -------
    numpy.ndarray
        float64 array of the input's shape.
    """
    arr = np.asarray(image, dtype=float)
    if arr.ndim == 3:
        return np.stack([fourier_shift(b, shift_px, pad_px=pad_px) for b in arr])
    dc, dr = shift_px
    if dc == 0 and dr == 0:
        return arr.copy()
    pad = min(pad_px + int(np.ceil(max(abs(dc), abs(dr)))), min(arr.shape) - 1)
    padded = np.pad(arr, pad, mode="reflect")
    spec = scipy.fft.fft2(padded)
    fy = np.fft.fftfreq(padded.shape[0])[:, None]
    fx = np.fft.fftfreq(padded.shape[1])[None, :]
    spec *= np.exp(-2j * np.pi * (fx * dc + fy * dr))
    out = np.real(scipy.fft.ifft2(spec))
    return out[pad:pad + arr.shape[0], pad:pad + arr.shape[1]]


def step_side(shape: tuple[int, int], *, normal_deg: float, offset_px: float) -> np.ndarray:
    """Bool mask (rows, cols) of the pixels beyond a line.

    The line's normal points ``normal_deg`` degrees from the column axis toward the row
    axis; a pixel is beyond it when the projection of its centre (relative to the image
    centre, pixels) on the normal exceeds ``offset_px``.
    """
    rows, cols = shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    th = np.radians(normal_deg)
    proj = (cc + 0.5 - cols / 2.0) * np.cos(th) + (rr + 0.5 - rows / 2.0) * np.sin(th)
    return proj > offset_px
