"""The paper's degradation, I_sat = (I_uav ⊛ PSF(Q)) ↓φ, as pure array kernels.

Model
-----
Each band is convolved with the circular-aperture PSF of the given Q (cutoff
1 / (Q φ) cycles per UAV pixel), then downsampled by the whole factor φ with
OpenCV's bicubic ``cv2.resize(..., INTER_CUBIC)``, as in the paper.

Boundary. The convolution uses the half-sample symmetric extension of the image
(``…c b a | a b c … | … c b a``, OpenCV's ``BORDER_REFLECT``), and the full,
untruncated PSF: it is computed exactly in the DCT-II domain, which is the FFT of
the symmetric extension. Multiplying the DCT-II coefficient (k, l) by the optics
OTF at (k / 2N, l / 2M) cycles per pixel
(:func:`geosim.physics.otf.optics_otf`) is the convolution with the Airy PSF
(its periodisation over the 2N × 2M symmetric extension), so nothing is wrapped
across edges, no kernel is truncated and the mean is conserved exactly.

Two methods compute the same numbers:

``"reference"``
    Literally the paper: the full-resolution blurred image (inverse DCT), then
    ``cv2.resize`` with ``INTER_CUBIC``.
``"fast"``
    Since the OTF is exactly zero above 1 / (Q φ) cycles per pixel, only the
    lowest ⌈2N/(Qφ)⌉ DCT coefficients per axis are non-zero, and since
    ``INTER_CUBIC`` downsampling by a whole factor reads only a 4 × 4
    neighbourhood of the blurred image per output pixel, the output is
    ``A_rows @ (C · H) @ A_cols.T`` where ``C`` are the kept coefficients, ``H``
    the OTF and ``A`` the inverse-DCT basis at the 4 source rows (columns) of
    each output pixel, weighted by OpenCV's cubic coefficients. The kept
    coefficients come from a band-limited half-resolution pyramid
    (:func:`reduce_band_limited`: binomial filter + 2 × 2 decimation, whose effect
    on every kept coefficient is a known gain, divided out; the aliases it folds
    in weigh ≤ :data:`ALIAS_TOLERANCE`), so the transform runs on a 4× or 16×
    smaller image; sizes the pyramid cannot halve use row-blocked full-length
    DCTs. Agrees with the reference to ~3e-5 DN before rounding.

No-data. Invalid UAV pixels are first filled with a smooth continuation of the
valid ones (:func:`fill_invalid`, a pull–push pyramid), then the filled image is
degraded as a whole; a 0.5 m pixel is valid only when all φ × φ UAV pixels under
it are. Filling keeps the PSF's full weight on valid data, so neither a fill
colour bleeds in (as with a constant fill) nor is local contrast inflated (as
with normalised convolution, D(I·V)/D(V), whose renormalisation by the slowly
decaying Airy wings raised the calibrated Q of a 30 m flight inside a larger
satellite scene by +1 % in development; with the fill and the calibration's guard
band it is within ±0.05 %, ``tests/test_calibrate.py``). Valid pixels within about
one PSF radius of no-data see a smooth fill instead of the true ground beyond,
which the calibration excludes with a guard band.

Output size. ``rows // φ`` × ``cols // φ``: trailing rows/columns that do not
fill a whole satellite pixel are dropped (the output keeps the input's origin,
its pixels are φ times larger).
"""

from __future__ import annotations

import functools
from typing import Literal

import cv2
import numpy as np
import scipy.fft

from geosim.physics.otf import optics_otf
from geosim.physics.pyramid import (
    halve_binomial4_uint8,
    halve_binomial6,
    level_gain,
    row_strips,
)
from geosim.scratch import scratch_array

Method = Literal["fast", "reference"]
METHODS: tuple[str, ...] = ("fast", "reference")

#: OpenCV's bicubic coefficient (Keys' a), used by cv2.resize INTER_CUBIC.
CV2_CUBIC_A = -0.75

_ROW_BLOCK = 2048   # rows per forward-DCT call: long calls use every FFT worker


# ----------------------------------------------------------------------- validation

def _check_q(q: float) -> float:
    try:
        qf = float(q)
    except (TypeError, ValueError):
        raise ValueError(f"q must be a positive number, got {q!r}") from None
    if not (np.isfinite(qf) and qf > 0):
        raise ValueError(f"q must be a positive number, got {q!r}")
    return qf


def _check_phi(phi: int | float) -> int:
    if isinstance(phi, bool) or not isinstance(phi, (int, float, np.integer, np.floating)):
        raise ValueError(f"phi must be a whole number ≥ 1, got {phi!r}")
    if not np.isfinite(phi) or phi < 1 or int(phi) != phi:
        raise ValueError(f"phi must be a whole number ≥ 1 (satellite GSD / UAV GSD), "
                         f"got {phi!r}")
    return int(phi)


