"""A product resampled from a coarser native grid of any pitch and phase.

A satellite product delivered at 0.5 m from detectors of a coarser native GSD (e.g. 0.65–0.8 m)
is two steps: each native detector averages the optics' image over its area, and cubic
convolution interpolates the native samples onto the product grid. On a crop of a product
the native pitch (native GSD / product GSD) is a real number and the native grid's phase
(where its first pixel edge lies against the product's) is arbitrary; below Q ≈ 2, where
the optics pass content above the native Nyquist, the aliasing the native sampling makes
depends on both (development c09: spectral error 0.146 at the grid's phase 0, 0.046 near the
true one).

:func:`native_area` integrates a fine-grid image over native pixels at any pitch and phase
(overlap weights, exact for box detectors on the fine pixels' piecewise-constant image);
:func:`native_to_product` interpolates native samples onto product pixel centres by cubic
convolution (:func:`geosim.physics.cubic.cubic_weights`, edge samples replicated as OpenCV
does). Pure numerics, no I/O.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from geosim.physics.cubic import OPENCV_A, cubic_weights

#: per-axis matrices kept (a pitch scan renders each native phase of an axis with every
#: phase of the other axis, and both cubic kernels: the same matrices many times)
AXIS_CACHE = 64

__all__ = ["native_edges", "native_area", "native_area_dct", "native_rows_dct",
           "native_cols_dct", "native_to_product", "render_through_native"]


def native_edges(n_px: int, native_pitch_px: float, phase_px: float) -> np.ndarray:
    """Edges of the native pixels covering ``n_px`` product pixels, product-pixel
    coordinates (0 at the product's first pixel edge): phase + k · pitch for every k with
    a native pixel overlapping [0, n_px); ``phase_px`` is taken modulo the pitch."""
    p = float(native_pitch_px)
    if p <= 0:
        raise ValueError(f"native_pitch_px must be positive, got {native_pitch_px}")
    ph = float(phase_px) % p
    k0 = -1 if ph > 0 else 0
    k1 = int(np.ceil((n_px - ph) / p))
    return ph + p * np.arange(k0, k1 + 1)


def _area_weights(edges_fine: np.ndarray, n: int) -> np.ndarray:
    """(n_native, n) weights of the fine pixels [i, i + 1) in each native pixel
    [e_k, e_k+1) (fine-pixel coordinates, clipped to [0, n]): overlap over width."""
    e = np.clip(edges_fine, 0.0, float(n))
    i = np.arange(n)
    lo, hi = e[:-1, None], e[1:, None]
    overlap = np.clip(np.minimum(i + 1, hi) - np.maximum(i, lo), 0.0, None)
    return overlap / np.maximum(hi - lo, 1e-12)


def native_area(fine: np.ndarray, phi: int, native_pitch_px: float,
                phase_px: tuple[float, float] = (0.0, 0.0)
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each native detector's mean over its area.

    Parameters
    ----------
    fine
        Image on the fine grid, (..., rows · phi, cols · phi).
    phi
        Fine pixels per product pixel.
    native_pitch_px
        Native pitch, product pixels.
    phase_px
        (row, col) position of a native pixel edge, product pixels (modulo the pitch).

    Returns
    -------
    native, centres_row, centres_col
        The native samples (..., n_rows, n_cols) and their centres, product-pixel
        coordinates (detectors cut by the scene's edge average the part inside).
    """
    rows, cols = fine.shape[-2] // phi, fine.shape[-1] // phi
    er = native_edges(rows, native_pitch_px, phase_px[0])
    ec = native_edges(cols, native_pitch_px, phase_px[1])
    # separable: one matrix product per axis (float32, as the fine image is kept)
    wr = _area_weights(er * phi, rows * phi).astype(np.float32)
    wc = _area_weights(ec * phi, cols * phi).astype(np.float32)
    img = np.asarray(fine[..., :rows * phi, :cols * phi], dtype=np.float32)
    return (wr @ img @ wc.T).astype(float), _centres(er), _centres(ec)


def _centres(edges: np.ndarray) -> np.ndarray:
    """Centres of the native pixels between ``edges``."""
    return (edges[:-1] + edges[1:]) / 2


def _dct_box_matrix(edges: np.ndarray, n: int, n_coef: int) -> np.ndarray:
    """(n_native, n_coef) means over [e_j, e_j+1] (positions from the image's first edge,
    fine pixels) of the first ``n_coef`` orthonormal DCT-II basis functions of an ``n``-pixel
    axis, continued between the pixel centres: √(c_k / n) cos(π k s / n) (c_0 = 1, else 2)."""
    k = np.arange(n_coef)[np.newaxis, :]
    s0, s1 = edges[:-1, np.newaxis], edges[1:, np.newaxis]
    width = np.maximum(s1 - s0, 1e-12)
    # the sines at every edge once: a native pixel's far edge is the next one's near edge
    sines = np.sin(np.pi * k * edges[:, np.newaxis] / n)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(k == 0, 1.0, n * (sines[1:] - sines[:-1])
                        / (np.pi * np.maximum(k, 1) * width))
    return np.where(k == 0, np.sqrt(1.0 / n), np.sqrt(2.0 / n)) * mean


def native_area_dct(coef: np.ndarray, fine_shape: tuple[int, int], phi: int,
                    native_pitch_px: float, phase_px: tuple[float, float] = (0.0, 0.0)
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`native_area` of the image whose first orthonormal DCT-II coefficients are
    ``coef`` (..., K_rows, K_cols; the rest zero, as past the optics' cut-off), the image
    continued between pixel centres by its cosine series (the band-limited image the
    optics make, where :func:`native_area` takes each fine pixel as constant). Two small
    matrix products per band instead of an inverse transform of the fine image
    (:func:`native_rows_dct` then :func:`native_cols_dct`).

    ``fine_shape``: (rows, cols) of the fine image, pixels; the scene is its first
    (rows // phi) · phi × (cols // phi) · phi pixels."""
    rows, cr = native_rows_dct(coef, int(fine_shape[0]), phi, native_pitch_px, phase_px[0])
    nat, cc = native_cols_dct(rows, int(fine_shape[1]), phi, native_pitch_px, phase_px[1])
    return nat, cr, cc


def native_rows_dct(coef: np.ndarray, n_rows_fine: int, phi: int, native_pitch_px: float,
                    phase_row_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The row step of :func:`native_area_dct`: each native row's mean of the cosine
    series ``coef`` (..., K_rows, K_cols) → (..., n_native_rows, K_cols), and the native
    rows' centres (product px). Kept by callers that render one native row phase with
    several column phases (:meth:`geosim.diagnose.simulate.QSimulator.native`)."""
    mr, cr = _axis_box(int(n_rows_fine), phi, float(native_pitch_px), float(phase_row_px),
                       coef.shape[-2])
    return mr @ coef, cr


def native_cols_dct(rows: np.ndarray, n_cols_fine: int, phi: int, native_pitch_px: float,
                    phase_col_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The column step of :func:`native_area_dct` on :func:`native_rows_dct`'s ``rows``
    (..., n_native_rows, K_cols): the native samples (..., n_native_rows, n_native_cols)
    and the native columns' centres (product px)."""
    mc, cc = _axis_box(int(n_cols_fine), phi, float(native_pitch_px), float(phase_col_px),
                       rows.shape[-1])
    return rows @ mc.T, cc


@lru_cache(maxsize=AXIS_CACHE)
def _axis_box(n: int, phi: int, pitch_px: float, phase_px: float, n_coef: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """(:func:`_dct_box_matrix` of one axis of ``n`` fine pixels, the native centres),
    read-only: cached, shared by every band and render at this pitch and phase."""
    n_px = n // phi
    edges = native_edges(n_px, pitch_px, phase_px)
    out = (_dct_box_matrix(np.clip(edges * phi, 0.0, n_px * phi), n, n_coef), _centres(edges))
    for a in out:
        a.setflags(write=False)
    return out


def native_to_product(native: np.ndarray, centres_row: np.ndarray, centres_col: np.ndarray,
                      shape: tuple[int, int], cubic_a: float = OPENCV_A) -> np.ndarray:
    """Cubic convolution (kernel parameter ``cubic_a``) of native samples (..., n_rows,
    n_cols) at ``centres_row`` × ``centres_col`` onto the product grid ``shape``."""
    wr = _cubic_weights(centres_row, shape[0], cubic_a)
    wc = _cubic_weights(centres_col, shape[1], cubic_a)
    return wr @ native @ wc.T


def _cubic_weights(centres: np.ndarray, n_out: int, a: float) -> np.ndarray:
    """(n_out, n_in) cubic-convolution weights from samples at ``centres`` (evenly
    spaced, product-pixel coordinates) to product pixel centres j + 0.5; kept (a native
    grid's first centre, spacing and count determine them), read-only."""
    p = float(centres[1] - centres[0]) if len(centres) > 1 else 1.0
    return _cubic_weights_of(float(centres[0]), p, len(centres), int(n_out), float(a))


@lru_cache(maxsize=AXIS_CACHE)
def _cubic_weights_of(first_px: float, pitch_px: float, n_in: int, n_out: int, a: float
                      ) -> np.ndarray:
    """:func:`_cubic_weights` from ``n_in`` centres ``first_px + k · pitch_px``."""
    w = cubic_weights((np.arange(n_out) + 0.5 - first_px) / pitch_px, n_in, a)
    w.setflags(write=False)
    return w


def render_through_native(fine: np.ndarray, phi: int, native_pitch_px: float, *,
                          phase_px: tuple[float, float] = (0.0, 0.0),
                          cubic_a: float = OPENCV_A) -> np.ndarray:
    """The product a native grid of ``native_pitch_px`` at ``phase_px`` makes of the
    fine-grid image ``fine`` (the optics' image, (..., rows · phi, cols · phi)):
    :func:`native_area` then :func:`native_to_product`, (..., rows, cols), float64."""
    nat, cr, cc = native_area(fine, phi, native_pitch_px, phase_px)
    rows, cols = fine.shape[-2] // phi, fine.shape[-1] // phi
    return native_to_product(nat, cr, cc, (rows, cols), cubic_a)
