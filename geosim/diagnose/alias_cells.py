"""Alias cells: the parts of a simulation that sampling folds from beyond the Nyquist.

The transfer fits model a blur as a transfer multiplying the *sampled* simulation,
H(f) · G(Q)(f). A blur that acts on the ground (a detector box, the atmosphere, a smear)
acts before sampling: where the optics pass content above the product Nyquist (Q < 2,
cut-off 1/Q > 0.5 cycles/px), sampling folds a component of frequency f + k (k a pair of
whole cycles per pixel) onto f, and the blur damped it by H(f + k), not H(f). At Q 0.85 and
a 1.44 px detector box the two models differ by more than the box's own signature, and Q
absorbs the box (round 21, ``benchmarks/diagnose_alias_cells.py``).

This module splits a simulation into the pieces folded from each alias cell (the UAV
image filtered by the cell's mask on the fine grid, before the optics; complex, since one
cell is not its own mirror image; the cells partition the spectrum, so the pieces and the
k = 0 part sum to the simulation). The fits then model

    T(f) = g · [G(Q)(f) · H(f) + Σ_{k ≠ 0} G_k(Q)(f) · (H(f + k) − H(f))],

exact for any shift-invariant blur, and the same as without pieces at Q ≥ 2 (no content
beyond the Nyquist) — where none are made.

Where the diagnosis uses them (:func:`geosim.diagnose.stage_blur.split_alias_cells`): fits
that start below :data:`SPLIT_Q_MAX`, no JPEG in the model; made from the UAV image with
its invalid pixels filled and filled on the product grid as the simulations are (since
round 37; before, a flight's nodata rim turned them off); tapered as the simulations under
a change taper. A model holding a resampling gets no cell
correction (:func:`geosim.diagnose.fit.model_transfer`): that scene was sampled on its
native grid, whose alias cells are not the product's.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
import scipy.fft

__all__ = ["ALIAS_CELLS", "ALIAS_Q_MAX", "SPLIT_Q_MAX", "AliasPieces", "cell_parts",
           "iter_cell_parts", "alias_pieces"]

#: the alias cells k = (k_row, k_col) ≠ (0, 0), cycles per product pixel (content beyond
#: 1.5 cycles/px, which only Q < 0.67 passes, joins the |k| = 1 cells)
ALIAS_CELLS: tuple[tuple[int, int], ...] = tuple(
    (ky, kx) for ky in (-1, 0, 1) for kx in (-1, 0, 1) if (ky, kx) != (0, 0))
#: at and above this Q the optics pass nothing above the product Nyquist: no pieces
ALIAS_Q_MAX = 2.0
#: the scenes are split only where the fits start below this Q (the model's Q at the
#: spectral setup): the split costs ~16 paper-model renders per grid member below 2, and
#: fits that start higher rarely end below 2 (development, round 28: 12 of 376 rows
#: calibrated at Q >= 2.5; a refit from a lower Q splits again)
SPLIT_Q_MAX = 2.5

#: per Q of the grid: {cell: complex grey piece (rows, cols)} or None (no content beyond
#: the Nyquist at that Q)
AliasPieces = list[dict[tuple[int, int], np.ndarray] | None]


def iter_cell_parts(fine: np.ndarray, phi: int
                    ) -> Iterator[tuple[tuple[int, int], np.ndarray]]:
    """(cell, the part of a 2-D fine-grid image in that alias cell: complex, same shape),
    one cell at a time, so that a caller keeping less than the parts (a simulator's
    truncated coefficients) never holds all eight full-size complex images at once.

    The image is reflect-padded (1/8 of its side, ≥ 16 px, as
    :func:`geosim.physics.otf.apply_transfer` pads) and split by the cell of each FFT
    frequency: round(f · phi) per axis, clipped to ±1 (f in cycles per fine pixel)."""
    arr = np.asarray(fine, float)
    pad = min(max(16, max(arr.shape) // 8), min(arr.shape) - 1)
    p = np.pad(arr, pad, mode="reflect")
    spec = scipy.fft.fft2(p)
    ky = np.clip(np.round(np.fft.fftfreq(p.shape[0]) * phi), -1, 1)[:, None]
    kx = np.clip(np.round(np.fft.fftfreq(p.shape[1]) * phi), -1, 1)[None, :]
    for c in ALIAS_CELLS:
        yield c, scipy.fft.ifft2(spec * ((ky == c[0]) & (kx == c[1])))[pad:-pad, pad:-pad]


def cell_parts(fine: np.ndarray, phi: int) -> dict[tuple[int, int], np.ndarray]:
    """The part of a 2-D fine-grid image in each alias cell (complex, same shape):
    :func:`iter_cell_parts` gathered."""
    return dict(iter_cell_parts(fine, phi))


def alias_pieces(cell_sims: dict[tuple[int, int], tuple[Callable[[float], np.ndarray],
                                                         Callable[[float], np.ndarray]]],
                 q_grid: Sequence[float], *, q_min: float,
                 finish: Callable[[np.ndarray], np.ndarray] | None = None) -> AliasPieces:
    """The pieces of the simulations at ``q_grid``: ``cell_sims`` gives, per cell, the
    paper model of the real and the imaginary part of the cell's (moved) UAV image;
    ``finish`` is what the simulations went through after sampling (a linear map: the
    registration's move of the sampled image), applied to both parts. None at
    Q ≥ :data:`ALIAS_Q_MAX` and below ``q_min`` (the grid's simulations there come from
    another renderer)."""
    out: AliasPieces = []
    for q in q_grid:
        if q >= ALIAS_Q_MAX or q < q_min:
            out.append(None)
            continue
        d: dict[tuple[int, int], np.ndarray] = {}
        for c, (re, im) in cell_sims.items():
            a, b = _grey2d(re(q)), _grey2d(im(q))
            if finish is not None:
                a, b = finish(a), finish(b)
            d[c] = a + 1j * b
        out.append(d)
    return out


def _grey2d(img: Any) -> np.ndarray:
    a = np.asarray(img, float)
    return a[0] if a.ndim == 3 else a

