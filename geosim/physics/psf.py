"""Point spread function of a diffraction-limited circular aperture, from Q.

Q = λ f / (D p) is defined on the satellite detector pitch p. On a grid with
``phi`` pixels per satellite pixel (φ = 10 for a 0.05 m UAV grid under a 0.5 m
satellite grid) the incoherent cutoff of the optics is 1 / (Q φ) cycles per
pixel and the PSF is the Airy pattern

    I(r) = (2 J1(x) / x)²,   x = π r / (Q φ),   r in pixels,

whose first zero lies at r = 1.2197 Q φ pixels. With a central obscuration of
diameter ratio ε the amplitude becomes (2 J1(x)/x − ε² 2 J1(εx)/(εx)) / (1 − ε²).

Two constructions are provided and must agree (``tests/test_psf.py``):

* :func:`airy_psf`, the analytic pattern sampled at pixel centres;
* :func:`pupil_psf`, the paper's construction: the squared modulus of the
  discrete Fourier transform of a sampled circular pupil whose radius is chosen
  so that the cutoff is exactly 1 / (Q φ) cycles per pixel.

The PSF's wings are wide: 99.5 % of the energy lies within about 40.5 Q φ
pixels (:func:`energy_radius_px`), i.e. a 3500-pixel kernel at Q = 4.34 and
φ = 10. Blurring an image therefore uses the Fourier-domain counterpart,
:func:`geosim.physics.otf.optics_otf`, which is exact and untruncated; these
kernels serve validation, plotting and small-image convolution.

References
----------
Born, M. & Wolf, E., *Principles of Optics*, §8.5.2 (Airy pattern, encircled energy).
Mahajan, V. N. (1981), "Zernike annular polynomials for imaging systems with
annular pupils", JOSA 71, 75–85 (annular-pupil encircled energy).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.integrate
import scipy.optimize
import scipy.special

#: Position of the first zero of J1 (x = 3.8317…), so the Airy first dark ring is at
#: r = FIRST_ZERO_X / π · Q φ = 1.2197 Q φ pixels.
FIRST_ZERO_X = float(scipy.special.jn_zeros(1, 1)[0])


def _check(q: float, phi: float, obscuration: float) -> None:
    if not (np.isfinite(q) and q > 0):
        raise ValueError(f"q must be a positive number, got {q!r}")
    if not (np.isfinite(phi) and phi > 0):
        raise ValueError(f"phi must be a positive number of pixels per satellite pixel, "
                         f"got {phi!r}")
    if not 0.0 <= obscuration < 1.0:
        raise ValueError(f"obscuration must be a diameter ratio in [0, 1), got {obscuration!r}")


def first_zero_px(q: float, *, phi: float = 10) -> float:
    """Radius of the first dark ring of the clear-aperture Airy pattern, pixels.

    r₀ = 3.8317 / π · Q φ = 1.2197 Q φ.
    """
    _check(q, phi, 0.0)
    return FIRST_ZERO_X / math.pi * q * phi


def airy_intensity(r_px: np.ndarray | float, *, q: float, phi: float = 10,
                   obscuration: float = 0.0) -> np.ndarray:
    """Airy intensity at radius ``r_px`` (pixels), normalised to 1 at r = 0.

    Parameters
    ----------
    r_px
        Radial distance from the PSF centre, pixels of the grid (UAV pixels).
    q
        Q = λ f / (D p) on the satellite detector pitch (dimensionless).
    phi
        Grid pixels per satellite pixel (dimensionless; 10 for 0.05 m → 0.5 m).
    obscuration
        Central obscuration as a ratio of diameters, in [0, 1).

    Returns
    -------
    numpy.ndarray
        Intensity relative to the peak (dimensionless), same shape as ``r_px``.
    """
    _check(q, phi, obscuration)
    x = np.pi * np.abs(np.asarray(r_px, dtype=float)) / (q * phi)
    amp = _jinc(x)
    if obscuration > 0:
        amp = (amp - obscuration**2 * _jinc(obscuration * x)) / (1.0 - obscuration**2)
    return amp * amp


def _jinc(x: np.ndarray) -> np.ndarray:
    """2 J1(x) / x with its limit 1 at x = 0."""
    x = np.asarray(x, dtype=float)
    out = np.ones_like(x)
    nz = x != 0
    out[nz] = 2.0 * scipy.special.j1(x[nz]) / x[nz]
    return out


def encircled_energy(r_px: float, *, q: float, phi: float = 10,
                     obscuration: float = 0.0) -> float:
    """Fraction of the PSF's energy inside a circle of radius ``r_px`` pixels.

    Clear aperture: 1 − J0²(x) − J1²(x) with x = π r / (Q φ). Annular aperture
    (Mahajan 1981): [1 − J0²(x) − J1²(x) + ε²(1 − J0²(εx) − J1²(εx))
    − 4ε ∫₀ˣ J1(t) J1(εt) / t dt] / (1 − ε²).
    """
    _check(q, phi, obscuration)
    x = math.pi * max(float(r_px), 0.0) / (q * phi)
    if x == 0:
        return 0.0

    def clear(t: float) -> float:
        return 1.0 - scipy.special.j0(t) ** 2 - scipy.special.j1(t) ** 2

    if obscuration == 0:
        return float(clear(x))
    eps = obscuration
    cross, _ = scipy.integrate.quad(
        lambda t: scipy.special.j1(t) * scipy.special.j1(eps * t) / t if t > 0 else 0.0,
        0.0, x, limit=max(200, int(x)), epsabs=1e-10, epsrel=1e-10)
    return float((clear(x) + eps**2 * clear(eps * x) - 4 * eps * cross) / (1 - eps**2))


def energy_radius_px(q: float, *, phi: float = 10, energy: float = 0.995,
                     obscuration: float = 0.0) -> float:
    """Smallest radius (pixels) whose circle holds ``energy`` of the PSF's energy.

    For a clear aperture and energy = 0.995 this is about 40.5 Q φ pixels: the
    Airy wings fall only as r⁻³, so 1 − EE(x) ≈ 2 / (π x).
    """
    _check(q, phi, obscuration)
    if not 0.0 < energy < 1.0:
        raise ValueError(f"energy must be a fraction in (0, 1), got {energy!r}")
    scale = q * phi / math.pi  # pixels per unit of x

    def deficit(x: float) -> float:
        return encircled_energy(x * scale, q=q, phi=phi, obscuration=obscuration) - energy

    hi = 4.0
    while deficit(hi) < 0:
        hi *= 2.0
    x = scipy.optimize.brentq(deficit, 1e-9, hi, xtol=1e-9)
    return float(x * scale)


def psf_size_px(q: float, *, phi: float = 10, energy: float = 0.995,
                obscuration: float = 0.0) -> int:
    """Odd side (pixels) of a square kernel holding at least ``energy`` of the PSF.

    The kernel's half-width is the radius of the circle holding ``energy``
    (:func:`energy_radius_px`), rounded up; the square contains that circle,
    so it holds at least as much.
    """
    return 2 * math.ceil(energy_radius_px(q, phi=phi, energy=energy,
                                          obscuration=obscuration)) + 1


def _size_or_default(size_px: int | None, q: float, phi: float, obscuration: float) -> int:
    if size_px is None:
        return psf_size_px(q, phi=phi, obscuration=obscuration)
    size = int(size_px)
    if size != size_px or size < 1 or size % 2 == 0:
        raise ValueError(f"size_px must be a positive odd whole number, got {size_px!r}")
    return size


def airy_psf(q: float, *, phi: float = 10, size_px: int | None = None,
             obscuration: float = 0.0) -> np.ndarray:
    """Analytic Airy PSF sampled at pixel centres, centred, normalised to sum 1.

    Parameters
    ----------
    q
        Q = λ f / (D p) on the satellite detector pitch (dimensionless).
    phi
        Grid pixels per satellite pixel (dimensionless).
    size_px
        Odd kernel side in pixels; default: the side holding ≥ 99.5 % of the
        energy (:func:`psf_size_px`), about 81 Q φ.
    obscuration
        Central obscuration as a ratio of diameters, in [0, 1).

    Returns
    -------
    numpy.ndarray
        (size_px, size_px) float64 kernel, peak at the centre, sum 1.
    """
    _check(q, phi, obscuration)
    size = _size_or_default(size_px, q, phi, obscuration)
    h = size // 2
    offsets = np.arange(-h, h + 1, dtype=float)
    r = np.hypot(offsets[:, np.newaxis], offsets[np.newaxis, :])
    kernel = airy_intensity(r, q=q, phi=phi, obscuration=obscuration)
    return kernel / kernel.sum()


def _disc_coverage(coords: np.ndarray, radius: float, *, supersample: int) -> np.ndarray:
    """Fraction of each unit cell (centres ``coords`` × ``coords``) inside a disc."""
    d = np.hypot(coords[:, np.newaxis], coords[np.newaxis, :])
    cover = (d <= radius).astype(float)
    edge = np.abs(d - radius) < 0.75  # cells the circle can cross (half-diagonal 0.707)
    if radius > 0 and edge.any():
        iy, ix = np.nonzero(edge)
        sub = (np.arange(supersample) + 0.5) / supersample - 0.5
        yy = coords[iy][:, np.newaxis, np.newaxis] + sub[np.newaxis, :, np.newaxis]
        xx = coords[ix][:, np.newaxis, np.newaxis] + sub[np.newaxis, np.newaxis, :]
        cover[iy, ix] = (np.hypot(yy, xx) <= radius).mean(axis=(1, 2))
    return cover


def pupil_psf(q: float, *, phi: float = 10, size_px: int | None = None,
              obscuration: float = 0.0, pupil_radius_px: float = 64.0,
              supersample: int = 16) -> np.ndarray:
    """PSF built as the paper does: |DFT(circular pupil)|², normalised to sum 1.

    A circular pupil of radius R samples (anti-aliased: each pupil sample holds
    the fraction of its cell inside the circle) sits in a periodic pupil plane
    of N = 2 R Q φ samples, so that the pupil's autocorrelation, the OTF, cuts
    off at 2R/N = 1 / (Q φ) cycles per image pixel. The squared modulus of its
    discrete Fourier transform is the PSF sampled at image-pixel centres.

    Only the ``size_px`` × ``size_px`` PSF samples around the centre are needed,
    so the DFT is evaluated as a matrix Fourier transform (real cosine matrices,
    as the pupil is symmetric), which is mathematically identical to
    ``abs(fft2(zero-padded pupil))**2`` at those samples but costs
    O(size·R² + size²·R) instead of O(N² log N).

    Parameters
    ----------
    q
        Q = λ f / (D p) on the satellite detector pitch (dimensionless).
    phi
        Grid pixels per satellite pixel (dimensionless).
    size_px
        Odd kernel side in pixels; default: the side holding ≥ 99.5 % of the energy.
    obscuration
        Central obscuration as a ratio of diameters, in [0, 1).
    pupil_radius_px
        Minimum pupil radius in pupil samples; the discretisation error of the
        circle edge falls as R⁻² (about 2e-4 of the peak at R = 64).
    supersample
        Sub-samples per pupil sample side used to anti-alias the edge.

    Returns
    -------
    numpy.ndarray
        (size_px, size_px) float64 kernel, peak at the centre, sum 1.
    """
    _check(q, phi, obscuration)
    size = _size_or_default(size_px, q, phi, obscuration)
    if pupil_radius_px < 1:
        raise ValueError(f"pupil_radius_px must be ≥ 1, got {pupil_radius_px!r}")
    n_fft = max(math.ceil(2.0 * pupil_radius_px * q * phi), size)
    radius = n_fft / (2.0 * q * phi)  # pupil radius in samples: cutoff 2R/N = 1/(Qφ)
    half = math.ceil(radius) + 1
    u = np.arange(-half, half + 1, dtype=float)
    pupil = _disc_coverage(u, radius, supersample=supersample)
    if obscuration > 0:
        pupil -= _disc_coverage(u, obscuration * radius, supersample=supersample)
    h = size // 2
    r = np.arange(-h, h + 1, dtype=float)
    # The pupil is even in each axis, so the sine terms of its DFT cancel and the
    # amplitude is the real, separable sum  Σ_u Σ_v P(u, v) cos(2π u y / N) cos(2π v x / N).
    cos_mat = np.cos(2.0 * np.pi * np.outer(r, u) / n_fft)
    amp = cos_mat @ pupil @ cos_mat.T
    kernel = amp * amp
    return kernel / kernel.sum()
