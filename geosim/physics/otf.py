"""Optical transfer functions and their application in the Fourier domain.

Conventions
-----------
* Spatial frequencies are in cycles per pixel of the grid the image is on
  (``numpy.fft.fftfreq`` units); ``fx`` runs along columns (east), ``fy`` along
  rows (south, since row numbers grow southwards on a north-up grid).
* ``direction_deg`` / ``azimuth_deg`` are measured clockwise from grid north,
  in [0, 180): 0 = north–south, 90 = east–west. A unit vector at angle θ has
  (east, north) = (sin θ, cos θ), i.e. (col, row) = (sin θ, −cos θ).
* Q is defined on the satellite detector pitch; on a grid with ``phi`` pixels
  per satellite pixel (10 for 0.05 m UAV → 0.5 m), the circular-aperture OTF
  cuts off at 1 / (Q · phi) cycles per pixel.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.fft

TransferFunction = Callable[[np.ndarray, np.ndarray], np.ndarray]


def frequency_grid(shape: tuple[int, int], *, real: bool = False
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Broadcastable (fy, fx) frequency grids in cycles per pixel.

    Parameters
    ----------
    shape
        (rows, cols) of the array to be transformed.
    real
        Return the half-plane grid matching ``rfft2`` (last axis ``rfftfreq``).
    """
    rows, cols = shape
    fy = np.fft.fftfreq(rows)[:, np.newaxis]
    fx = (np.fft.rfftfreq(cols) if real else np.fft.fftfreq(cols))[np.newaxis, :]
    return fy, fx


def _circle_overlap(r1: float, r2: float, d: np.ndarray) -> np.ndarray:
    """Area of intersection of two circles of radii r1, r2 with centres d apart."""
    d = np.asarray(d, dtype=float)
    out = np.zeros_like(d)
    inside = d <= abs(r1 - r2)
    out[inside] = np.pi * min(r1, r2) ** 2
    part = (~inside) & (d < r1 + r2)
    dp = d[part]
    a1 = np.clip((dp**2 + r1**2 - r2**2) / (2 * dp * r1), -1, 1)
    a2 = np.clip((dp**2 + r2**2 - r1**2) / (2 * dp * r2), -1, 1)
    k = (-dp + r1 + r2) * (dp + r1 - r2) * (dp - r1 + r2) * (dp + r1 + r2)
    out[part] = r1**2 * np.arccos(a1) + r2**2 * np.arccos(a2) - 0.5 * np.sqrt(np.maximum(k, 0))
    return out


def circular_aperture_otf(f_radial: np.ndarray, *, cutoff_cyc_per_px: float,
                          obscuration: float = 0.0) -> np.ndarray:
    """Diffraction-limited OTF of a circular (optionally annular) aperture.

    The OTF is the normalised autocorrelation of the pupil: the overlap area of
    the pupil with a copy shifted by 2ν pupil radii, ν = f / f_c. For a clear
    aperture this is (2/π)(arccos ν − ν√(1 − ν²)).

    Parameters
    ----------
    f_radial
        Radial spatial frequency, cycles per pixel.
    cutoff_cyc_per_px
        Incoherent cutoff f_c = D / (λ f) expressed in cycles per pixel.
    obscuration
        Central obscuration as a ratio of diameters, in [0, 1).

    Returns
    -------
    numpy.ndarray
        OTF values (real, 1 at f = 0, 0 beyond the cutoff).
    """
    if not 0.0 <= obscuration < 1.0:
        raise ValueError(f"obscuration must be in [0, 1), got {obscuration}")
    d = 2.0 * np.abs(np.asarray(f_radial, dtype=float)) / cutoff_cyc_per_px
    eps = float(obscuration)
    area = _circle_overlap(1.0, 1.0, d)
    if eps > 0:
        area = area - 2 * _circle_overlap(1.0, eps, d) + _circle_overlap(eps, eps, d)
    return area / (np.pi * (1.0 - eps**2))


def optics_otf(fy: np.ndarray, fx: np.ndarray, *, q: float, phi: float = 1.0,
               obscuration: float = 0.0) -> np.ndarray:
    """Circular-aperture OTF for a given Q on a grid with ``phi`` px per satellite pixel."""
    if q <= 0:
        raise ValueError(f"q must be > 0, got {q}")
    return circular_aperture_otf(np.hypot(fy, fx), cutoff_cyc_per_px=1.0 / (q * phi),
                                 obscuration=obscuration)


