"""Pure geometric image helpers shared by forward models and fits.

``fourier_shift`` moves an image by a sub-pixel offset; ``affine_field`` and
``warp_to_fine_grid`` carry a shift + rotation + scale field from a coarse grid to the
image on a finer one; ``step_side`` gives the pixels on one side of a straight line.
They live here (not in :mod:`geosim.diagnose`) so that the effect catalogue, the seam
finder and the fitters can all use them without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import ndimage

__all__ = ["fourier_shift", "step_side", "AffineField", "affine_field", "warp_to_fine_grid"]

#: largest departure (px) of a displacement field from its affine fit that
#: :func:`affine_field` accepts
AFFINE_TOLERANCE_PX = 1e-6


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


@dataclass(frozen=True)
class AffineField:
    """A displacement field affine in the pixel position (pixels of its grid).

    d_col(r, c) = ``col[0]`` + ``col[1]`` · c + ``col[2]`` · r, and d_row likewise with
    ``row``, at pixel indices (r, c) (a pixel's centre at its index)."""

    col: tuple[float, float, float]
    row: tuple[float, float, float]


def affine_field(d_col: np.ndarray, d_row: np.ndarray) -> AffineField:
    """The affine form of a displacement field given as (rows, cols) maps (px).

    Raises
    ------
    ValueError
        When the maps depart from their affine fit by more than
        :data:`AFFINE_TOLERANCE_PX` (a field that is not a shift + rotation + scale).
    """
    d_col = np.asarray(d_col, float)
    d_row = np.asarray(d_row, float)
    rows, cols = np.indices(d_col.shape)
    design = np.column_stack([np.ones(d_col.size), cols.ravel(), rows.ravel()])
    coef = []
    for d in (d_col, d_row):
        c = np.linalg.lstsq(design, d.ravel(), rcond=None)[0]
        if np.max(np.abs(design @ c - d.ravel())) > AFFINE_TOLERANCE_PX:
            raise ValueError("the displacement field is not affine in the pixel position "
                             "(a shift + rotation + scale field was expected)")
        coef.append(tuple(float(v) for v in c))
    return AffineField(col=coef[0], row=coef[1])  # type: ignore[arg-type]


def warp_to_fine_grid(image: np.ndarray, field: AffineField, phi: int) -> np.ndarray:
    """Move an image on a grid ``phi`` times finer than the field's: out(x) = image(x − d(x)),
    d the field carried to the fine grid (cubic spline, reflected at the edges).

    A coarse pixel with index r covers the fine pixels φr … φr + φ − 1, its centre at fine
    index φr + (φ − 1)/2; a displacement of d coarse pixels is φ·d fine pixels.

    Parameters
    ----------
    image
        (rows, cols) or (bands, rows, cols) on the fine grid.
    field
        The displacement on the coarse grid (:func:`affine_field`), coarse pixels.
    phi
        Fine pixels per coarse pixel (whole number).

    Returns
    -------
    numpy.ndarray
        float64 array of the input's shape.
    """
    arr = np.asarray(image, dtype=float)
    if arr.ndim == 3:
        return np.stack([warp_to_fine_grid(b, field, phi) for b in arr])
    h = (phi - 1) / 2.0
    a0, a1, a2 = field.col
    b0, b1, b2 = field.row
    # fine displacement at fine index (R, C): φ·d((R − h)/φ, (C − h)/φ)
    #   d_col_f = φ a0 + a1 (C − h) + a2 (R − h), d_row_f likewise with b;
    # the source (R, C) − d_f, as a matrix on (R, C) plus an offset
    matrix = np.array([[1.0 - b2, -b1], [-a2, 1.0 - a1]])
    offset = np.array([-phi * b0 + (b1 + b2) * h, -phi * a0 + (a1 + a2) * h])
    return ndimage.affine_transform(arr, matrix, offset=offset, order=3, mode="reflect",
                                    prefilter=True)
