"""Cubic convolution (Keys) with any kernel parameter ``a``: the kernel, its transfer and a
separable resize.

Processors differ in ``a``: OpenCV's bicubic uses a = −0.75, GDAL's ``cubic``, Pillow's
bicubic and most remote-sensing "cubic convolution" a = −0.5 (Keys 1981, the value that
reproduces quadratics). The kernel is linear in ``a`` (k = k₀ + a·k₁), and so is its
transfer. Pure numerics, no I/O.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

__all__ = ["OPENCV_A", "KEYS_A", "keys_kernel", "cubic_mtf", "cubic_resize", "cubic_weights"]

#: OpenCV's INTER_CUBIC
OPENCV_A = -0.75
#: Keys' third-order value: GDAL ``cubic``, Pillow ``BICUBIC``
KEYS_A = -0.5


def keys_kernel(x: np.ndarray, a: float = OPENCV_A) -> np.ndarray:
    """The cubic-convolution kernel at ``x`` (samples): 1 at 0, 0 at the other integers,
    support (−2, 2)."""
    ax = np.abs(np.asarray(x, dtype=float))
    return np.where(ax <= 1, (a + 2) * ax**3 - (a + 3) * ax**2 + 1,
                    np.where(ax < 2, a * ax**3 - 5 * a * ax**2 + 8 * a * ax - 4 * a, 0.0))


@lru_cache(maxsize=1)
def _mtf_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ν, transfer of k₀, transfer of k₁) on ν = 0–8 cycles per sample (Riemann sum)."""
    x = np.linspace(-2.0, 2.0, 4001)
    dx = x[1] - x[0]
    k0 = keys_kernel(x, 0.0)
    k1 = keys_kernel(x, 1.0) - k0
    nu = np.linspace(0.0, 8.0, 3201)
    c = np.cos(2 * np.pi * nu[:, None] * x[None, :]) * dx
    return nu, c @ k0, c @ k1


def cubic_mtf(nu: np.ndarray, a: float = OPENCV_A) -> np.ndarray:
    """Transfer of the kernel at ``nu`` cycles per sample (1 at 0; 0 beyond 8)."""
    table_nu, t0, t1 = _mtf_tables()
    anu = np.abs(nu)
    return np.interp(anu, table_nu, t0, right=0.0) + a * np.interp(anu, table_nu, t1,
                                                                    right=0.0)


def cubic_weights(src: np.ndarray, n_in: int, a: float) -> np.ndarray:
    """(len(src), n_in) cubic-convolution weights of ``n_in`` samples at the input
    coordinates ``src`` (in samples, 0 at the first sample's centre); edge samples
    replicated, as OpenCV does."""
    src = np.asarray(src, dtype=float)
    base = np.floor(src).astype(int)
    w = np.zeros((len(src), n_in))
    rows = np.arange(len(src))
    for t in range(-1, 3):
        np.add.at(w, (rows, np.clip(base + t, 0, n_in - 1)), keys_kernel(src - (base + t), a))
    return w


def _weights(n_in: int, n_out: int, a: float) -> np.ndarray:
    """(n_out, n_in) interpolation matrix with OpenCV's geometry: output pixel centre j maps
    to input coordinate (j + 0.5) · n_in / n_out − 0.5."""
    return cubic_weights((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, n_in, a)


def cubic_resize(band: np.ndarray, shape: tuple[int, int], a: float = OPENCV_A) -> np.ndarray:
    """Resize a 2-D ``band`` to ``shape`` (rows, cols) by cubic convolution with ``a``.

    a = −0.75 is OpenCV's ``INTER_CUBIC`` itself (float32, as OpenCV computes it); any
    other ``a`` is the same geometry as separable matrix products (float64).
    """
    rows, cols = shape
    if a == OPENCV_A:
        return cv2.resize(np.asarray(band, dtype=np.float32), (cols, rows),
                          interpolation=cv2.INTER_CUBIC)
    b = np.asarray(band, dtype=float)
    return _weights(b.shape[0], rows, a) @ b @ _weights(b.shape[1], cols, a).T
