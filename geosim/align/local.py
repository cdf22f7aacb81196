"""Local shift field: phase correlation in a grid of windows.

Run after global alignment to reveal what a single similarity transform cannot
absorb (stitching warps, relief displacement, local misregistration). Shift and
pixel conventions are those of :mod:`geosim.align.phasecorr`: a window's
``(dx, dy)`` is the position of the moving content relative to the reference
at that window, in pixels, ``dx`` along columns and ``dy`` along rows (down).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from tqdm import tqdm

from geosim.align.phasecorr import (
    DEFAULT_MIN_CONFIDENCE,
    MIN_WINDOW_PX,
    as_grey,
    correlate_prepared,
    prepare,
    window_2d,
)
from geosim.errors import AlignmentError, GeosimError, RasterError

__all__ = ["LocalShiftField", "local_shift_field", "local_shift_fields", "window_starts"]


@dataclass(frozen=True, eq=False)
class LocalShiftField:
    """Shifts measured in a grid of windows (``n_win_rows × n_win_cols``).

    Attributes
    ----------
    centres : numpy.ndarray
        ``(n_win_rows, n_win_cols, 2)`` float, window centres in pixel
        coordinates ``(row, col)`` (pixel centres at integer coordinates, so a
        window starting at column 0 of width ``w`` is centred at ``(w - 1) / 2``).
    dx_px, dy_px : numpy.ndarray
        ``(n_win_rows, n_win_cols)`` float, shift in pixels along columns (x,
        right) and rows (y, down): the position of the moving content relative
        to the reference in that window (reference pixel ``(x, y)`` ~ moving
        pixel ``(x + dx, y + dy)``). NaN where the window could not be measured
        (too few valid pixels, flat).
    confidence : numpy.ndarray
        ``(n_win_rows, n_win_cols)`` float in ``[0, 1]`` (0 where not measured),
        same scale as :attr:`geosim.align.PhaseCorrelation.confidence`.
    valid : numpy.ndarray
        ``(n_win_rows, n_win_cols)`` bool: measured and ``confidence >= min_confidence``.
    window_px, step_px : int
        Window side and step, in pixels.
    min_confidence : float
        Threshold used for :attr:`valid`.
    """

    centres: np.ndarray
    dx_px: np.ndarray
    dy_px: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray
    window_px: int
    step_px: int
    min_confidence: float = DEFAULT_MIN_CONFIDENCE

    @property
    def magnitude_px(self) -> np.ndarray:
        """``hypot(dx_px, dy_px)`` per window, in pixels (NaN where not measured)."""
        return np.hypot(self.dx_px, self.dy_px)

    def summary(self) -> dict:
        """Statistics of the shift magnitude over the confident windows.

        Returns
        -------
        dict
            JSON-able: ``n_windows``, ``n_confident``, ``median_px``, ``p95_px``,
            ``max_px`` (shift magnitude in pixels; ``None`` when no window is
            confident), ``median_dx_px``, ``median_dy_px`` (signed medians, a
            non-zero value means a residual global shift), ``window_px``, ``step_px``.
        """
        mag = self.magnitude_px[self.valid]
        out: dict = {"n_windows": int(self.valid.size), "n_confident": int(mag.size),
                     "window_px": int(self.window_px), "step_px": int(self.step_px)}
        if mag.size:
            out.update(median_px=float(np.median(mag)), p95_px=float(np.percentile(mag, 95)),
                       max_px=float(mag.max()),
                       median_dx_px=float(np.median(self.dx_px[self.valid])),
                       median_dy_px=float(np.median(self.dy_px[self.valid])))
        else:
            out.update(median_px=None, p95_px=None, max_px=None, median_dx_px=None,
                       median_dy_px=None)
        return out


def window_starts(n_px: int, window_px: int, step_px: int) -> np.ndarray:
    """First pixel of each window along one axis (windows fully inside ``n_px``)."""
    if window_px > n_px:
        return np.zeros(0, dtype=int)
    return np.arange(0, n_px - window_px + 1, step_px, dtype=int)


def shifts_in_windows(ref: np.ndarray, mov: np.ndarray, valid_ref: np.ndarray,
                      valid_mov: np.ndarray, starts_r: np.ndarray, starts_c: np.ndarray,
                      window_px: int, *, upsample_factor: int, min_valid_fraction: float,
                      progress: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase-correlate grey float32 images window by window.

    Returns ``(dx_px, dy_px, confidence)`` arrays of shape ``(len(starts_r), len(starts_c))``;
    unmeasurable windows get NaN shifts and confidence 0.
    """
    return shifts_in_windows_many(ref, [(mov, valid_ref, valid_mov)], starts_r, starts_c,
                                  window_px, upsample_factor=upsample_factor,
                                  min_valid_fraction=min_valid_fraction, progress=progress)[0]


