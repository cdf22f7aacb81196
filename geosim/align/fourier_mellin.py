"""Rotation + scale + translation registration (Fourier–Mellin, then refinement).

Conventions (see also :mod:`geosim.align.phasecorr`)
---------------------------------------------------
* Pixel coordinates ``(x, y)``: ``x`` = column, ``y`` = row (downward), pixel
  centres at integer coordinates.
* The transform maps **reference pixel coordinates to moving pixel
  coordinates**: the ground seen at reference pixel ``p = (x, y)`` is seen at
  moving pixel ``M @ [x, y, 1]``, with the 2×3 matrix

  ``M = [[ s·cos θ,  s·sin θ,  tx],``
  ``     [-s·sin θ,  s·cos θ,  ty]]``

  so ``cv2.warpAffine(moving, M, (cols, rows), flags=cv2.INTER_CUBIC |
  cv2.WARP_INVERSE_MAP)`` resamples ``moving`` onto the reference grid.
* ``rotation_deg`` (θ) is positive when the moving content is rotated
  **counter-clockwise as displayed** (rows growing downward, i.e. north-up
  display of a north-up raster) relative to the reference — the same sign as
  ``cv2.getRotationMatrix2D``: ``M`` equals ``cv2.getRotationMatrix2D(centre,
  rotation_deg, scale)`` with ``shift_px`` added to its last column.
* ``scale`` (s) > 1 means the moving content appears larger (objects span more
  moving pixels, i.e. the moving image has a finer effective pixel size).
* Rotation and scale are about the **image centre** ``c = ((cols - 1) / 2,
  (rows - 1) / 2)``; ``shift_px = (dx, dy)`` is the displacement of the centre:
  the reference centre ``c`` is seen at moving pixel ``c + (dx, dy)``. Hence
  ``tx, ty = c + shift_px - s·R(θ)·c``. For a pure translation ``shift_px``
  equals :attr:`geosim.align.PhaseCorrelation.shift_px`.

Method
------
1. Rotation/scale hypotheses (Reddy & Chatterji 1996): magnitude spectra of
   the apodised images (block-averaged to at most :data:`FM_MAX_PX` px),
   high-pass filtered with ``(1 - X)(2 - X)``, ``X = cos(π fx) cos(π fy)``,
   resampled on a log-polar grid over 0–180°; the :data:`N_LOG_POLAR_PEAKS`
   best peaks of the phase correlation of the two log-polar images (within
   ``max_rotation_deg`` and ``scale_range``) give rotations (modulo 180°) and
   log-scales. Each peak θ also yields θ ± 180° (the magnitude spectrum cannot
   tell them apart), and the identity (0°, 1) is always added, because on
   georeferenced imagery across seasons the log-polar peak can be lost while the
   truth is near the identity.
2. Every hypothesis is scored by the confidence of a translation phase
   correlation after undoing its rotation/scale; the best
   :data:`N_REFINED_CANDIDATES` (fewer when one clearly wins) are refined.
3. Refinement (iterated until the update moves no image corner by more than
   :data:`geosim.align.refine.REFINE_TOLERANCE_PX`): ``moving`` is resampled onto the reference
   with the current estimate, sub-pixel shifts are measured by phase
   correlation in a 4×4 grid of windows of 0.4 × the image side (centres 0.2,
   0.4, 0.6 and 0.8 of the side), a similarity is fitted to them by robust
   (Huber) weighted least squares and composed with the estimate. Phase
   correlation is insensitive to brightness and contrast changes, so this works
   across seasons where intensity-based refinement (e.g. ECC) struggles; the
   accuracy comes from the lever arm of the outer windows (0.6 × the side apart).
   On images larger than :data:`FM_MAX_PX` steps 1–3 run on the block-averaged
   images and the winner is refined again at full resolution.
4. ``confidence`` = whole-window phase-correlation confidence after alignment
   (scale of :attr:`geosim.align.PhaseCorrelation.confidence`) × the support of
   the refinement windows (see :func:`register_similarity`); the hypothesis
   with the highest confidence wins.

References
----------
Reddy, B. S. & Chatterji, B. N. (1996). An FFT-based technique for translation,
rotation, and scale-invariant image registration. IEEE Trans. Image Processing 5(8).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft

from geosim.align.phasecorr import (
    DEFAULT_MIN_CONFIDENCE,
    ENVELOPE_MIN,
    MIN_WINDOW_PX,
    PhaseCorrelation,
    _valid_mask,
    correlate_prepared,
    cross_power,
    grey_pair,
    noise_envelope,
    peak_confidence,
    prepare,
    refine_peak,
    top_peaks,
    window_2d,
    wrap_shift,
)
from geosim.errors import AlignmentError

__all__ = [
    "FM_MAX_PX",
    "SimilarityTransform",
    "register_similarity",
    "similarity_matrix",
]

#: The Fourier–Mellin (coarse) stage works on images block-averaged to at most
#: this many pixels per side; rotation and scale do not depend on resolution and
#: the refinement restores full accuracy.
FM_MAX_PX = 512

#: Smallest window side accepted by :func:`register_similarity`, in pixels.
MIN_SIMILARITY_PX = 64

#: Number of log-polar correlation peaks kept as rotation/scale hypotheses.
N_LOG_POLAR_PEAKS = 3

#: The refinement measures shifts in REFINE_GRID × REFINE_GRID windows.
REFINE_GRID = 4

#: Side of the refinement windows as a fraction of the shorter image side; the
#: windows are spread evenly from edge to edge, so the outer centres are
#: ``1 - f`` of the side apart.
REFINE_WINDOW_FRACTION = 0.4

#: Sub-pixel resolution of the refinement windows (1/20 px grid + quadratic fit).
REFINE_UPSAMPLE = 20

#: Number of best-scoring rotation/scale hypotheses that are refined and compared.
N_REFINED_CANDIDATES = 3

#: Windows agree with the fitted similarity within max(2 px, this × window side).
SUPPORT_TOLERANCE = 0.02

#: Support assigned when fewer than three refinement windows are confident.
UNCONFIRMED_SUPPORT = 0.5

#: Windows below this confidence are ignored by the refinement.
REFINE_MIN_CONFIDENCE = 0.05


def similarity_matrix(rotation_deg: float, scale: float, shift_px: tuple[float, float],
                      centre_px: tuple[float, float]) -> np.ndarray:
    """2×3 matrix mapping reference pixel ``(x, y)`` to moving pixel (see module docstring).

    Parameters
    ----------
    rotation_deg : float
        Counter-clockwise as displayed (rows down), degrees.
    scale : float
        Moving / reference size of the content (dimensionless).
    shift_px : tuple of float
        ``(dx, dy)`` displacement of ``centre_px``, pixels.
    centre_px : tuple of float
        ``(x, y)`` centre of rotation and scale, pixels.

    Returns
    -------
    numpy.ndarray
        ``(2, 3)`` float64.
    """
    t = math.radians(rotation_deg)
    a, b = scale * math.cos(t), scale * math.sin(t)
    cx, cy = centre_px
    dx, dy = shift_px
    return np.array([[a, b, cx + dx - (a * cx + b * cy)],
                     [-b, a, cy + dy - (-b * cx + a * cy)]], dtype=float)


def _h(m: np.ndarray) -> np.ndarray:
    """2×3 → 3×3 homogeneous."""
    return np.vstack([m, [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class SimilarityTransform:
    """Result of :func:`register_similarity` (conventions in the module docstring).

    Attributes
    ----------
    rotation_deg : float
        Rotation of the moving content relative to the reference, degrees,
        counter-clockwise as displayed (north-up, rows down) positive, in (-180, 180].
    scale : float
        Size of the moving content relative to the reference (dimensionless).
    shift_px : tuple of float
        ``(dx, dy)`` pixels: the reference centre ``centre_px`` is seen at moving
        pixel ``centre_px + shift_px`` (dx along columns, dy along rows, down).
    confidence : float
        In ``[0, 1]``, phase-correlation confidence after alignment.
    centre_px : tuple of float
        ``(x, y)`` centre of rotation and scale: ``((cols - 1) / 2, (rows - 1) / 2)``.
    residual_px : float
        Robust RMS, in pixels, of the refinement windows' shifts about the
        fitted similarity (a measure of non-rigid distortion; NaN if not refined).
    n_windows : int
        Number of windows used by the last refinement step (0: translation-only fallback).
    """

    rotation_deg: float
    scale: float
    shift_px: tuple[float, float]
    confidence: float
    centre_px: tuple[float, float]
    residual_px: float = float("nan")
    n_windows: int = 0

    @property
    def matrix(self) -> np.ndarray:
        """``(2, 3)`` float64: reference pixel ``[x, y, 1]`` → moving pixel.

        Use ``cv2.warpAffine(moving, M, (cols, rows), flags=cv2.INTER_CUBIC |
        cv2.WARP_INVERSE_MAP)`` to put ``moving`` onto the reference grid.
        """
        return similarity_matrix(self.rotation_deg, self.scale, self.shift_px, self.centre_px)

    @property
    def inverse_matrix(self) -> np.ndarray:
        """``(2, 3)`` float64: moving pixel → reference pixel."""
        return np.linalg.inv(_h(self.matrix))[:2]

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, centre_px: tuple[float, float], *,
                    confidence: float = float("nan"), residual_px: float = float("nan"),
                    n_windows: int = 0) -> SimilarityTransform:
        """Decompose a reference→moving similarity matrix (2×3 or 3×3, pixels).

        The linear part is projected onto the nearest similarity
        ``[[a, b], [-b, a]]`` (least squares) if it is not one exactly.
        """
        m = np.asarray(matrix, dtype=float)[:2]
        a = 0.5 * (m[0, 0] + m[1, 1])
        b = 0.5 * (m[0, 1] - m[1, 0])
        cx, cy = centre_px
        centre_to = m @ np.array([cx, cy, 1.0])
        return cls(rotation_deg=math.degrees(math.atan2(b, a)), scale=math.hypot(a, b),
                   shift_px=(float(centre_to[0] - cx), float(centre_to[1] - cy)),
                   confidence=float(confidence), centre_px=(float(cx), float(cy)),
                   residual_px=float(residual_px), n_windows=int(n_windows))

    def map_matrix(self, transform) -> np.ndarray:
        """The same transform in map coordinates, as a 3×3 matrix.

        Parameters
        ----------
        transform : affine.Affine
            GDAL-style geotransform of the (shared) pixel grid of both windows:
            maps ``(col, row)`` of pixel *corners* to map ``(X, Y)``; the pixel
            centre ``(x, y)`` of this module is at corner coordinates ``(x + 0.5, y + 0.5)``.

        Returns
        -------
        numpy.ndarray
            ``(3, 3)`` float64 mapping reference map coordinates ``[X, Y, 1]`` to
            the moving image's map coordinates (where that ground appears in the
            moving image's stated georeference).
        """
        t = np.array([[transform.a, transform.b, transform.c],
                      [transform.d, transform.e, transform.f],
                      [0.0, 0.0, 1.0]])
        half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        pix_to_map = t @ half
        return pix_to_map @ _h(self.matrix) @ np.linalg.inv(pix_to_map)

    def shift_m(self, transform) -> tuple[float, float]:
        """``shift_px`` in map units: displacement ``(dX, dY)`` of the window centre.

        For a north-up grid of pixel size ``g`` this is ``(dx·g, -dy·g)``.
        """
        dx, dy = self.shift_px
        return (float(transform.a * dx + transform.b * dy),
                float(transform.d * dx + transform.e * dy))

    def to_dict(self) -> dict:
        """JSON-able dict of the fields and the matrix."""
        return {"rotation_deg": float(self.rotation_deg), "scale": float(self.scale),
                "shift_px": [float(v) for v in self.shift_px],
                "confidence": float(self.confidence),
                "centre_px": [float(v) for v in self.centre_px],
                "residual_px": None if math.isnan(self.residual_px) else float(self.residual_px),
                "n_windows": int(self.n_windows),
                "matrix": self.matrix.tolist()}


# --------------------------------------------------------------------------- internals


def _downsample(grey: np.ndarray, valid: np.ndarray, factor: int
                ) -> tuple[np.ndarray, np.ndarray]:
    if factor <= 1:
        return grey, valid
    h, w = grey.shape
    size = (max(1, w // factor), max(1, h // factor))
    g = cv2.resize(np.where(valid, grey, 0).astype(np.float32), size, interpolation=cv2.INTER_AREA)
    v = cv2.resize(valid.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    ok = v > 0.999
    g = np.where(ok, g / np.maximum(v, 1e-6), 0).astype(np.float32)
    return g, ok


def _highpass(n: int) -> np.ndarray:
    f = sfft.fftshift(sfft.fftfreq(n))
    x = np.outer(np.cos(np.pi * f), np.cos(np.pi * f))
    return ((1.0 - x) * (2.0 - x)).astype(np.float32)


def _log_polar_spectrum(prep: np.ndarray, size: int, map_x: np.ndarray, map_y: np.ndarray,
                        hp: np.ndarray) -> np.ndarray:
    pad = np.zeros((size, size), dtype=np.float32)
    pad[:prep.shape[0], :prep.shape[1]] = prep
    mag = np.abs(sfft.fftshift(sfft.fft2(pad))).astype(np.float32) * hp
    return cv2.remap(mag, map_x, map_y, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def _fourier_mellin(r: np.ndarray, rv: np.ndarray, m: np.ndarray, mv: np.ndarray, *,
                    max_rotation_deg: float, scale_range: tuple[float, float],
                    upsample_factor: int, n_peaks: int = N_LOG_POLAR_PEAKS
                    ) -> list[tuple[float, float, float]]:
    """Candidate ``(rotation_deg, scale, confidence)`` from the log-polar spectra.

    Rotation is modulo 180° (in [-90, 90)); the ``n_peaks`` best peaks of the
    log-polar phase correlation within the search ranges are returned, best first.
    """
    apod = window_2d(r.shape, "hann")
    feather_px = max(4.0, min(r.shape) / 16.0)
    pr, _ = prepare(r, rv, apod, feather_px=feather_px, what="reference image")
    pm, _ = prepare(m, mv, apod, feather_px=feather_px, what="moving image")
    size = int(sfft.next_fast_len(max(r.shape)))
    n_theta = size                      # samples over 180°
    n_rho = size // 2
    r_max = 0.45 * size
    r_min = max(2.0, 0.02 * size)
    dlog = math.log(r_max / r_min) / n_rho
    theta = np.arange(n_theta) * (np.pi / n_theta)
    radius = r_min * np.exp(np.arange(n_rho) * dlog)
    c = size // 2
    map_x = (c + radius[None, :] * np.cos(theta)[:, None]).astype(np.float32)
    map_y = (c + radius[None, :] * np.sin(theta)[:, None]).astype(np.float32)
    hp = _highpass(size)
    lp_r = _log_polar_spectrum(pr, size, map_x, map_y, hp)
    lp_m = _log_polar_spectrum(pm, size, map_x, map_y, hp)
    # rows (angle) are circular with period 180°; apodise along log-radius only
    apod_lp = np.outer(np.ones(n_theta, dtype=np.float32),
                       window_2d((1, n_rho), "hann")[0]).astype(np.float32)
    all_valid = np.ones(lp_r.shape, dtype=bool)
    qr, wr = prepare(lp_r, all_valid, apod_lp, feather_px=1.0, what="reference spectrum")
    qm, wm = prepare(lp_m, all_valid, apod_lp, feather_px=1.0, what="moving spectrum")
    # allowed peak positions: scale range and rotation range
    dy = (np.arange(n_theta) + n_theta // 2) % n_theta - n_theta // 2     # angle samples
    dx = (np.arange(n_rho) + n_rho // 2) % n_rho - n_rho // 2             # log-radius samples
    rot = -dy * (180.0 / n_theta)                                         # in [-90, 90]
    rot_ok = np.minimum(np.abs(rot), 180.0 - np.abs(rot)) <= max_rotation_deg + 180.0 / n_theta
    s_lo, s_hi = scale_range
    sc = np.exp(-dx * dlog)
    sc_ok = (sc >= s_lo * math.exp(-dlog)) & (sc <= s_hi * math.exp(dlog))
    allowed = rot_ok[:, None] & sc_ok[None, :]
    xr = cross_power(qr, qm)
    surface = sfft.ifft2(xr).real
    env = noise_envelope(wr, wm)
    usable = env >= ENVELOPE_MIN
    z_surface = surface / np.maximum(env, ENVELOPE_MIN)
    out = []
    for iy, ix in top_peaks(surface, n_peaks, allowed=allowed & usable):
        y, x, _ = refine_peak(surface, iy, ix, upsample_factor)
        d_theta, d_rho = wrap_shift(y, n_theta), wrap_shift(x, n_rho)
        out.append((-d_theta * 180.0 / n_theta, math.exp(-d_rho * dlog),
                    peak_confidence(z_surface, iy, ix, usable=usable)))
    return out


def _candidates(r: np.ndarray, rv: np.ndarray, m: np.ndarray, mv: np.ndarray, *,
                max_rotation_deg: float, scale_range: tuple[float, float],
                upsample_factor: int) -> list[tuple[float, float]]:
    """Rotation/scale hypotheses: log-polar peaks, their 180° twins, and the identity."""
    cands: list[tuple[float, float]] = []
    for rot, scale, _ in _fourier_mellin(r, rv, m, mv, max_rotation_deg=max_rotation_deg,
                                         scale_range=scale_range,
                                         upsample_factor=upsample_factor):
        for rr in (rot, rot + 180.0 if rot <= 0 else rot - 180.0):
            if abs(rr) <= max_rotation_deg + 1.0:
                cands.append((rr, scale))
    cands.append((0.0, 1.0))  # georeferenced inputs are usually close to the identity
    return cands


def _fill_invalid(grey: np.ndarray, valid: np.ndarray) -> np.ndarray:
    if valid.all():
        return grey
    mean = float(grey[valid].mean(dtype=np.float64)) if valid.any() else 0.0
    return np.where(valid, grey, np.float32(mean)).astype(np.float32)


def _warp(mov_filled: np.ndarray, vm: np.ndarray, m: np.ndarray, shape: tuple[int, int]
          ) -> tuple[np.ndarray, np.ndarray]:
    """Resample ``moving`` onto the reference grid with the ref→moving matrix ``m``."""
    h, w = shape
    out = cv2.warpAffine(mov_filled, m, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    v = cv2.warpAffine(vm.astype(np.float32), m, (w, h),
                       flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    ok = v > 0.999
    ok = cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    return out, ok


def _correlate_full(ref: np.ndarray, vr: np.ndarray, warped: np.ndarray, wv: np.ndarray,
                    upsample_factor: int) -> PhaseCorrelation:
    apod = window_2d(ref.shape, "hann")
    feather_px = max(4.0, min(ref.shape) / 16.0)
    pr, wr = prepare(ref, vr, apod, feather_px=feather_px, what="reference image")
    pm, wm = prepare(warped, wv, apod, feather_px=feather_px,
                     what="moving image resampled onto the reference")
    return correlate_prepared(pr, pm, wr, wm, upsample_factor=upsample_factor)


def _translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class _Fit:
    m: np.ndarray           # 3×3 ref→moving
    rms_px: float
    n_windows: int
    support: float          # [0, 1], agreement of the refinement windows
    phase_confidence: float  # whole-window phase correlation after alignment

    @property
    def confidence(self) -> float:
        return self.phase_confidence * self.support


def _refine(ref: np.ndarray, vr: np.ndarray, mov_filled: np.ndarray, vm: np.ndarray,
            m: np.ndarray, *, upsample_factor: int, max_iterations: int
            ) -> tuple[np.ndarray, float, int, float]:
    """Iteratively refine a ref→moving 3×3 similarity with a grid of window shifts.

    :func:`geosim.align.refine.refine_with_windows` on ``REFINE_GRID``² windows of
    ``REFINE_WINDOW_FRACTION`` of the side; a whole-window translation when fewer than
    three are confident. Returns ``(m, rms_px, n_windows, support)``; ``support`` is the
    confidence-weighted fraction of the confident windows of the last iteration that
    agree with the fitted similarity within ``max(2 px, SUPPORT_TOLERANCE × window side)``
    (:data:`UNCONFIRMED_SUPPORT` when fewer than three windows are confident).
    """
    from geosim.align.refine import refine_with_windows

    h, w = ref.shape
    win = int(REFINE_WINDOW_FRACTION * min(h, w)) & ~1
    if win >= MIN_WINDOW_PX:
        starts_r = np.round(np.linspace(0, h - win, REFINE_GRID)).astype(int)
        starts_c = np.round(np.linspace(0, w - win, REFINE_GRID)).astype(int)
    else:
        starts_r = starts_c = np.zeros(0, dtype=int)

    def whole_window(warped: np.ndarray, wv: np.ndarray) -> np.ndarray:
        pc = _correlate_full(ref, vr, warped, wv, upsample_factor)
        return _translation(*pc.shift_px)

    r = refine_with_windows(
        ref, vr, lambda mm: _warp(mov_filled, vm, mm[:2], ref.shape), m,
        starts_r=starts_r, starts_c=starts_c, window_px=max(win, MIN_WINDOW_PX),
        min_confidence=REFINE_MIN_CONFIDENCE,
        upsample_factor=min(upsample_factor, REFINE_UPSAMPLE), min_valid_fraction=0.5,
        support_tolerance_px=max(2.0, SUPPORT_TOLERANCE * win), model="similarity",
        max_iterations=max_iterations, fallback=whole_window)
    return r.matrix, r.rms_px, r.n_windows, r.support


def _solve(ref: np.ndarray, vr: np.ndarray, mov_filled: np.ndarray, vm: np.ndarray,
           m_init: np.ndarray, *, upsample_factor: int, refine: bool,
           max_iterations: int) -> _Fit | None:
    """Translation (after ``m_init``'s rotation/scale), refinement and evaluation."""
    warped, wv = _warp(mov_filled, vm, m_init[:2], ref.shape)
    if np.count_nonzero(wv & vr) < 0.05 * wv.size:
        return None
    pc = _correlate_full(ref, vr, warped, wv, upsample_factor)
    m = m_init @ _translation(*pc.shift_px)
    rms, n_used, support = float("nan"), 0, 1.0
    if refine:
        m, rms, n_used, support = _refine(ref, vr, mov_filled, vm, m,
                                          upsample_factor=upsample_factor,
                                          max_iterations=max_iterations)
    warped, wv = _warp(mov_filled, vm, m[:2], ref.shape)
    if np.count_nonzero(wv & vr) < 0.05 * wv.size:
        return None
    pc = _correlate_full(ref, vr, warped, wv, upsample_factor)
    return _Fit(m=m, rms_px=rms, n_windows=n_used, support=support,
                phase_confidence=pc.confidence)


def _same_rotation_scale(m1: np.ndarray, m2: np.ndarray, *, rotation_deg: float = 0.5,
                         scale_rel: float = 0.005) -> bool:
    """Whether two similarity matrices have nearly the same rotation and scale."""
    z1 = complex(m1[0, 0], m1[0, 1])
    z2 = complex(m2[0, 0], m2[0, 1])
    if abs(z2) == 0:
        return False
    ratio = z1 / z2
    return (abs(math.degrees(math.atan2(ratio.imag, ratio.real))) < rotation_deg
            and abs(abs(ratio) - 1.0) < scale_rel)


def _downsample_matrix(shape: tuple[int, int], shape_ds: tuple[int, int]) -> np.ndarray:
    """3×3 map from full-resolution pixel coordinates to block-averaged ones (cv2.resize)."""
    sy, sx = shape_ds[0] / shape[0], shape_ds[1] / shape[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


# --------------------------------------------------------------------------- public API


def register_similarity(reference: np.ndarray, moving: np.ndarray, *,
                        valid_reference: np.ndarray | None = None,
                        valid_moving: np.ndarray | None = None,
                        max_rotation_deg: float = 180.0,
                        scale_range: tuple[float, float] = (0.5, 2.0),
                        upsample_factor: int = 100,
                        min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                        refine: bool = True,
                        max_iterations: int = 5) -> SimilarityTransform:
    """Rotation, scale and translation of ``moving`` relative to ``reference``.

    Parameters
    ----------
    reference, moving : numpy.ndarray
        Windows of the same shape (``(rows, cols)`` or bands-first
        ``(bands, rows, cols)``, reduced to grey), at least 64×64 px; typically the
        same central window (e.g. 1024–2000 px) of two rasters on a shared grid.
    valid_reference, valid_moving : numpy.ndarray of bool, optional
        ``(rows, cols)`` masks, ``True`` = valid (default: finite pixels).
    max_rotation_deg : float
        Largest |rotation| searched, degrees (default 180: any). Below 90 it
        also settles the 180° ambiguity of the spectrum; for north-up
        georeferenced flights a small value (e.g. 10) is faster and more robust.
    scale_range : tuple of float
        ``(min, max)`` scale searched (default 0.5–2; e.g. (0.9, 1.1) for
        flights resampled to the same GSD).
    upsample_factor : int
        Sub-pixel resolution of the whole-window phase correlations
        (``1/upsample_factor`` px before a final quadratic fit).
    min_confidence : float
        Raise :class:`~geosim.errors.AlignmentError` below this final confidence
        (default :data:`geosim.align.DEFAULT_MIN_CONFIDENCE` = 0.1).
    refine : bool
        Run the window-based refinement (default True); without it the result
        is the best Fourier–Mellin hypothesis with a whole-window translation
        (about 0.05° / 0.05 % on clean synthetic images, far worse across
        seasonal change).
    max_iterations : int
        Maximum refinement iterations.

    Returns
    -------
    SimilarityTransform
        ``rotation_deg``, ``scale``, ``shift_px``, ``confidence`` and ``matrix``
        (reference pixel → moving pixel; conventions in the module docstring).
        ``confidence`` is the whole-window phase-correlation confidence after
        alignment (:attr:`geosim.align.PhaseCorrelation.confidence`) times the
        refinement windows' support: the confidence-weighted fraction of the
        confident windows whose shift agrees with the fitted similarity within
        ``max(2 px, 2 % of the window side)``, or 0.5 when fewer than three of
        the 16 windows are confident (rotation and scale are then not
        confirmed locally).

    Raises
    ------
    RasterError
        Shapes differ or are not 2-D / bands-first 3-D.
    AlignmentError
        The windows are smaller than 64 px, have fewer than 5 % valid pixels or
        are flat, or the final confidence is below ``min_confidence`` (no
        texture, no overlap, unrelated images); the message says which.
    """
    ref, mov = grey_pair(reference, moving, min_px=MIN_SIMILARITY_PX,
                         purpose="registering rotation and scale")
    lo, hi = (float(v) for v in scale_range)
    if not 0 < lo <= 1.0 <= hi:
        raise ValueError(f"scale_range must satisfy 0 < min <= 1 <= max, got {scale_range}")
    if max_rotation_deg < 0:
        raise ValueError(f"max_rotation_deg must be ≥ 0, got {max_rotation_deg}")
    vr = _valid_mask(ref, valid_reference, "reference")
    vm = _valid_mask(mov, valid_moving, "moving")
    upsample_factor = int(upsample_factor)
    centre = ((ref.shape[1] - 1) / 2.0, (ref.shape[0] - 1) / 2.0)

    # 1. rotation/scale hypotheses (Fourier–Mellin) on images of at most FM_MAX_PX
    factor = max(1, math.ceil(max(ref.shape) / FM_MAX_PX))
    r_ds, rv_ds = _downsample(ref, vr, factor)
    m_ds, mv_ds = _downsample(mov, vm, factor)
    cands = _candidates(r_ds, rv_ds, m_ds, mv_ds, max_rotation_deg=max_rotation_deg,
                        scale_range=(lo, hi), upsample_factor=upsample_factor)
    # 2. quick score of each: translation phase correlation after undoing rotation/scale
    m_ds_filled = _fill_invalid(m_ds, mv_ds)
    centre_ds = ((r_ds.shape[1] - 1) / 2.0, (r_ds.shape[0] - 1) / 2.0)
    scored = []
    for rot, scale in cands:
        m_rs = similarity_matrix(rot, scale, (0.0, 0.0), centre_ds)
        warped, wv = _warp(m_ds_filled, mv_ds, m_rs, r_ds.shape)
        if np.count_nonzero(wv & rv_ds) < 0.05 * wv.size:
            continue
        pc = _correlate_full(r_ds, rv_ds, warped, wv, 1)  # integer peak suffices to score
        scored.append((pc.confidence + 1e-3 * pc.peak, _h(m_rs)))
    scored.sort(key=lambda t: -t[0])
    # 3. the best few, refined (at reduced resolution), compete on final confidence
    fits: list[_Fit] = []
    for score, m_rs in scored[:N_REFINED_CANDIDATES]:
        if fits and scored[0][0] >= 0.3 and score < 0.5 * scored[0][0]:
            break  # a clear winner: weaker hypotheses are not worth refining
        if any(_same_rotation_scale(m_rs, f.m) for f in fits):
            continue  # an earlier hypothesis already converged here
        fit = _solve(r_ds, rv_ds, m_ds_filled, mv_ds, m_rs, upsample_factor=upsample_factor,
                     refine=refine, max_iterations=max_iterations if factor == 1 else 3)
        if fit is not None:
            fits.append(fit)
    if not fits:
        raise AlignmentError("moving window: no rotation/scale hypothesis leaves an overlap with "
                             "the reference; the windows do not show the same ground")
    best = max(fits, key=lambda f: (f.confidence, f.phase_confidence))
    mov_filled = _fill_invalid(mov, vm)
    if factor > 1:  # 4. full resolution
        s = _downsample_matrix(ref.shape, r_ds.shape)
        m_full = np.linalg.inv(s) @ best.m @ s
        rot0 = SimilarityTransform.from_matrix(m_full, centre)
        m_rs = _h(similarity_matrix(rot0.rotation_deg, rot0.scale, (0.0, 0.0), centre))
        fit = _solve(ref, vr, mov_filled, vm, m_rs, upsample_factor=upsample_factor,
                     refine=refine, max_iterations=max_iterations)
        if fit is None:
            raise AlignmentError("moving window: the estimated transform leaves almost no "
                                 "overlap with the reference; the windows do not show the same "
                                 "ground")
        best = fit
    result = SimilarityTransform.from_matrix(best.m, centre, confidence=best.confidence,
                                             residual_px=best.rms_px, n_windows=best.n_windows)
    if not result.confidence >= min_confidence:
        raise AlignmentError(
            f"registration confidence {result.confidence:.3f} is below min_confidence "
            f"{min_confidence:.3f} (best estimate: rotation {result.rotation_deg:.3f}°, scale "
            f"{result.scale:.5f}, shift {result.shift_px[0]:.2f}, {result.shift_px[1]:.2f} px; "
            f"whole-window confidence {best.phase_confidence:.3f}, window support "
            f"{best.support:.2f}): the windows lack common texture, do not overlap or show "
            "different ground; choose another window or lower min_confidence")
    return result
