"""Windowed sub-pixel phase correlation (translation only).

Conventions used by every function of :mod:`geosim.align`
---------------------------------------------------------
* Pixel coordinates: ``x`` is the column, ``y`` is the row (growing downward),
  pixel *centres* sit at integer coordinates, so the first pixel's centre is
  ``(0, 0)`` and an image of ``w`` columns spans ``x`` in ``[-0.5, w - 0.5]``.
* Shift sign: a shift ``(dx, dy)`` is the **position of the moving image's
  content relative to the reference**: the ground seen at reference pixel
  ``(x, y)`` is seen at moving pixel ``(x + dx, y + dy)``. Equivalently
  ``moving(x, y) = reference(x - dx, y - dy)``, and sampling ``moving`` at
  ``(x + dx, y + dy)`` (e.g. ``scipy.ndimage.shift(moving, (-dy, -dx))``)
  aligns it onto ``reference``. (This is the opposite sign of
  scikit-image's ``phase_cross_correlation``, which returns the shift to
  apply to ``moving``.)
* Images are 2-D ``(rows, cols)`` or bands-first ``(bands, rows, cols)``; a
  multi-band image is reduced to grey (BT.601 luma of the first three bands, or
  the mean of one or two bands). Valid masks are boolean, ``True`` = valid;
  non-finite pixels are treated as invalid too.

Method
------
Each image is reduced to grey, invalid pixels are replaced by the mean of the
valid ones, the valid area is feathered (raised-cosine taper over
``feather_px``) so that mask edges do not correlate, the result is apodised with
a Hann (or Tukey) window and its weighted mean removed. The cross-power
spectrum ``X = F_mov · conj(F_ref)`` is partially whitened (``X / |X|**0.5``,
see :data:`WHITENING_EXPONENT`; ``whitening=1`` gives classical phase correlation),
multiplied by a radial raised-cosine taper that reaches 0 at Nyquist
(:func:`spectral_taper`, which keeps noise, aliasing and interpolation phase
errors at the highest frequencies from biasing the sub-pixel position) and
transformed back into the correlation surface, whose maximum gives the integer
shift. The peak is refined by windowed-sinc interpolation of that band-limited
surface on a fine grid (1/8 px, then ``1/upsample_factor`` px), equivalent to
the upsampled matrix-multiply DFT of Guizar-Sicairos et al. (2008) to about
0.001 px; a final 3-point quadratic fit on the finest grid removes the residual
quantisation.

Confidence
----------
``confidence = clip(1 - max(z2, z_noise) / z1, 0, 1)``. The surface is first
divided by the expected noise envelope (for apodised windows the correlation of
unrelated content is noisier near zero shift, see :func:`noise_envelope`);
``z1`` is the normalised surface at the main peak and ``z2`` its highest value
outside a 6 px disc around it, both in robust (MAD) standard deviations above
the median; ``z_noise`` is the level that the largest of ``N`` Gaussian noise
samples exceeds with 1 % probability (about 5.3 for a 400×400 surface). It reads
as "the fraction of the peak that stands above the best alternative": 0 for
featureless or unrelated images, about 0.2–0.8 for real pairs across seasonal
change, 0.85–0.95 for the same scene imaged twice (synthetic). See
:data:`DEFAULT_MIN_CONFIDENCE`.

References
----------
Kuglin, C. D. & Hines, D. C. (1975). The phase correlation image alignment method.
Guizar-Sicairos, M., Thurman, S. T. & Fienup, J. R. (2008). Efficient subpixel
image registration algorithms. Optics Letters 33(2), 156-158.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft

from geosim.errors import AlignmentError, RasterError
from geosim.physics.radiometry import LUMA_WEIGHTS

__all__ = [
    "DEFAULT_MIN_CONFIDENCE",
    "PhaseCorrelation",
    "phase_correlate",
]

#: Default acceptance threshold on the confidences of this package (used by
#: :func:`geosim.align.register_similarity` and :func:`geosim.align.local_shift_field`).
#: Measured (``docs/alignment.md``): unrelated synthetic textures give 0.00,
#: unrelated real SJER tiles 0.00 (median; 1 of 198 above 0.1), matched 2017/2018
#: SJER tiles across seasonal change 0.1–0.86 (median 0.48), same scene 0.85–0.95.
DEFAULT_MIN_CONFIDENCE = 0.1

#: Exponent of the spectral whitening: 1 is pure phase correlation, 0 plain
#: cross-correlation. 0.5 keeps the sharp peak of phase correlation (sub-pixel
#: errors ≤ 0.05 px on synthetic shifts) while weighting frequencies that carry
#: energy in both images more, which measurably helps across seasonal change
#: (real SJER 2017/2018 pairs: median confidence 0.29 → 0.44).
WHITENING_EXPONENT = 0.5

#: Floor of the noise envelope (relative noise standard deviation) used to
#: normalise the surface; shifts where the apodised windows overlap so little
#: that the envelope is below it are not searched.
ENVELOPE_MIN = 0.1

#: Probability with which the largest of the surface's noise samples may exceed
#: the reference level ``z_noise`` of the confidence (Gaussian model).
FALSE_ALARM = 0.01

#: Half-width (taps) of the Lanczos kernel interpolating the correlation surface.
LANCZOS_A = 8

#: Smallest window side accepted, in pixels.
MIN_WINDOW_PX = 32

#: Pixels per strip of :func:`as_grey` (its float32 temporaries: 4 × this × 4 bytes).
GREY_STRIP_PX = 1 << 16

#: A valid-pixel standard deviation below this (in the image's grey units) counts as flat.
FLAT_STD = 1e-6


@dataclass(frozen=True)
class PhaseCorrelation:
    """Result of :func:`phase_correlate`.

    Attributes
    ----------
    shift_px : tuple of float
        ``(dx, dy)`` in pixels, ``dx`` along columns (x, to the right), ``dy``
        along rows (y, downward): the position of the moving content relative
        to the reference (reference pixel ``(x, y)`` shows the same ground as
        moving pixel ``(x + dx, y + dy)``). NaN when no peak could be found.
    confidence : float
        Peak distinctness in ``[0, 1]`` (see the module docstring); 0 means
        indistinguishable from the best alternative peak or from noise.
    peak : float
        Height of the sub-pixel correlation peak, at most 1 (exactly 1 for
        identical content circularly shifted; smaller with non-overlap,
        apodisation, change and noise).
    """

    shift_px: tuple[float, float]
    confidence: float
    peak: float


# --------------------------------------------------------------------------- helpers


def grey_pair(reference: np.ndarray, moving: np.ndarray, *, min_px: int, purpose: str
              ) -> tuple[np.ndarray, np.ndarray]:
    """Grey versions of a reference/moving pair, checked to be equal-shaped and large enough.

    Raises
    ------
    RasterError
        The two windows differ in shape.
    AlignmentError
        A side is shorter than ``min_px`` pixels (too small for ``purpose``).
    """
    ref = as_grey(reference, "reference")
    mov = as_grey(moving, "moving")
    if ref.shape != mov.shape:
        raise RasterError(f"reference {ref.shape} and moving {mov.shape} windows differ in "
                          "shape; cut windows of the same size from both")
    if min(ref.shape) < min_px:
        raise AlignmentError(f"window of {ref.shape[0]}×{ref.shape[1]} px is too small for "
                             f"{purpose} (need ≥ {min_px} px per side); use a larger window")
    return ref, mov


def as_grey(image: np.ndarray, what: str = "image") -> np.ndarray:
    """Return a float32 2-D grey image from a 2-D or bands-first 3-D array.

    Parameters
    ----------
    image : numpy.ndarray
        ``(rows, cols)`` or ``(bands, rows, cols)``; 3 or more bands are
        reduced with BT.601 luma of the first three (R, G, B), 1 or 2 bands
        with their mean.
    what : str
        Name used in error messages.

    Returns
    -------
    numpy.ndarray
        ``(rows, cols)`` float32, in the input's grey units.
    """
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.float32, copy=False)
    if img.ndim == 3:
        if img.shape[0] >= 3:
            wr, wg, wb = (np.float32(w) for w in LUMA_WEIGHTS)  # float32: half the memory
            out = np.empty(img.shape[1:], dtype=np.float32)
            # a strip of rows at a time: the float32 temporaries stay in the CPU cache
            # (the same arithmetic per pixel as on the whole image)
            step = max(1, GREY_STRIP_PX // max(1, img.shape[2]))
            for r0 in range(0, img.shape[1], step):
                s = img[:3, r0:r0 + step].astype(np.float32, copy=False)
                np.add(wr * s[0] + wg * s[1], wb * s[2], out=out[r0:r0 + step])
            return out
        return img.astype(np.float32, copy=False).mean(axis=0, dtype=np.float32)
    raise RasterError(f"{what}: expected a (rows, cols) or bands-first (bands, rows, cols) "
                      f"array, got shape {img.shape}; pass one band or a bands-first stack")


def _valid_mask(grey: np.ndarray, valid: np.ndarray | None, what: str) -> np.ndarray:
    finite = np.isfinite(grey)
    if valid is None:
        return finite
    v = np.asarray(valid)
    if v.shape != grey.shape:
        raise RasterError(f"valid mask of {what}: shape {v.shape} does not match the image "
                          f"shape {grey.shape}; pass a boolean (rows, cols) mask, True = valid")
    return finite & v.astype(bool, copy=False)


def window_2d(shape: tuple[int, int], window: str | None) -> np.ndarray:
    """Separable apodisation window of ``shape`` (rows, cols), float32, peak ≤ 1.

    ``"hann"`` (symmetric Hann sampled at pixel centres, near 0 at the borders),
    ``"tukey"`` (flat top, cosine tapers over 25 % of each side) or
    ``None``/``"none"``. The returned array is cached and read-only.
    """
    return _window_2d(tuple(int(v) for v in shape), window)


@functools.lru_cache(maxsize=32)
def _window_2d(shape: tuple[int, int], window: str | None) -> np.ndarray:
    if window is None or window == "none":
        out = np.ones(shape, dtype=np.float32)
        out.flags.writeable = False
        return out

    def one(n: int) -> np.ndarray:
        t = (np.arange(n) + 0.5) / n  # in (0, 1), symmetric
        if window == "hann":
            return 0.5 - 0.5 * np.cos(2.0 * np.pi * t)
        if window == "tukey":
            alpha = 0.5
            w = np.ones(n)
            edge = t < alpha / 2
            w[edge] = 0.5 - 0.5 * np.cos(2.0 * np.pi * t[edge] / alpha)
            edge = t > 1 - alpha / 2
            w[edge] = 0.5 - 0.5 * np.cos(2.0 * np.pi * (1 - t[edge]) / alpha)
            return w
        raise ValueError(f"window must be 'hann', 'tukey' or None, got {window!r}")

    out = np.outer(one(shape[0]), one(shape[1])).astype(np.float32)
    out.flags.writeable = False
    return out


def feather(valid: np.ndarray, feather_px: float) -> np.ndarray:
    """Raised-cosine taper from 0 at invalid pixels to 1 at ``feather_px`` inside the valid area."""
    if valid.all():
        return np.ones(valid.shape, dtype=np.float32)
    dist = cv2.distanceTransform(valid.astype(np.uint8), cv2.DIST_L2, 5)
    t = np.clip(dist / max(float(feather_px), 1.0), 0.0, 1.0)
    return (0.5 - 0.5 * np.cos(np.pi * t)).astype(np.float32)


def prepare(grey: np.ndarray, valid: np.ndarray, apod: np.ndarray, *,
            feather_px: float, what: str, min_valid_fraction: float = 0.05
            ) -> tuple[np.ndarray, np.ndarray]:
    """Mean-fill, feather, apodise and de-mean one grey image for correlation.

    Returns
    -------
    tuple of numpy.ndarray
        ``(image, weight)``: the weighted, zero-weighted-mean image and the
        weight (apodisation × feathered mask) that multiplies it, float32.

    Raises
    ------
    AlignmentError
        Too few valid pixels, or the valid pixels are flat.
    """
    n_valid = int(np.count_nonzero(valid))
    if n_valid < max(16, min_valid_fraction * valid.size):
        raise AlignmentError(f"{what}: only {n_valid} of {valid.size} pixels are valid "
                             f"(< {min_valid_fraction:.0%}); choose a window inside the valid "
                             "data of both images")
    vals = grey[valid]
    mean = float(vals.mean(dtype=np.float64))
    std = float(vals.std(dtype=np.float64))
    if not std > FLAT_STD * max(1.0, abs(mean)):
        raise AlignmentError(f"{what}: the valid pixels are flat (std {std:.3g}), there is no "
                             "texture to register; choose a textured window")
    weight = apod if valid.all() else apod * feather(valid, feather_px)
    img = np.where(valid, grey, np.float32(mean))
    wsum = float(weight.sum(dtype=np.float64))
    if wsum <= 0:
        raise AlignmentError(f"{what}: no valid pixel inside the apodisation window; choose a "
                             "window inside the valid data")
    m = float((img * weight).sum(dtype=np.float64)) / wsum
    return ((img - np.float32(m)) * weight).astype(np.float32, copy=False), weight


def spectral_taper(shape: tuple[int, int]) -> np.ndarray:
    """Radial raised-cosine weight ``cos²(π f)`` (f in cycles/px, 0 beyond 0.5), FFT layout.

    Applied to the whitened cross-power spectrum: it keeps the peak sharp but
    stops the highest frequencies — where noise, aliasing and interpolation
    phase errors live — from biasing the sub-pixel position. The array is cached
    (every window of a local shift field has the same shape) and read-only.
    """
    return _spectral_taper(tuple(int(v) for v in shape))


@functools.lru_cache(maxsize=8)
def _spectral_taper(shape: tuple[int, int]) -> np.ndarray:
    fy = sfft.fftfreq(shape[0]).astype(np.float32)[:, None]
    fx = sfft.fftfreq(shape[1]).astype(np.float32)[None, :]
    f = np.minimum(np.sqrt(fy * fy + fx * fx), np.float32(0.5))
    out = (np.cos(np.float32(np.pi) * f) ** 2).astype(np.float32)
    out.flags.writeable = False
    return out


def cross_power(prep_ref: np.ndarray, prep_mov: np.ndarray, *,
                whitening: float = WHITENING_EXPONENT,
                fft_ref: np.ndarray | None = None) -> np.ndarray:
    """Whitened, tapered cross-power spectrum (complex64, FFT layout).

    ``X = F_mov · conj(F_ref)``, divided by ``|X| ** whitening`` (default
    :data:`WHITENING_EXPONENT`; 1 is classical phase correlation), times
    :func:`spectral_taper`, then scaled so that its mean modulus is 1 (a perfect
    circular match then gives a surface peak of exactly 1). Its inverse FFT peaks
    at the position of the moving content relative to the reference. ``fft_ref``:
    ``scipy.fft.fft2(prep_ref)`` when already computed (a reference window correlated
    with several images).
    """
    if not 0.0 <= whitening <= 1.0:
        raise ValueError(f"whitening must be in [0, 1], got {whitening}")
    fr = sfft.fft2(prep_ref) if fft_ref is None else fft_ref
    fm = sfft.fft2(prep_mov)
    r = fm * np.conj(fr)
    mag = np.abs(r)
    floor = np.float32(1e-12) * (float(mag.max()) if mag.size else 1.0)
    den = np.maximum(mag, floor)
    # x ** 0.5 as sqrt: the same float32 values (checked for every positive finite float32
    # on numpy 2.4 / glibc), 4× faster
    r = r / (np.sqrt(den) if whitening == 0.5 else den ** np.float32(whitening))
    r *= spectral_taper(r.shape)
    norm = float(np.abs(r).mean(dtype=np.float64))
    if norm > 0:
        r /= np.float32(norm)
    return r.astype(np.complex64, copy=False)


def noise_envelope(weight_ref: np.ndarray, weight_mov: np.ndarray) -> np.ndarray:
    """Relative standard deviation of the correlation noise at each (circular) shift.

    For unrelated content the phase-correlation surface of weighted images has a
    variance roughly proportional to the cross-correlation of the squared
    weights, so noise peaks crowd near zero shift. Returns ``sqrt(E(s) / max E)``
    in the FFT layout of the surface (1 at full overlap, falling with the shift).
    """
    if weight_ref is weight_mov and not weight_ref.flags.writeable:
        return _self_envelope(weight_ref)
    return _envelope(weight_ref, weight_mov)


_SELF_ENVELOPES: dict[int, tuple[np.ndarray, np.ndarray]] = {}


def _self_envelope(weight: np.ndarray) -> np.ndarray:
    """Cached envelope of a (read-only, cached) apodisation window with itself."""
    hit = _SELF_ENVELOPES.get(id(weight))
    if hit is None or hit[0] is not weight:
        if len(_SELF_ENVELOPES) > 32:
            _SELF_ENVELOPES.clear()
        env = _envelope(weight, weight)
        env.flags.writeable = False
        hit = (weight, env)
        _SELF_ENVELOPES[id(weight)] = hit
    return hit[1]


def _envelope(weight_ref: np.ndarray, weight_mov: np.ndarray) -> np.ndarray:
    e = sfft.ifft2(sfft.fft2(weight_mov * weight_mov)
                   * np.conj(sfft.fft2(weight_ref * weight_ref))).real
    e_max = float(e.max())
    if not e_max > 0:
        return np.ones(e.shape, dtype=np.float32)
    return np.sqrt(np.clip(e / e_max, 1e-4, 1.0)).astype(np.float32)


def wrap_shift(pos: float, n: int) -> float:
    """Map a circular peak position in ``[0, n)`` to a signed shift in ``[-n/2, n/2)``."""
    return ((pos + n / 2.0) % n) - n / 2.0


def _lanczos(t: np.ndarray, a: int) -> np.ndarray:
    return np.where(np.abs(t) < a, np.sinc(t) * np.sinc(t / a), 0.0)


def refine_peak(surface: np.ndarray, y0: int, x0: int, upsample_factor: int
                ) -> tuple[float, float, float]:
    """Sub-pixel maximum of a circular correlation surface near its integer peak.

    The surface is interpolated with a separable windowed sinc (Lanczos,
    ``a = LANCZOS_A``) from a ``(2a + 5)²`` neighbourhood, first on a 1/8 px
    grid over ±1 px, then on a ``1/upsample_factor`` px grid over ±3/16 px,
    and a 3-point quadratic fit on the finest grid removes the last
    quantisation. Because the cross-power spectrum is tapered to zero at
    Nyquist (:func:`spectral_taper`) the surface is band-limited and this agrees
    with exact upsampled-DFT evaluation (Guizar-Sicairos et al. 2008) to about
    0.001 px, at a cost independent of the image size.

    Parameters
    ----------
    surface : numpy.ndarray
        Real 2-D surface, circular (FFT layout).
    y0, x0 : int
        Integer peak position (row, col).
    upsample_factor : int
        Finest grid step is ``1 / upsample_factor`` px.

    Returns
    -------
    tuple of float
        ``(y, x, height)``: peak position in pixels (near ``(y0, x0)``, not
        wrapped) and the interpolated peak height.
    """
    n_r, n_c = surface.shape
    a = LANCZOS_A
    taps = np.arange(-(a + 2), a + 3)
    patch = surface[np.ix_((int(y0) + taps) % n_r, (int(x0) + taps) % n_c)].astype(np.float64)
    y = x = 0.0
    steps = [1.0 / 8.0]
    if upsample_factor > 8:
        steps.append(1.0 / float(upsample_factor))
    half_range = 1.0
    for step in steps:
        n_half = int(math.ceil(half_range / step))
        offs = np.arange(-n_half, n_half + 1) * step
        ky = _lanczos((y + offs)[:, None] - taps[None, :], a)
        kx = _lanczos((x + offs)[:, None] - taps[None, :], a)
        surf = np.einsum("ij,jk,lk->il", ky, patch, kx, optimize=False)
        iy, ix = np.unravel_index(int(np.argmax(surf)), surf.shape)
        y, x = y + offs[iy], x + offs[ix]
        half_range = 1.5 * step
    height = float(surf[iy, ix])
    if 0 < iy < surf.shape[0] - 1 and 0 < ix < surf.shape[1] - 1:
        step = steps[-1]
        lo, mid, hi = surf[iy - 1, ix], surf[iy, ix], surf[iy + 1, ix]
        den = lo - 2 * mid + hi
        if den < 0:
            y += float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) * step
        lo, hi = surf[iy, ix - 1], surf[iy, ix + 1]
        den = lo - 2 * mid + hi
        if den < 0:
            x += float(np.clip(0.5 * (lo - hi) / den, -0.5, 0.5)) * step
    return float(y0) + y, float(x0) + x, height


def noise_level_z(n_samples: int, false_alarm: float | None = None) -> float:
    """Height (in noise standard deviations) that the maximum of ``n_samples``
    independent Gaussian samples exceeds with probability ``false_alarm``."""
    if false_alarm is None:
        false_alarm = FALSE_ALARM
    p = min(0.5, false_alarm / max(int(n_samples), 1))
    # inverse survival function of the standard normal
    from scipy.special import ndtri
    return float(-ndtri(p))


def peak_confidence(z_surface: np.ndarray, iy: int, ix: int, exclusion_px: float = 6.0,
                    usable: np.ndarray | None = None) -> float:
    """Confidence in ``[0, 1]`` of the peak at ``(iy, ix)`` of a noise-normalised surface.

    ``1 - max(z2, z_noise) / z1``: ``z1`` is the surface at the peak, ``z2`` its
    maximum outside a disc of ``exclusion_px`` around the peak (circular
    layout) within ``usable``, ``z_noise`` the level pure noise exceeds with 1 %
    probability (:func:`noise_level_z`); heights are in robust (MAD) standard
    deviations above the median of the usable surface outside the disc.
    """
    n_r, n_c = z_surface.shape
    ar, ac = np.arange(n_r), np.arange(n_c)
    dy = np.minimum(np.abs(ar - iy), n_r - np.abs(ar - iy))
    dx = np.minimum(np.abs(ac - ix), n_c - np.abs(ac - ix))
    far = (dy[:, None] ** 2 + dx[None, :] ** 2) > exclusion_px ** 2
    if usable is not None:
        far &= usable
    rest = z_surface[far]
    if rest.size < 16:
        return 0.0
    sample = rest[:: max(1, rest.size // 20000)]  # robust statistics on ≤ ~20k samples
    med = float(np.median(sample))
    sigma = 1.4826 * float(np.median(np.abs(sample - med)))
    if not sigma > 0:
        sigma = float(rest.std())
        if not sigma > 0:
            return 0.0
    z1 = (float(z_surface[iy, ix]) - med) / sigma
    z2 = (float(rest.max()) - med) / sigma
    if not z1 > 0:
        return 0.0
    n_eff = int(np.count_nonzero(usable)) if usable is not None else z_surface.size
    return float(np.clip(1.0 - max(z2, noise_level_z(n_eff)) / z1, 0.0, 1.0))


def top_peaks(surface: np.ndarray, k: int, *, allowed: np.ndarray | None = None,
              exclusion_px: float = 6.0) -> list[tuple[int, int]]:
    """Integer positions ``(row, col)`` of the ``k`` highest maxima of a circular surface.

    Greedy non-maximum suppression: each maximum removes a disc of
    ``exclusion_px`` (circular layout) before the next is taken; ``allowed``
    restricts the search to a boolean mask.
    """
    work = surface.astype(np.float64, copy=True)
    if allowed is not None:
        work[~allowed] = -np.inf
    n_r, n_c = work.shape
    ar, ac = np.arange(n_r), np.arange(n_c)
    out: list[tuple[int, int]] = []
    for _ in range(max(1, k)):
        iy, ix = np.unravel_index(int(np.argmax(work)), work.shape)
        if not np.isfinite(work[iy, ix]):
            break
        out.append((int(iy), int(ix)))
        dy = np.minimum(np.abs(ar - iy), n_r - np.abs(ar - iy))
        dx = np.minimum(np.abs(ac - ix), n_c - np.abs(ac - ix))
        work[(dy[:, None] ** 2 + dx[None, :] ** 2) <= exclusion_px ** 2] = -np.inf
    return out


def correlate_prepared(prep_ref: np.ndarray, prep_mov: np.ndarray, weight_ref: np.ndarray,
                       weight_mov: np.ndarray, *, upsample_factor: int,
                       allowed: np.ndarray | None = None, exclusion_px: float = 6.0,
                       whitening: float = WHITENING_EXPONENT,
                       fft_ref: np.ndarray | None = None) -> PhaseCorrelation:
    """Phase-correlate two images prepared by :func:`prepare` (with their weights).

    ``allowed`` optionally restricts the peak search to a boolean mask of the
    surface (FFT layout: index ``(i, j)`` is shift ``(dx, dy) = (j, i)`` modulo the shape);
    ``whitening`` and ``fft_ref`` are those of :func:`cross_power`.
    """
    r = cross_power(prep_ref, prep_mov, whitening=whitening, fft_ref=fft_ref)
    surface = sfft.ifft2(r).real
    env = noise_envelope(weight_ref, weight_mov)
    usable = env >= ENVELOPE_MIN
    z_surface = surface / np.maximum(env, ENVELOPE_MIN)
    search = usable if allowed is None else usable & allowed
    if not search.any():
        search = allowed if allowed is not None else np.ones(surface.shape, dtype=bool)
    iy, ix = np.unravel_index(int(np.argmax(np.where(search, surface, -np.inf))), surface.shape)
    if upsample_factor > 1:
        y, x, height = refine_peak(surface, int(iy), int(ix), upsample_factor)
    else:
        y, x, height = float(iy), float(ix), float(surface[iy, ix])
    conf = peak_confidence(z_surface, int(iy), int(ix), exclusion_px, usable)
    n_r, n_c = surface.shape
    return PhaseCorrelation(shift_px=(float(wrap_shift(x, n_c)), float(wrap_shift(y, n_r))),
                            confidence=float(conf), peak=float(np.clip(height, -1.0, 1.0)))


# --------------------------------------------------------------------------- public API


def phase_correlate(reference: np.ndarray, moving: np.ndarray, *,
                    valid_reference: np.ndarray | None = None,
                    valid_moving: np.ndarray | None = None,
                    window: str | None = "hann",
                    upsample_factor: int = 100,
                    feather_px: float | None = None,
                    max_shift_px: float | None = None,
                    whitening: float = WHITENING_EXPONENT) -> PhaseCorrelation:
    """Sub-pixel translation between two images by windowed phase correlation.

    Parameters
    ----------
    reference, moving : numpy.ndarray
        Images of the same shape, ``(rows, cols)`` or bands-first
        ``(bands, rows, cols)`` (reduced to grey, see :func:`as_grey`), any
        numeric dtype; at least 32×32 pixels.
    valid_reference, valid_moving : numpy.ndarray of bool, optional
        ``(rows, cols)`` masks, ``True`` = valid (default: all finite pixels).
        Invalid pixels are set to the valid mean and feathered out.
    window : {"hann", "tukey", None}
        Apodisation window against edge effects (default Hann).
    upsample_factor : int
        Sub-pixel resolution is ``1 / upsample_factor`` pixel before the final
        quadratic fit (default 100, i.e. 0.01 px).
    feather_px : float, optional
        Width in pixels of the taper at mask edges (default ``min(rows, cols) / 16``,
        at least 4).
    max_shift_px : float, optional
        Search the peak only among shifts with ``|dx|, |dy| <= max_shift_px`` (default:
        everywhere the windows overlap enough). The search is clipped, not
        re-centred: when the true shift lies outside, the maximum found is on the
        border of the square and is not a peak.
    whitening : float
        Exponent ``p`` in ``[0, 1]`` of the spectral whitening ``X / |X|**p`` (default
        :data:`WHITENING_EXPONENT` = 0.5). ``1`` is classical phase correlation: every
        frequency counts the same, so broad low-frequency differences between the
        images (illumination gradients, exposure seams, haze, changed fields) cannot
        raise a smooth ramp on the surface. Use 1 when the two images are different
        renderings of the scene (simulation against a real satellite scene:
        :func:`geosim.diagnose.coregister.integer_shift`); with 0.5 such a ramp
        outweighed the true peak on the sample site and a search clipped to ±8 px
        returned its border (−7, −8) px instead of the true (1.6, 2.5) px.

    Returns
    -------
    PhaseCorrelation
        ``shift_px = (dx, dy)`` in pixels: the position of the moving content
        relative to the reference (reference pixel ``(x, y)`` ~ moving pixel
        ``(x + dx, y + dy)``; ``moving(x, y) = reference(x - dx, y - dy)``),
        wrapped to ``[-cols/2, cols/2) × [-rows/2, rows/2)``; ``confidence`` in
        ``[0, 1]``; ``peak`` height.

    Raises
    ------
    RasterError
        Shapes differ or are not 2-D / bands-first 3-D.
    AlignmentError
        An image is smaller than 32×32 px, has fewer than 5 % valid pixels,
        or is flat (no texture). Low confidence is *returned*, not raised.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> ref = rng.normal(size=(128, 128))
    >>> mov = np.roll(ref, (2, -3), axis=(0, 1))     # content moved 3 px left, 2 px down
    >>> pc = phase_correlate(ref, mov)
    >>> [round(v, 2) for v in pc.shift_px]
    [-3.0, 2.0]
    """
    ref, mov = grey_pair(reference, moving, min_px=MIN_WINDOW_PX, purpose="phase correlation")
    if upsample_factor < 1:
        raise ValueError(f"upsample_factor must be ≥ 1, got {upsample_factor}")
    vr = _valid_mask(ref, valid_reference, "reference")
    vm = _valid_mask(mov, valid_moving, "moving")
    f_px = feather_px if feather_px is not None else max(4.0, min(ref.shape) / 16.0)
    apod = window_2d(ref.shape, window)
    pr, wr = prepare(ref, vr, apod, feather_px=f_px, what="reference image")
    pm, wm = prepare(mov, vm, apod, feather_px=f_px, what="moving image")
    allowed = None
    if max_shift_px is not None:
        rows, cols = ref.shape
        dy = np.abs(sfft.fftfreq(rows, 1.0 / rows))[:, None]
        dx = np.abs(sfft.fftfreq(cols, 1.0 / cols))[None, :]
        allowed = (dy <= max_shift_px) & (dx <= max_shift_px)
    return correlate_prepared(pr, pm, wr, wm, upsample_factor=int(upsample_factor),
                              allowed=allowed, whitening=float(whitening))