def detector_otf(fy: np.ndarray, fx: np.ndarray, *, pitch_px: float) -> np.ndarray:
    """Transfer function of a square detector integrating over ``pitch_px`` pixels.

    sinc(fx·p)·sinc(fy·p) with numpy's normalised sinc; zeros at multiples of 1/p.
    """
    return np.sinc(fx * pitch_px) * np.sinc(fy * pitch_px)


def atmospheric_otf(fy: np.ndarray, fx: np.ndarray, *, f0_cyc_per_px: float) -> np.ndarray:
    """Long-exposure turbulence/scattering MTF, exp(−(f / f0)^(5/3))."""
    if f0_cyc_per_px <= 0:
        raise ValueError(f"f0_cyc_per_px must be > 0, got {f0_cyc_per_px}")
    return np.exp(-((np.hypot(fy, fx) / f0_cyc_per_px) ** (5.0 / 3.0)))


def along_direction(fy: np.ndarray, fx: np.ndarray, direction_deg: float) -> np.ndarray:
    """Frequency component along a direction measured clockwise from grid north."""
    theta = np.deg2rad(direction_deg)
    return fx * np.sin(theta) - fy * np.cos(theta)


def motion_otf(fy: np.ndarray, fx: np.ndarray, *, length_px: float,
               direction_deg: float) -> np.ndarray:
    """Linear smear of ``length_px`` along ``direction_deg``: sinc(L · f_parallel)."""
    return np.sinc(length_px * along_direction(fy, fx, direction_deg))


def off_nadir_otf(fy: np.ndarray, fx: np.ndarray, *, sigma_px: float,
                  azimuth_deg: float) -> np.ndarray:
    """Smooth anisotropic blur along the look azimuth: a Gaussian of ``sigma_px``.

    exp(−2π²σ²f∥²); no zeros, unlike motion smear.
    """
    f_par = along_direction(fy, fx, azimuth_deg)
    return np.exp(-2.0 * np.pi**2 * sigma_px**2 * f_par**2)


def apply_transfer(image: np.ndarray, transfer: TransferFunction, *,
                   pad_px: int | None = None, workers: int | None = None) -> np.ndarray:
    """Filter a 2-D image (or stack with bands first) by a real transfer function.

    The image is reflect-padded by ``pad_px`` (default: 1/8 of the larger side,
    at least 16) so the periodic FFT does not wrap content across edges, filtered
    with ``rfft2``, and cropped back. ``transfer(fy, fx)`` receives half-plane
    frequency grids in cycles per pixel. The mean is preserved when H(0) = 1.

    Returns
    -------
    numpy.ndarray
        Float64 (or float32 when the input is float32) filtered image, same shape.
    """
    arr = np.asarray(image)
    out_dtype = np.float32 if arr.dtype == np.float32 else np.float64
    if arr.ndim == 3:
        return np.stack([apply_transfer(b, transfer, pad_px=pad_px, workers=workers)
                         for b in arr]).astype(out_dtype, copy=False)
    rows, cols = arr.shape
    if pad_px is None:
        pad_px = max(16, max(rows, cols) // 8)
    pad_r, pad_c = min(pad_px, rows - 1), min(pad_px, cols - 1)
    padded = np.pad(arr.astype(out_dtype, copy=False), ((pad_r, pad_r), (pad_c, pad_c)),
                    mode="reflect")
    shape = (scipy.fft.next_fast_len(padded.shape[0], real=True),
             scipy.fft.next_fast_len(padded.shape[1], real=True))
    spectrum = scipy.fft.rfft2(padded, s=shape, workers=workers)
    fy, fx = frequency_grid(shape, real=True)
    spectrum *= transfer(fy, fx).astype(spectrum.real.dtype, copy=False)
    filtered = scipy.fft.irfft2(spectrum, s=shape, workers=workers)
    return filtered[pad_r:pad_r + rows, pad_c:pad_c + cols].astype(out_dtype, copy=False)


def compose(*transfers: TransferFunction) -> TransferFunction:
    """Product of transfer functions (cascaded linear shift-invariant blurs)."""
    def product(fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        h = np.ones(np.broadcast_shapes(fy.shape, fx.shape))
        for t in transfers:
            h = h * t(fy, fx)
        return h
    return product