def _check_obscuration(obscuration: float) -> float:
    if not 0.0 <= float(obscuration) < 1.0:
        raise ValueError(f"obscuration must be a diameter ratio in [0, 1), got {obscuration!r}")
    return float(obscuration)


def _as_stack(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 2:
        arr = arr[np.newaxis]
    if arr.ndim != 3:
        raise ValueError(f"image must be (rows, cols) or bands-first (bands, rows, cols), "
                         f"got shape {np.shape(image)}")
    if arr.shape[0] < 1:
        raise ValueError("image has no bands")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"image must hold integer or float values, got dtype {arr.dtype}")
    return arr


def _check_valid(valid: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    if valid is None:
        return None
    v = np.asarray(valid)
    if v.shape != shape:
        raise ValueError(f"valid mask shape {v.shape} does not match the image's "
                         f"(rows, cols) = {shape}")
    v = v.astype(bool, copy=False)
    return None if v.all() else v


def _output_shape(shape: tuple[int, int], phi: int) -> tuple[int, int]:
    rows, cols = shape
    if rows < phi or cols < phi:
        raise ValueError(f"image of {rows} × {cols} px is smaller than one satellite pixel "
                         f"(phi = {phi} px); nothing to degrade")
    return rows // phi, cols // phi


# ----------------------------------------------------------------------- small helpers

def block_all(valid: np.ndarray, phi: int) -> np.ndarray:
    """A coarse pixel is True only when all ``phi`` × ``phi`` fine pixels under it are.

    Trailing rows/columns that do not fill a coarse pixel are ignored.
    """
    phi = _check_phi(phi)
    v = np.asarray(valid, dtype=bool)
    rows, cols = v.shape[0] // phi, v.shape[1] // phi
    return v[:rows * phi, :cols * phi].reshape(rows, phi, cols, phi).all(axis=(1, 3))


def to_dtype(arr: np.ndarray, dtype: np.dtype | type | str) -> np.ndarray:
    """Round half to even and clip to the range of an integer ``dtype``; cast floats.

    Parameters
    ----------
    arr
        Values in digital numbers (DN).
    dtype
        Target dtype (e.g. the input tile's ``uint8``).
    """
    dt = np.dtype(dtype)
    a = np.asarray(arr)
    if np.issubdtype(dt, np.integer):
        info = np.iinfo(dt)
        return np.clip(np.rint(a), info.min, info.max).astype(dt)
    if np.issubdtype(dt, np.floating):
        return a.astype(dt)
    raise ValueError(f"cannot convert to dtype {dt}")


def cv2_cubic_taps(src_len: int, dst_len: int) -> tuple[np.ndarray, np.ndarray]:
    """Source indices and weights OpenCV's ``INTER_CUBIC`` resize uses along one axis.

    For output sample ``d`` the source coordinate is ``(d + 0.5) · s − 0.5`` with
    ``s = src_len / dst_len``; the four taps around it get Keys' cubic
    coefficients with a = −0.75, and indices beyond the image are clamped
    (OpenCV replicates the border in ``resize``).

    Returns
    -------
    tuple of numpy.ndarray
        ``(index, weight)``, both (dst_len, 4); ``index`` int64, ``weight`` float64.
    """
    scale = src_len / dst_len
    pos = (np.arange(dst_len, dtype=np.float64) + 0.5) * scale - 0.5
    pos = pos.astype(np.float32).astype(np.float64)  # OpenCV computes fx in single precision
    base = np.floor(pos)
    t = pos - base
    a = CV2_CUBIC_A
    w0 = ((a * (t + 1) - 5 * a) * (t + 1) + 8 * a) * (t + 1) - 4 * a
    w1 = ((a + 2) * t - (a + 3)) * t * t + 1
    w2 = ((a + 2) * (1 - t) - (a + 3)) * (1 - t) * (1 - t) + 1
    w3 = 1.0 - w0 - w1 - w2
    index = base.astype(np.int64)[:, np.newaxis] + np.arange(-1, 3)[np.newaxis, :]
    return np.clip(index, 0, src_len - 1), np.stack([w0, w1, w2, w3], axis=1)


def _dct_basis(n: int, index: np.ndarray, n_coef: int) -> np.ndarray:
    """Orthonormal inverse DCT-II basis: value of coefficient k at sample ``index``."""
    k = np.arange(n_coef, dtype=np.float64)
    basis = np.sqrt(2.0 / n) * np.cos(np.pi * np.outer(2.0 * index + 1.0, k) / (2.0 * n))
    basis[:, 0] *= np.sqrt(0.5)
    return basis


@functools.lru_cache(maxsize=8)
def _resample_basis(n: int, n_out: int, n_coef: int, phi: int) -> np.ndarray:
    """(n_out, n_coef) matrix: inverse DCT at the cubic taps of each output sample, weighted.

    The blurred axis has ``n`` samples; the resize reads its first ``n_out · phi``
    (as the reference crops before ``cv2.resize``), so the scale is exactly ``phi``.
    Cached (read-only): the tiles of a run share their size.
    """
    index, weight = cv2_cubic_taps(n_out * phi, n_out)
    out = np.zeros((n_out, n_coef))
    for j in range(4):
        out += weight[:, j:j + 1] * _dct_basis(n, index[:, j], n_coef)
    out.flags.writeable = False
    return out


def n_coefficients(n: int, *, q: float, phi: int) -> int:
    """DCT-II coefficients (per axis of length ``n``) below the optics cutoff 1/(Qφ).

    Coefficient k has frequency k / (2n) cycles per pixel; the OTF is exactly
    zero from the cutoff on, so coefficients k ≥ 2n / (Qφ) are not needed.
    """
    return int(min(n, np.floor(2.0 * n / (q * phi)) + 1))


def optics_otf_dct(shape: tuple[int, int], *, q: float, phi: int, obscuration: float = 0.0,
                   n_coef: tuple[int, int] | None = None) -> np.ndarray:
    """The optics OTF at the DCT-II frequencies (k / 2N, l / 2M) of an N × M image.

    Parameters
    ----------
    shape
        (rows, cols) = (N, M) of the full-resolution image, pixels.
    n_coef
        Only the first (K_rows, K_cols) coefficients (default: all).
    """
    rows, cols = shape
    k_r, k_c = n_coef if n_coef is not None else shape
    fy = (np.arange(k_r) / (2.0 * rows))[:, np.newaxis]
    fx = (np.arange(k_c) / (2.0 * cols))[np.newaxis, :]
    return optics_otf(fy, fx, q=q, phi=phi, obscuration=obscuration)


def optics_otf_below_cutoff(shape: tuple[int, int], *, q: float, phi: int,
                            obscuration: float = 0.0,
                            max_coef: tuple[int, int] | None = None) -> np.ndarray:
    """:func:`optics_otf_dct` over only the DCT-II coefficients below the optics' cut-off
    (:func:`n_coefficients` per axis, at most ``max_coef``): its shape (K_rows, K_cols) is
    how many coefficients a filtered image keeps."""
    k_r = n_coefficients(shape[0], q=q, phi=phi)
    k_c = n_coefficients(shape[1], q=q, phi=phi)
    if max_coef is not None:
        k_r, k_c = min(k_r, max_coef[0]), min(k_c, max_coef[1])
    return optics_otf_dct(shape, q=q, phi=phi, obscuration=obscuration, n_coef=(k_r, k_c))


# ----------------------------------------------------------------------- blur

def blur(image: np.ndarray, *, q: float, phi: int = 10, obscuration: float = 0.0,
         workers: int | None = None) -> np.ndarray:
    """Convolve each band with the full Airy PSF of ``q`` (symmetric boundary, exact).

    Parameters
    ----------
    image
        (rows, cols) or bands-first (bands, rows, cols), DN.
    q
        Q = λ f / (D p) on the satellite detector pitch (dimensionless).
    phi
        UAV pixels per satellite pixel (dimensionless whole number).
    obscuration
        Central obscuration, diameter ratio in [0, 1).

    Returns
    -------
    numpy.ndarray
        Float64 blurred image, same shape; its mean equals the input's exactly
        (up to rounding error).
    """
    arr = np.asarray(image)
    stack = _as_stack(arr)
    transfer = _checked_otf_dct(stack.shape[1:], q, phi, obscuration)
    out = np.empty(stack.shape)
    for i, band in enumerate(stack):  # one band's coefficients at a time (memory)
        out[i] = _idct_filtered(_dct_band(band, workers), transfer, workers)
    return out[0] if arr.ndim == 2 else out


def dct_coefficients(image: np.ndarray, *, workers: int | None = None) -> np.ndarray:
    """Orthonormal DCT-II of each band (float64, bands first): what :func:`blur` filters,
    kept by callers that blur one image at many Q (:func:`blur_coefficients`)."""
    stack = _as_stack(np.asarray(image))
    out = np.empty(stack.shape)
    for i, band in enumerate(stack):
        out[i] = _dct_band(band, workers)
    return out


def blur_coefficients(coefficients: np.ndarray, *, q: float, phi: int = 10,
                      obscuration: float = 0.0, workers: int | None = None) -> np.ndarray:
    """:func:`blur` of the image whose :func:`dct_coefficients` are ``coefficients``
    (bands, rows, cols); the same values. Float64, bands first, DN."""
    transfer = _checked_otf_dct(coefficients.shape[1:], q, phi, obscuration)
    out = np.empty(coefficients.shape)
    for i, coef in enumerate(coefficients):
        out[i] = _idct_filtered(coef, transfer, workers)
    return out


def _checked_otf_dct(shape: tuple[int, ...], q: float, phi: int, obscuration: float
                     ) -> np.ndarray:
    """:func:`optics_otf_dct` of the full ``shape`` after the arguments' checks."""
    return optics_otf_dct((int(shape[0]), int(shape[1])), q=_check_q(q), phi=_check_phi(phi),
                          obscuration=_check_obscuration(obscuration))


def _dct_band(band: np.ndarray, workers: int | None) -> np.ndarray:
    return scipy.fft.dctn(band.astype(np.float64), type=2, norm="ortho", workers=workers,
                          overwrite_x=True)


def _idct_filtered(coef: np.ndarray, transfer: np.ndarray, workers: int | None) -> np.ndarray:
    # a new array (``coef`` may be kept by the caller), transformed in place
    return scipy.fft.idctn(coef * transfer, type=2, norm="ortho", workers=workers,
                           overwrite_x=True)


def _resize_cubic(band: np.ndarray, out_shape: tuple[int, int], phi: int) -> np.ndarray:
    rows, cols = out_shape
    src = np.ascontiguousarray(band[:rows * phi, :cols * phi])
    return cv2.resize(src, (cols, rows), interpolation=cv2.INTER_CUBIC)


def _degrade_reference(stack: np.ndarray, *, q: float, phi: int,
                       obscuration: float) -> np.ndarray:
    out_shape = _output_shape(stack.shape[1:], phi)
    out = np.empty((stack.shape[0], *out_shape))
    for i, band in enumerate(stack):
        out[i] = _resize_cubic(blur(band, q=q, phi=phi, obscuration=obscuration), out_shape, phi)
    return out


def fill_invalid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid pixels with a smooth continuation of the valid ones (pull–push).

    A mask-weighted image pyramid is built by 2 × 2 area averaging (pull); from
    the coarsest level down, each pixel without valid data takes the bilinear
    upsampling of the level above (push). Valid pixels keep their values.
    (Gortler et al. 1996, "The Lumigraph", §3.3.) See :class:`InvalidFill`, which
    this calls, for how it is computed.

    Parameters
    ----------
    image
        (rows, cols) or bands-first (bands, rows, cols), DN.
    valid
        (rows, cols) bool, True = valid; at least one pixel must be valid.

    Returns
    -------
    numpy.ndarray
        Float32 image, same shape, with invalid pixels filled.
    """
    arr = np.asarray(image)
    stack = _as_stack(arr)
    filler = InvalidFill(valid, stack.shape[1:])
    out = np.empty(stack.shape, np.float32)
    for i, band in enumerate(stack):
        filler.fill(band, out=out[i])
    return out[0] if arr.ndim == 2 else out


class InvalidFill:
    """The pull–push fill of :func:`fill_invalid` for one mask, applied band by band.

    The same numbers as the plain pyramid of float32 levels ``(a_k, w_k)``, with
    ``a_0 = band · valid``, ``w_0 = valid`` and each level the ``INTER_AREA`` halving of
    the one below, pushed down with ``has = w > 1e-6``, ``mean = a / w`` and
    ``estimate = where(has, mean, INTER_LINEAR(estimate above))``, but for less memory
    traffic (a 5000² RGB tile with an invalid edge: ≈ 1.2 s → see docs/degradation.md):

    * the weight pyramid is the same for every band: computed once;
    * at full resolution the estimate is needed only where the mask is invalid (the
      valid pixels keep the band), so the full-resolution mean is never formed:
      the output is the upsampled level 1 with the band copied over its valid pixels;
    * for a uint8 band of even size, level 1 is computed in integers: the 2 × 2 block
      sums of ``4 · band · valid`` (uint16) and of ``4 · valid`` (uint8) through
      ``INTER_AREA``, which rounds (4 s + 2) >> 2 = s, the block sum, exactly; divided
      by 4 these are exactly the float32 block means (quarter integers ≤ 255), so no
      full-size float32 copy of the band is made.
    """

    def __init__(self, valid: np.ndarray, shape: tuple[int, int]) -> None:
        v = np.asarray(valid, dtype=bool)
        if v.shape != tuple(shape):
            raise ValueError(f"valid mask shape {v.shape} does not match the image's "
                             f"{tuple(shape)}")
        if not v.any():
            raise ValueError("no valid pixel to fill from")
        self.valid = v
        rows, cols = v.shape
        #: Level 1 in integers (uint8 bands only): both sides even.
        self.even = rows % 2 == 0 and cols % 2 == 0 and max(rows, cols) > 1
        weight0 = v.astype(np.float32)
        if self.even:
            self._mask4 = v.view(np.uint8) * np.uint8(4)
            counts = cv2.resize(self._mask4, self._size(v.shape), interpolation=cv2.INTER_AREA)
            weight1 = counts.astype(np.float32) * np.float32(0.25)
        else:
            weight1 = self._halve(weight0)
        self._weight0 = None if self.even else weight0
        self.weights = [weight1]  # levels 1, 2, ...
        while max(self.weights[-1].shape) > 1:
            self.weights.append(self._halve(self.weights[-1]))
        self._has = [w > 1e-6 for w in self.weights]

    @staticmethod
    def _size(shape: tuple[int, ...]) -> tuple[int, int]:
        return max(1, (shape[1] + 1) // 2), max(1, (shape[0] + 1) // 2)

    @classmethod
    def _halve(cls, level: np.ndarray) -> np.ndarray:
        return cv2.resize(level, cls._size(level.shape), interpolation=cv2.INTER_AREA)

    def _level1(self, band: np.ndarray) -> np.ndarray:
        """``INTER_AREA`` halving of ``band · valid`` (float32)."""
        if self.even and band.dtype == np.uint8:
            rows, cols = band.shape
            out = np.empty((rows // 2, cols // 2), np.float32)
            # strips whose uint16 stay in cache
            for j0, j1, s0, s1 in row_strips(rows // 2, rows, reach=0):
                sums4 = np.multiply(band[s0:s1], self._mask4[s0:s1], dtype=np.uint16)
                sums = cv2.resize(sums4, (cols // 2, j1 - j0), interpolation=cv2.INTER_AREA)
                np.multiply(sums, np.float32(0.25), out=out[j0:j1])
            return out
        weight0 = self._weight0 if self._weight0 is not None \
            else self.valid.astype(np.float32)
        return self._halve(band.astype(np.float32) * weight0)

    def fill(self, band: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``band`` (rows, cols) with its invalid pixels filled, float32 (into ``out``)."""
        if band.shape != self.valid.shape:
            raise ValueError(f"band shape {band.shape} does not match the mask's "
                             f"{self.valid.shape}")
        levels = [self._level1(band)]
        for _ in self.weights[1:]:
            levels.append(self._halve(levels[-1]))
        estimate: np.ndarray | None = None
        for a, w, has in zip(reversed(levels), reversed(self.weights), reversed(self._has),
                             strict=True):
            # the mean a / w where the level has data, the level above upsampled elsewhere
            estimate = (np.zeros_like(a) if estimate is None
                        else cv2.resize(estimate, (a.shape[1], a.shape[0]),
                                        interpolation=cv2.INTER_LINEAR))
            np.divide(a, w, out=estimate, where=has)
        rows, cols = band.shape
        if out is None:
            out = np.empty((rows, cols), np.float32)
        up = cv2.resize(estimate, (cols, rows), dst=out, interpolation=cv2.INTER_LINEAR)
        if up.ctypes.data != out.ctypes.data:  # OpenCV did not write in place
            out[...] = up
        np.copyto(out, band, where=self.valid, casting="unsafe")
        return out


# ----------------------------------------------------------------------- band-limited reduction

#: Largest relative leak of an alias into a kept DCT coefficient a pyramid level may add.
ALIAS_TOLERANCE = 5e-4

def _halvable(shape: tuple[int, ...]) -> bool:
    """Whether a band of ``shape`` can take a pyramid level: even sides, at least 16 px."""
    return all(n % 2 == 0 and n >= 16 for n in shape)


def _level_power(dtype: np.dtype | type, f_cut: float) -> int:
    """Order p of the level's filter cos^p(π f) (0 = no level): p = 3 on uint8, else 5."""
    if not 0.0 < f_cut < 0.25:  # kept coefficients must lie in the level's lower half
        return 0
    leak = np.tan(np.pi * f_cut)
    if dtype == np.uint8 and leak ** 3 <= ALIAS_TOLERANCE:
        return 3
    if leak ** 5 <= ALIAS_TOLERANCE:
        return 5
    return 0


def reduce_band_limited(band: np.ndarray, q_phi: float, *, reuse_buffers: bool = False
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Halve a band while keeping its DCT-II coefficients below the cutoff 1/(Qφ).

    Each level filters with the binomial kernel [1, 3, 3, 1]/8 or
    [1, 5, 10, 10, 5, 1]/32 (``BORDER_REFLECT``) centred on the middle of each
    2 × 2 block of pixels and keeps one value per block: transfer
    G(f) = cos^p(π f), p = 3 or 5. The blocks' centres keep the half-
    sample symmetry of the DCT-II at both ends (even lengths only), so the
    orthonormal DCT-II coefficient k of the level is exactly
    (G(k/2N) X_k − G((N − k)/2N) X_{N−k}) / √2 for a length-N input with
    coefficients X. Below the cutoff the alias term is at most tan^p(π f)
    ≤ :data:`ALIAS_TOLERANCE` of X_{N−k}; levels are added while that holds.
    uint8 bands take the first level in exact int16 arithmetic.

    Parameters
    ----------
    band
        (rows, cols) image, DN.
    q_phi
        Q × φ: the optics cutoff is 1 / (Q φ) cycles per pixel of ``band``.
    reuse_buffers
        Compute the levels in this thread's reused scratch arrays (:mod:`geosim.scratch`):
        the reduced band returned is then valid only until the next such call.

    Returns
    -------
    reduced : numpy.ndarray
        The last level (float32), or ``band`` itself when no level is possible.
    gain_rows, gain_cols : numpy.ndarray
        Per axis, for coefficient k of the reduced band's DCT-II: the factor
        (product of G(k/2N) / √2 over levels) that divides it into X_k.
    """
    data = np.asarray(band)
    gains = [np.ones(data.shape[0]), np.ones(data.shape[1])]
    f_cut = 1.0 / q_phi
    level = 0
    after_uint8_level = False
    while _halvable(data.shape):
        power = _level_power(data.dtype, f_cut)
        if power == 0:
            break
        rows, cols = data.shape
        level += 1
        halved = (scratch_array(f"degrade.level{level}", (rows // 2, cols // 2), np.float32)
                  if reuse_buffers else np.empty((rows // 2, cols // 2), np.float32))
        if power == 3:  # integer sums of 64 uint8 values: exact in int16
            halve_binomial4_uint8(data, out=halved)
        else:  # after a uint8 level the values are multiples of 1/64: exact float sums
            halve_binomial6(data, out=halved, exact_sums=after_uint8_level)
        after_uint8_level = power == 3
        for axis, n in enumerate((rows, cols)):
            gains[axis] = gains[axis][:n // 2] * level_gain(n, power)
        data, f_cut = halved, 2.0 * f_cut
    return (band if data is band else data), gains[0], gains[1]


def level1_allowed(shape: tuple[int, int], q_phi: float) -> bool:
    """Whether the p = 5 level (:func:`~geosim.physics.pyramid.halve_binomial6`) of a band
    of ``shape`` (rows, cols) may stand in for it at the cutoff 1 / ``q_phi`` (the first
    level of :func:`reduce_band_limited` would be at least that good: even sides ≥ 16, the
    kept coefficients in its lower half, the alias leak ≤ :data:`ALIAS_TOLERANCE`)."""
    return _halvable(shape) and _level_power(np.float32, 1.0 / q_phi) == 5


def reduce_from_level1(level1: np.ndarray, shape: tuple[int, int], q_phi: float, *,
                       reuse_buffers: bool = False
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`reduce_band_limited` of a band of ``shape`` given only its p = 5 first level.

    ``level1`` is ``halve_binomial6(band)`` (e.g. a tile's first overview, rounded to its
    integer type: the rounding is the only difference from reducing the band itself); the
    reduction goes on from it at twice the cutoff and the first level's gains
    (:func:`~geosim.physics.pyramid.level_gain`) are multiplied in. The caller checks
    :func:`level1_allowed` first.
    """
    rows, cols = shape
    if level1.shape != (rows // 2, cols // 2):
        raise ValueError(f"a first level of a {rows} × {cols} band is "
                         f"{rows // 2} × {cols // 2}, got {level1.shape}")
    reduced, gain_rows, gain_cols = reduce_band_limited(level1, q_phi / 2.0,
                                                        reuse_buffers=reuse_buffers)
    return (reduced, level_gain(rows, 5)[:gain_rows.size] * gain_rows,
            level_gain(cols, 5)[:gain_cols.size] * gain_cols)


# ----------------------------------------------------------------------- fast path

class SpectralDegrader:
    """Degrade one image at many Q quickly (the ``"fast"`` method).

    The truncated DCT-II coefficients of the image (invalid pixels filled by
    :func:`fill_invalid`) up to the cutoff of ``q_min`` are computed once;
    :meth:`degrade` then costs two small matrix products per band. Used by
    :func:`degrade_array` and by the calibration, which evaluates many Q.

    Parameters
    ----------
    image
        (rows, cols) or bands-first (bands, rows, cols), DN.
    phi
        UAV pixels per satellite pixel (whole number).
    q_min
        Smallest Q that :meth:`degrade` will be asked for (sets how many
        coefficients are kept: about 2N / (q_min φ) per axis).
    valid
        (rows, cols) bool mask, True = valid; None = all valid.
    obscuration
        Central obscuration, diameter ratio in [0, 1).
    reuse_buffers
        Compute the pyramid levels in this thread's reused scratch arrays
        (:mod:`geosim.scratch`), which stay allocated for the next image: for many
        images of one size (the tiles of a run); not for one-off large images.
    level1_of
        ``image`` is not the image but its p = 5 first pyramid level
        (:func:`~geosim.physics.pyramid.halve_binomial6`, e.g. a tile's first overview)
        and the image, all valid, is ``level1_of`` = (rows, cols) pixels: see
        :func:`reduce_from_level1`. Needs :func:`level1_allowed` at ``q_min``.
    """

    def __init__(self, image: np.ndarray, *, phi: int = 10, q_min: float,
                 valid: np.ndarray | None = None, obscuration: float = 0.0,
                 workers: int | None = None, reuse_buffers: bool = False,
                 level1_of: tuple[int, int] | None = None) -> None:
        self.phi = _check_phi(phi)
        self.q_min = _check_q(q_min)
        self.obscuration = _check_obscuration(obscuration)
        arr = np.asarray(image)
        stack = _as_stack(arr)
        self.squeeze = arr.ndim == 2
        self.shape = stack.shape[1:]
        self._level1_of = None if level1_of is None else (int(level1_of[0]),
                                                          int(level1_of[1]))
        if self._level1_of is not None:
            if valid is not None:
                raise ValueError("a first pyramid level stands in only for an all-valid "
                                 "image: give valid=None")
            if not level1_allowed(self._level1_of, self.q_min * self.phi):
                raise ValueError(f"a first pyramid level cannot stand in for a "
                                 f"{self._level1_of} image at Q = {self.q_min}, φ = "
                                 f"{self.phi}: degrade the image itself")
            self.shape = self._level1_of
        self.out_shape = _output_shape(self.shape, self.phi)
        valid_b = _check_valid(valid, self.shape)
        self.valid_out = (np.ones(self.out_shape, bool) if valid_b is None
                          else block_all(valid_b, self.phi))
        rows, cols = self.shape
        self.n_coef = (n_coefficients(rows, q=self.q_min, phi=self.phi),
                       n_coefficients(cols, q=self.q_min, phi=self.phi))
        self._workers = workers
        self._reuse = reuse_buffers
        filler = (InvalidFill(valid_b, self.shape)
                  if valid_b is not None and valid_b.any() else None)
        # invalid pixels filled one band at a time: a float32 copy of one band, not of all
        # (the same numbers: fill_invalid treats each band on its own)
        self._coef = np.stack([self._truncated_dct(band if filler is None
                                                   else self._filled(filler, band))
                               for band in stack])
        self._basis_rows = _resample_basis(rows, self.out_shape[0], self.n_coef[0], self.phi)
        self._basis_cols = _resample_basis(cols, self.out_shape[1], self.n_coef[1], self.phi)

    def _filled(self, filler: InvalidFill, band: np.ndarray) -> np.ndarray:
        """``band`` filled (:class:`InvalidFill`), in a reused buffer when asked."""
        out = (scratch_array("degrade.filled", self.shape, np.float32) if self._reuse
               else None)
        return filler.fill(band, out=out)

    def _truncated_dct(self, band: np.ndarray) -> np.ndarray:
        k_r, k_c = self.n_coef
        if self._level1_of is None:
            reduced, gain_rows, gain_cols = reduce_band_limited(
                band, self.q_min * self.phi, reuse_buffers=self._reuse)
        else:
            reduced, gain_rows, gain_cols = reduce_from_level1(
                band, self._level1_of, self.q_min * self.phi, reuse_buffers=self._reuse)
        mine = reduced is not band  # a level of our own, not the caller's band: in place
        # row transforms, then column transforms of the k_c kept columns only
        partial = np.empty((reduced.shape[0], k_c), np.float32)
        for r0 in range(0, reduced.shape[0], _ROW_BLOCK):
            block = reduced[r0:r0 + _ROW_BLOCK].astype(np.float32, copy=False)
            partial[r0:r0 + _ROW_BLOCK] = scipy.fft.dct(
                block, type=2, norm="ortho", axis=1, workers=self._workers,
                overwrite_x=mine)[:, :k_c]
        coef = scipy.fft.dct(partial, type=2, norm="ortho", axis=0,
                             workers=self._workers)[:k_r]
        if reduced is not band or self._level1_of is not None:
            # coefficients of a pyramid level: divide its gains out
            coef /= np.outer(gain_rows[:k_r], gain_cols[:k_c]).astype(np.float32)
        return coef

    @property
    def nbytes(self) -> int:
        """Memory held by the cached coefficients and bases, bytes."""
        return self._coef.nbytes + self._basis_rows.nbytes + self._basis_cols.nbytes

    def degrade(self, q: float) -> np.ndarray:
        """Degraded image at ``q`` ≥ ``q_min``: float64, (bands,) rows//φ × cols//φ, DN.

        Invalid output pixels (see :attr:`valid_out`) are 0.
        """
        q = _check_q(q)
        if q < self.q_min * (1 - 1e-12):
            raise ValueError(f"q = {q} is below q_min = {self.q_min} this degrader was "
                             "prepared for")
        transfer = optics_otf_below_cutoff(self.shape, q=q, phi=self.phi,
                                           obscuration=self.obscuration, max_coef=self.n_coef)
        k_r, k_c = transfer.shape
        a_r = self._basis_rows[:, :k_r]
        a_c = self._basis_cols[:, :k_c]

        n_r, n_c = self.out_shape
        rows_first = n_r * k_c * (k_r + n_c) <= n_c * k_r * (k_c + n_r)  # fewer flops

        def apply(c: np.ndarray) -> np.ndarray:
            z = c[:k_r, :k_c] * transfer
            return (a_r @ z) @ a_c.T if rows_first else a_r @ (z @ a_c.T)

        out = np.stack([apply(c) for c in self._coef])
        out[:, ~self.valid_out] = 0.0
        return out[0] if self.squeeze else out


# ----------------------------------------------------------------------- public API

def degrade_array(image: np.ndarray, *, q: float, phi: int = 10,
                  valid: np.ndarray | None = None, method: Method = "fast",
                  obscuration: float = 0.0, reuse_buffers: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Simulate a satellite image: (image ⊛ PSF(q)) ↓φ, bicubic.

    Parameters
    ----------
    image
        UAV image, bands-first (bands, rows, cols) or (rows, cols), in DN.
    q
        Q = λ f / (D p) on the satellite detector pitch (dimensionless, > 0).
    phi
        Satellite GSD / UAV GSD, a whole number (10 for 0.05 m → 0.5 m).
    valid
        (rows, cols) bool mask of valid UAV pixels (True = valid); None = all.
    method
        ``"fast"`` (default) or ``"reference"`` (full-resolution blur then
        ``cv2.resize`` INTER_CUBIC, literally the paper); they agree within 1 DN
        after rounding.
    obscuration
        Central obscuration of the telescope, diameter ratio in [0, 1).
    reuse_buffers
        ``"fast"``: pyramid levels in reused scratch arrays (:class:`SpectralDegrader`).

    Returns
    -------
    degraded : numpy.ndarray
        Float64, same layout as ``image`` with rows//φ × cols//φ pixels, DN
        (not rounded; use :func:`to_dtype`). Invalid pixels are 0.
    valid_out : numpy.ndarray
        Bool (rows//φ, cols//φ): True where all φ × φ source pixels are valid.
    """
    q = _check_q(q)
    phi = _check_phi(phi)
    obscuration = _check_obscuration(obscuration)
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    arr = np.asarray(image)
    stack = _as_stack(arr)
    out_shape = _output_shape(stack.shape[1:], phi)
    valid_b = _check_valid(valid, stack.shape[1:])
    valid_out = np.ones(out_shape, bool) if valid_b is None else block_all(valid_b, phi)
    if not valid_out.any():
        out = np.zeros((stack.shape[0], *out_shape))
    elif method == "reference":
        filled = stack if valid_b is None else _as_stack(fill_invalid(stack, valid_b))
        out = _degrade_reference(filled, q=q, phi=phi, obscuration=obscuration)
        out[:, ~valid_out] = 0.0
    else:
        out = SpectralDegrader(stack, phi=phi, q_min=q, valid=valid_b,
                               obscuration=obscuration,
                               reuse_buffers=reuse_buffers).degrade(q)
    return (out[0] if arr.ndim == 2 else out), valid_out


def degrade_level1(level1: np.ndarray, shape: tuple[int, int], *, q: float, phi: int = 10,
                   obscuration: float = 0.0, reuse_buffers: bool = False
                   ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`degrade_array` (``"fast"``) of an all-valid image known only by its first level.

    Parameters
    ----------
    level1
        ``halve_binomial6`` of each band of the image (:mod:`geosim.physics.pyramid`),
        bands-first ``(bands, rows // 2, cols // 2)`` or 2-D, in DN: e.g. a tile's first
        overview (:mod:`geosim.io.overviews`), rounded to whole DN. The rounding (±0.5 DN at
        0.1 m) reaches the output through the optics' passband only: ≈ 0.01 DN RMS at
        Q = 4.34, φ = 10 (docs/degradation.md).
    shape
        (rows, cols) of the image itself.
    q, phi, obscuration, reuse_buffers
        As for :func:`degrade_array`; :func:`level1_allowed` must hold at ``q``.

    Returns
    -------
    degraded, valid_out
        As for :func:`degrade_array` (every output pixel valid).
    """
    q = _check_q(q)
    degrader = SpectralDegrader(level1, phi=phi, q_min=q, obscuration=obscuration,
                                reuse_buffers=reuse_buffers, level1_of=shape)
    return degrader.degrade(q), degrader.valid_out