def shifts_in_windows_many(ref: np.ndarray,
                           movs: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
                           starts_r: np.ndarray, starts_c: np.ndarray, window_px: int, *,
                           upsample_factor: int, min_valid_fraction: float,
                           progress: bool = False
                           ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`shifts_in_windows` of several moving images against one reference, window
    by window; ``movs`` holds ``(moving, valid_ref, valid_mov)`` per image.

    Each window of the reference is prepared and transformed once for every moving image
    whose window has the same valid pixels (re-prepared otherwise), while it is still in
    the CPU's cache: the same numbers as one :func:`shifts_in_windows` per image.
    """
    shape = (len(starts_r), len(starts_c))
    out = [(np.full(shape, np.nan), np.full(shape, np.nan), np.zeros(shape)) for _ in movs]
    apod = window_2d((window_px, window_px), "hann")
    feather_px = max(4.0, window_px / 16.0)
    jobs = [(i, j) for i in range(shape[0]) for j in range(shape[1])]
    for i, j in tqdm(jobs, desc="local shifts", unit="window", disable=not progress,
                     leave=False):
        r0, c0 = int(starts_r[i]), int(starts_c[j])
        sl = (slice(r0, r0 + window_px), slice(c0, c0 + window_px))
        prepared: tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray] | None] | None
        prepared = None                          # (its valid window, (image, weight, FFT))
        for (mov, valid_ref, valid_mov), (dx, dy, conf) in zip(movs, out, strict=True):
            vr, vm = valid_ref[sl], valid_mov[sl]
            if min(vr.mean(), vm.mean()) < min_valid_fraction:
                continue
            if prepared is None or not np.array_equal(prepared[0], vr):
                try:
                    pr, wr = prepare(ref[sl], vr, apod, feather_px=feather_px, what="window")
                    prepared = (vr, (pr, wr, sfft.fft2(pr)))
                except GeosimError:
                    prepared = (vr, None)            # flat window
            if prepared[1] is None:
                continue
            pr, wr, fr = prepared[1]
            try:
                pm, wm = prepare(mov[sl], vm, apod, feather_px=feather_px, what="window")
            except GeosimError:
                continue  # flat window
            pc = correlate_prepared(pr, pm, wr, wm, upsample_factor=upsample_factor,
                                    fft_ref=fr)
            dx[i, j], dy[i, j] = pc.shift_px
            conf[i, j] = pc.confidence
    return out


def pair_valid(ref: np.ndarray, mov: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """Pixels usable in both grey images: finite in each and, if given, ``valid``.

    Raises
    ------
    RasterError
        The images, or the mask and the images, differ in shape.
    """
    if ref.shape != mov.shape:
        raise RasterError(f"reference {ref.shape} and moving {mov.shape} images differ in "
                          "shape; resample both onto the same grid first")
    both = np.isfinite(ref) & np.isfinite(mov)
    if valid is not None:
        v = np.asarray(valid, dtype=bool)
        if v.shape != ref.shape:
            raise RasterError(f"valid mask shape {v.shape} does not match the images "
                              f"{ref.shape}")
        both &= v
    return both


def local_shift_field(reference: np.ndarray, moving: np.ndarray, *,
                      valid: np.ndarray | None = None, window_px: int = 256,
                      step_px: int = 256, min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                      upsample_factor: int = 20, min_valid_fraction: float = 0.5,
                      progress: bool = False) -> LocalShiftField:
    """Measure the local shift in a regular grid of windows.

    Parameters
    ----------
    reference, moving : numpy.ndarray
        Images of the same shape on the same pixel grid (typically after global
        alignment), ``(rows, cols)`` or bands-first ``(bands, rows, cols)``.
    valid : numpy.ndarray of bool, optional
        ``(rows, cols)``, ``True`` where *both* images are valid (default: all
        pixels finite in both).
    window_px : int
        Window side in pixels (≥ 32). The shift resolvable is at most about a
        quarter of it; accuracy improves with size.
    step_px : int
        Distance between window starts in pixels (``step_px < window_px`` overlaps).
        Windows start at pixel 0 and must lie fully inside the image.
    min_confidence : float
        Windows below this confidence are flagged not valid (default 0.1, see
        :data:`geosim.align.DEFAULT_MIN_CONFIDENCE`).
    upsample_factor : int
        Sub-pixel resolution ``1 / upsample_factor`` px before the final quadratic fit.
    min_valid_fraction : float
        A window is measured only if at least this fraction of its pixels is valid.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    LocalShiftField
        Per-window centres, ``dx_px``, ``dy_px``, ``confidence``, ``valid``; see
        :meth:`LocalShiftField.summary`.

    Raises
    ------
    RasterError
        Shapes differ or are not 2-D / bands-first 3-D.
    AlignmentError
        The image is smaller than one window, or ``window_px`` < 32.
    """
    return local_shift_fields(reference, [(moving, valid)], window_px=window_px,
                              step_px=step_px, min_confidence=min_confidence,
                              upsample_factor=upsample_factor,
                              min_valid_fraction=min_valid_fraction, progress=progress)[0]


def local_shift_fields(reference: np.ndarray,
                       movings: Sequence[tuple[np.ndarray, np.ndarray | None]], *,
                       window_px: int = 256, step_px: int = 256,
                       min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                       upsample_factor: int = 20, min_valid_fraction: float = 0.5,
                       progress: bool = False) -> list[LocalShiftField]:
    """:func:`local_shift_field` of several ``(moving, valid)`` images against one reference.

    The same fields as one :func:`local_shift_field` per image; each reference window is
    prepared once for the images that share its valid pixels
    (:func:`shifts_in_windows_many`).
    """
    ref = as_grey(reference, "reference")
    window_px, step_px = int(window_px), int(step_px)
    if window_px < MIN_WINDOW_PX or step_px < 1:
        raise AlignmentError(f"window_px={window_px}, step_px={step_px}: windows must be at least "
                             f"{MIN_WINDOW_PX} px and the step at least 1 px")
    if window_px > min(ref.shape):
        raise AlignmentError(f"window_px={window_px} is larger than the image "
                             f"({ref.shape[0]}×{ref.shape[1]} px); use a smaller window")
    jobs = []
    for moving, valid in movings:
        mov = as_grey(moving, "moving")
        both = pair_valid(ref, mov, valid)
        jobs.append((mov, both, both))
    starts_r = window_starts(ref.shape[0], window_px, step_px)
    starts_c = window_starts(ref.shape[1], window_px, step_px)
    measured = shifts_in_windows_many(ref, jobs, starts_r, starts_c, window_px,
                                      upsample_factor=int(upsample_factor),
                                      min_valid_fraction=min_valid_fraction, progress=progress)
    half = (window_px - 1) / 2.0
    centres = np.stack(np.meshgrid(starts_r + half, starts_c + half, indexing="ij"),
                       axis=-1).astype(float)
    return [LocalShiftField(centres=centres.copy(), dx_px=dx, dy_px=dy, confidence=conf,
                            valid=np.isfinite(dx) & (conf >= min_confidence),
                            window_px=window_px, step_px=step_px,
                            min_confidence=float(min_confidence))
            for dx, dy, conf in measured]
