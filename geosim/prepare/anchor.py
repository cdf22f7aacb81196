"""Anchoring the aligned UAV stack to the satellite scene (``site.anchor = "satellite"``).

The paper aligns every flight to a reference flight, so the aligned stack sits in
the reference flight's *stated* georeference, with that flight's georeferencing
error (on the sample site ≈ 1.4 m and 0.43°), while the satellite scene has its
own. With the anchor ``"satellite"`` the align step also registers the reference
flight to the satellite scene and composes that map → map transform ``T`` into
every flight's correction (``C' = T ∘ C``), so aligned rasters, tiles, degraded
tiles and labels overlay the satellite scene.

Method (all on the 0.5 m satellite grid, over the aligned window)
------------------------------------------------------------------
1. **Area-average** the reference flight's grey level (BT.601 luma) to the
   satellite grid: each satellite pixel is the mean of its φ × φ UAV pixels,
   valid only when all of them are (:func:`area_average`), read window by window
   (:func:`read_averaged_window`).
2. **Suppress what changes between dates**: pixels darker than
   :data:`DARK_FRACTION` × the median grey of each image are masked out
   (:func:`stable_mask`). Tree and fence shadows move with the sun and dominate
   a correlation otherwise (on the sample site the unmasked whole-scene phase
   correlation locks onto the shadows: confidence 0.07, wrong by 15 px; masked:
   confidence 0.6–0.8, right within 0.15 px); water and dark cattle go too.
3. **High-pass** both images (minus a Gaussian of :data:`HIGHPASS_SIGMA_PX`,
   :func:`highpass`) on top of the kernel's partial whitening: the UAV image is
   much sharper than the satellite's, and a blur is zero-phase (symmetric PSF),
   so the mismatch lowers the peak but does not move it.
4. **Coarse translation** by windowed sub-pixel phase correlation of the whole
   overlap (:func:`geosim.align.phasecorr.phase_correlate`).
5. **Local refinement**: after undoing the current estimate, phase correlation in
   a grid of windows (:func:`geosim.align.local.local_shift_field`) and a robust
   (Huber) least-squares fit of a translation or a similarity to the window
   shifts, iterated until the update moves no corner by more than 0.01 px.
6. **Model choice**: a similarity (rotation + scale + translation) is kept only
   when its rotation/scale part is significant (> :data:`SIGNIFICANCE` standard
   errors) *and* matters (moves the extent's edge by more than
   :data:`MIN_EFFECT_PX` satellite pixels); otherwise a translation. Satellite
   products rarely have rotation or scale errors at this scale, but the
   reference *flight* may: on the sample site its georeference is rotated by
   −0.43° and scaled by 0.9973, which a translation would leave as up to
   ±0.4 m (0.8 satellite px) at the edges of a 100 m extent.
7. **Confidence** = phase-correlation confidence of the whole overlap after
   applying the fit × the confidence-weighted fraction of the local windows
   that agree with the fit within :data:`SUPPORT_TOLERANCE_PX` (0.5 when fewer
   than three windows could be measured).

Conventions: pixel coordinates as in :mod:`geosim.align` (``(x, y)`` = (column,
row), centres at integers); :attr:`AnchorFit.matrix_px` maps *satellite* pixel
centres to *reference* pixel centres of the same window (where the ground seen at
a satellite pixel is seen in the area-averaged reference flight).
:func:`anchor_affine` turns it into ``T``: map coordinates in the reference
flight's frame (the paper's aligned frame) → map coordinates in the satellite's
frame.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from affine import Affine
from rasterio.windows import Window

from geosim.errors import AlignmentError, GeosimError
from geosim.io.raster import (
    RasterData,
    open_raster,
    read_window,
)
from geosim.prepare.alignment import _3x3, correction_affine

#: Pixels darker than this fraction of an image's median grey are masked (shadows,
#: water, dark animals: what moves or changes between acquisitions).
DARK_FRACTION = 0.6
#: Gaussian sigma (satellite px) of the high-pass applied before correlation.
HIGHPASS_SIGMA_PX = 4.0
#: Smallest / largest side of the local windows, satellite px.
LOCAL_WINDOW_MIN_PX = 64
LOCAL_WINDOW_MAX_PX = 128
#: Largest number of local windows (the step grows on large sites).
MAX_WINDOWS = 400
#: A window is measured only if this fraction of its pixels is valid in both images.
MIN_WINDOW_VALID_FRACTION = 0.4
#: Fewer confident windows than this: no similarity is fitted (translation only).
MIN_WINDOWS_SIMILARITY = 6
#: Rotation/scale must exceed this many (nominal) standard errors to be kept: the
#: windows overlap by half, so neighbouring residuals are correlated and the nominal
#: standard error is optimistic by up to about 2× ...
SIGNIFICANCE = 5.0
#: ... and move the extent's edge by more than this many satellite pixels.
MIN_EFFECT_PX = 0.1
#: Windows agreeing with the fit within this distance (satellite px) support it.
SUPPORT_TOLERANCE_PX = 1.0
#: Support assigned when fewer than three windows are confident.
UNCONFIRMED_SUPPORT = 0.5
#: Refinement stops after this many iterations (or when an update moves no corner by
#: more than :data:`geosim.align.refine.REFINE_TOLERANCE_PX`, shared with the flights).
MAX_ITERATIONS = 5
#: Local windows below this phase-correlation confidence are not used.
WINDOW_MIN_CONFIDENCE = 0.1

METHOD = ("reference flight area-averaged to the satellite grid; pixels darker than "
          f"{DARK_FRACTION:g} x median masked (shadows, water, cattle) and a Gaussian "
          f"high-pass (sigma {HIGHPASS_SIGMA_PX:g} px) in both; whole-overlap sub-pixel phase "
          "correlation, then local phase correlation in a grid of windows with a robust "
          "(Huber) fit of a translation or, when significant, a similarity")


@dataclass(frozen=True)
class AnchorFit:
    """Result of :func:`register_to_satellite` (satellite-grid pixels).

    Attributes
    ----------
    matrix_px : numpy.ndarray
        ``(3, 3)``: satellite pixel centre ``[x, y, 1]`` → reference pixel centre
        (same window, same 0.5 m grid).
    model : str
        ``"translation"`` or ``"similarity"``.
    confidence : float
        In ``[0, 1]``: ``phase_confidence × support`` (module docstring).
    phase_confidence : float
        Whole-overlap phase-correlation confidence after applying the fit.
    support : float
        Confidence-weighted fraction of the local windows agreeing with the fit.
    n_windows : int
        Local windows used by the last fit (0: whole-overlap translation only).
    rms_px : float
        Robust RMS of the window shifts about the fit, satellite px (NaN if none).
    coarse_shift_px : tuple of float
        Whole-overlap translation of step 4, ``(dx, dy)`` px (reference content
        relative to the satellite).
    rotation_deg, scale : float
        Of the reference content relative to the satellite, as displayed
        (counter-clockwise positive, rows down), and its scale.
    similarity_significance : float
        Rotation/scale part of the first similarity fit (where the model is
        chosen) in standard errors (NaN when not fitted).
    similarity_effect_px : float
        Displacement that rotation/scale part causes at the farthest window, px.
    window_px : int
        Side of the local windows, satellite px (0 when none fitted).
    """

    matrix_px: np.ndarray
    model: str
    confidence: float
    phase_confidence: float
    support: float
    n_windows: int
    rms_px: float
    coarse_shift_px: tuple[float, float]
    rotation_deg: float
    scale: float
    similarity_significance: float
    similarity_effect_px: float
    window_px: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (pixel units)."""
        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)
        return {"model": self.model, "confidence": float(self.confidence),
                "phase_confidence": float(self.phase_confidence),
                "support": float(self.support), "n_windows": int(self.n_windows),
                "window_px": int(self.window_px), "rms_px": num(self.rms_px),
                "coarse_shift_px": [float(v) for v in self.coarse_shift_px],
                "similarity_significance": num(self.similarity_significance),
                "similarity_effect_px": num(self.similarity_effect_px),
                "rotation_deg": float(self.rotation_deg), "scale": float(self.scale),
                "matrix_px": np.asarray(self.matrix_px, dtype=float)[:2].tolist()}


# --------------------------------------------------------------------------- kernels


def area_average(grey: np.ndarray, valid: np.ndarray, phi: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of each ``phi × phi`` block (UAV grid → satellite grid), with its mask.

    Parameters
    ----------
    grey
        ``(rows, cols)`` grey levels; rows and cols are multiples of ``phi``.
    valid
        ``(rows, cols)`` bool, True = valid.
    phi
        Satellite pixel size in UAV pixels (whole number).

    Returns
    -------
    (grey, valid)
        ``(rows / phi, cols / phi)`` float32 block means over the valid pixels, and
        a mask that is True only where every pixel of the block is valid (this is
        ``cv2.resize(..., INTER_AREA)`` of the masked image divided by that of
        the mask, exact for a whole-number factor).
    """
    g = np.asarray(grey, dtype=np.float64)
    v = np.asarray(valid, dtype=bool)
    h, w = g.shape
    if h % phi or w % phi:
        raise ValueError(f"area_average: shape {g.shape} is not a multiple of phi = {phi}")
    shape = (h // phi, phi, w // phi, phi)
    total = np.where(v, g, 0.0).reshape(shape).sum(axis=(1, 3))
    count = v.reshape(shape).sum(axis=(1, 3))
    out = np.where(count > 0, total / np.maximum(count, 1), 0.0).astype(np.float32)
    return out, count == phi * phi


def stable_mask(grey: np.ndarray, valid: np.ndarray, *,
                dark_fraction: float = DARK_FRACTION) -> np.ndarray:
    """Valid pixels that are not dark (shadow, water, dark animals), eroded by one pixel.

    Parameters
    ----------
    grey
        ``(rows, cols)`` grey levels (any units, haze offset allowed).
    valid
        ``(rows, cols)`` bool.
    dark_fraction
        Pixels below ``dark_fraction × median(grey[valid])`` are dropped.
    """
    v = np.asarray(valid, dtype=bool)
    if not v.any():
        return v.copy()
    keep = v & (grey > dark_fraction * float(np.median(grey[v])))
    return cv2.erode(keep.astype(np.uint8), np.ones((3, 3), np.uint8),
                     borderType=cv2.BORDER_CONSTANT, borderValue=1).astype(bool)


def highpass(grey: np.ndarray, valid: np.ndarray, *,
             sigma_px: float = HIGHPASS_SIGMA_PX) -> np.ndarray:
    """``grey`` minus its Gaussian low-pass (sigma in px), invalid pixels filled first.

    Invalid pixels are set to the valid median before filtering so that masked
    shadows do not leak dark halos; returns float32 (invalid pixels then 0).
    """
    v = np.asarray(valid, dtype=bool)
    fill = float(np.median(grey[v])) if v.any() else 0.0
    g = np.where(v, grey, fill).astype(np.float32)
    out = g - cv2.GaussianBlur(g, (0, 0), float(sigma_px), borderType=cv2.BORDER_REFLECT)
    return np.where(v, out, 0.0).astype(np.float32)


def prepare_for_satellite(grey: np.ndarray, valid: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`stable_mask` then :func:`highpass`: the images the registration correlates."""
    keep = stable_mask(grey, valid)
    return highpass(grey, keep), keep


def _warp(image: np.ndarray, valid: np.ndarray, m: np.ndarray, shape: tuple[int, int]
          ) -> tuple[np.ndarray, np.ndarray]:
    """``out(p) = image(m @ p)`` (3×3, pixel centres), bicubic, conservative mask."""
    flags = cv2.WARP_INVERSE_MAP
    out = cv2.warpAffine(image.astype(np.float32), m[:2], (shape[1], shape[0]),
                         flags=cv2.INTER_CUBIC | flags, borderMode=cv2.BORDER_CONSTANT)
    mv = cv2.warpAffine(valid.astype(np.float32), m[:2], (shape[1], shape[0]),
                        flags=cv2.INTER_LINEAR | flags, borderMode=cv2.BORDER_CONSTANT)
    ok = mv >= 0.999
    return np.where(ok, out, 0.0).astype(np.float32), ok


def _window_layout(shape: tuple[int, int]) -> tuple[int, int]:
    """Local window side and step (satellite px) for an overlap of ``shape``."""
    side = min(shape)
    win = 2 ** int(math.floor(math.log2(max(side / 3.0, 1.0))))
    win = int(min(LOCAL_WINDOW_MAX_PX, max(LOCAL_WINDOW_MIN_PX, win)))
    step = win // 2
    while (((shape[0] - win) // step + 1) * ((shape[1] - win) // step + 1) > MAX_WINDOWS):
        step += win // 4
    return win, step


def register_to_satellite(reference: np.ndarray, reference_valid: np.ndarray,
                          satellite: np.ndarray, satellite_valid: np.ndarray, *,
                          min_confidence: float = 0.1, what: str = "reference flight"
                          ) -> AnchorFit:
    """Register the (area-averaged) reference flight to the satellite scene.

    Parameters
    ----------
    reference, satellite
        ``(rows, cols)`` grey images of the same window of the satellite grid (the
        reference flight area-averaged with :func:`area_average`).
    reference_valid, satellite_valid
        ``(rows, cols)`` bool masks, True = valid.
    min_confidence
        Refuse (AlignmentError) below this :attr:`AnchorFit.confidence`.
    what
        Names the pair in error messages.

    Returns
    -------
    AnchorFit
        ``matrix_px`` maps satellite pixel centres to reference pixel centres.

    Raises
    ------
    AlignmentError
        The overlap is smaller than 32 × 32 px or flat, or the confidence is below
        ``min_confidence``.
    """
    from geosim.align.local import window_starts
    from geosim.align.phasecorr import phase_correlate
    from geosim.align.refine import refine_with_windows

    ref = np.asarray(reference, dtype=np.float32)
    sat = np.asarray(satellite, dtype=np.float32)
    if ref.shape != sat.shape:
        raise AlignmentError(f"{what}: reference {ref.shape} and satellite {sat.shape} "
                             "windows differ in shape")
    ref_p, ref_v = prepare_for_satellite(ref, reference_valid)
    sat_p, sat_v = prepare_for_satellite(sat, satellite_valid)
    try:
        coarse = phase_correlate(sat_p, ref_p, valid_reference=sat_v, valid_moving=ref_v)
    except GeosimError as exc:
        raise AlignmentError(f"{what}: {exc}") from exc
    m = np.array([[1.0, 0.0, coarse.shift_px[0]], [0.0, 1.0, coarse.shift_px[1]],
                  [0.0, 0.0, 1.0]])
    win, step = _window_layout(sat.shape)
    model: str | None = None
    rms, n_used, support = float("nan"), 0, UNCONFIRMED_SUPPORT
    signif = effect = float("nan")
    if min(sat.shape) >= LOCAL_WINDOW_MIN_PX:
        r = refine_with_windows(
            sat_p, sat_v, lambda mm: _warp(ref_p, ref_v, mm, sat.shape), m,
            starts_r=window_starts(sat.shape[0], win, step),
            starts_c=window_starts(sat.shape[1], win, step), window_px=win,
            min_confidence=WINDOW_MIN_CONFIDENCE, upsample_factor=20,
            min_valid_fraction=MIN_WINDOW_VALID_FRACTION,
            support_tolerance_px=SUPPORT_TOLERANCE_PX, model="auto", joint_mask=True,
            min_windows_similarity=MIN_WINDOWS_SIMILARITY, significance=SIGNIFICANCE,
            min_effect_px=MIN_EFFECT_PX, max_iterations=MAX_ITERATIONS)
        m, rms, n_used, support = r.matrix, r.rms_px, r.n_windows, r.support
        model, signif, effect = r.model, r.significance, r.effect_px
    warped, wv = _warp(ref_p, ref_v, m, sat.shape)
    try:
        final = phase_correlate(sat_p, warped, valid_reference=sat_v, valid_moving=wv)
    except GeosimError as exc:
        raise AlignmentError(f"{what}: {exc}") from exc
    if n_used == 0:  # no local windows: the whole-overlap translation is the estimate
        m = m @ np.array([[1.0, 0.0, final.shift_px[0]], [0.0, 1.0, final.shift_px[1]],
                          [0.0, 0.0, 1.0]])
    a = 0.5 * (m[0, 0] + m[1, 1])
    b = 0.5 * (m[0, 1] - m[1, 0])
    fit = AnchorFit(matrix_px=m, model=model or "translation",
                    confidence=float(final.confidence * support),
                    phase_confidence=float(final.confidence), support=support,
                    n_windows=n_used, rms_px=rms,
                    coarse_shift_px=(float(coarse.shift_px[0]), float(coarse.shift_px[1])),
                    rotation_deg=math.degrees(math.atan2(b, a)), scale=math.hypot(a, b),
                    similarity_significance=signif, similarity_effect_px=effect,
                    window_px=win if n_used else 0)
    if not fit.confidence >= min_confidence:
        raise AlignmentError(
            f"{what}: registration confidence {fit.confidence:.3f} is below "
            f"min_align_confidence {min_confidence:.3f} (whole-overlap phase correlation "
            f"{fit.phase_confidence:.3f}, window support {fit.support:.2f}, "
            f"{fit.n_windows} window(s))")
    return fit


def anchor_affine(matrix_px: np.ndarray, window_transform: Affine) -> Affine:
    """``T``: reference-frame map coordinates → satellite-frame map coordinates.

    Parameters
    ----------
    matrix_px
        ``(3, 3)`` satellite pixel centre → reference pixel centre
        (:attr:`AnchorFit.matrix_px`).
    window_transform
        Affine of the satellite-grid window both images were cut from (pixel corners).
    """
    m = np.asarray(matrix_px, dtype=float)
    pix = window_transform @ Affine.translation(0.5, 0.5)      # centre index → map
    mm = Affine(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2])
    return ~(pix @ mm @ ~pix)


def compose_entry(entry: Mapping[str, Any], anchor: Affine, grid_transform: Affine
                  ) -> dict[str, Any]:
    """A flight's ``alignment.json`` entry with the anchor composed in: ``C' = T ∘ C``.

    ``shift_m``, ``rotation_deg``, ``scale`` (at the same ``center_m``),
    ``correction_affine`` and ``matrix_grid_px`` become those of the full
    correction (what :func:`geosim.prepare.alignment.correction_affine` returns and
    what the aligned raster shows); the flight → reference part is kept under
    ``to_reference``. ``matrix_px`` stays the kernel's flight → reference result.
    """
    out = dict(entry)
    c = correction_affine(entry)
    full = anchor @ c
    cx, cy = (float(v) for v in entry["center_m"])
    moved = full @ (cx, cy)
    g = _3x3(grid_transform)
    m_grid = np.linalg.inv(g) @ np.linalg.inv(_3x3(full)) @ g
    out["to_reference"] = {k: entry[k] for k in ("shift_m", "rotation_deg", "scale",
                                                 "correction_affine", "matrix_grid_px")
                           if k in entry}
    out.update(shift_m=[float(moved[0] - cx), float(moved[1] - cy)],
               rotation_deg=math.degrees(math.atan2(full.d, full.a)),
               scale=math.sqrt(abs(full.determinant)),
               correction_affine=[float(v) for v in list(full)[:6]],
               matrix_grid_px=m_grid[:2].tolist())
    return out


# --------------------------------------------------------------------------- I/O


def read_averaged_window(path: str | os.PathLike[str], window: Window, phi: int, *,
                         block_px: int = 2048) -> RasterData:
    """Grey level of a UAV-grid raster, area-averaged to the satellite grid, block by block.

    Parameters
    ----------
    path
        A raster on the site UAV grid (e.g. ``grid/<flight>.tif``).
    window
        UAV-grid window whose offsets and sizes are multiples of ``phi``; it may reach
        outside the raster (those pixels are invalid).
    phi
        Satellite pixel size in UAV pixels.
    block_px
        Largest block read at once (rounded down to a multiple of ``phi``).

    Returns
    -------
    RasterData
        One band ``"grey"``: ``(1, height / phi, width / phi)`` float32 BT.601 luma means
        of the first three image bands, the mask (:func:`area_average`: every UAV pixel
        under a satellite pixel valid), the raster's CRS and the transform of the
        averaged grid (the window's transform scaled by ``phi``).
    """
    from geosim.align.phasecorr import as_grey

    if any(int(v) % phi for v in (window.col_off, window.row_off, window.width,
                                  window.height)):
        raise ValueError(f"window {window} is not on whole satellite pixels (phi = {phi})")
    rows, cols = int(window.height) // phi, int(window.width) // phi
    grey = np.zeros((rows, cols), np.float32)
    valid = np.zeros((rows, cols), bool)
    step = max(phi, (block_px // phi) * phi)
    with open_raster(path, what="raster on the site UAV grid", require_crs=False) as ds:
        for r0 in range(0, int(window.height), step):
            for c0 in range(0, int(window.width), step):
                h = min(step, int(window.height) - r0)
                w = min(step, int(window.width) - c0)
                block = read_window(ds, Window(int(window.col_off) + c0,
                                               int(window.row_off) + r0, w, h),
                                    max_bands=3, boundless=True, path=path)
                g, ok = area_average(as_grey(block.array), block.valid, phi)
                grey[r0 // phi:(r0 + h) // phi, c0 // phi:(c0 + w) // phi] = g
                valid[r0 // phi:(r0 + h) // phi, c0 // phi:(c0 + w) // phi] = ok
        transform = ds.window_transform(window) * Affine.scale(phi)
        crs = ds.crs
    return RasterData(array=grey[np.newaxis], valid=valid, transform=transform, crs=crs,
                      band_names=("grey",), path=Path(path))


@dataclass(frozen=True)
class AveragedWarpTask:
    """One strip of :func:`read_averaged_through_warp` (an engine task)."""

    warp: Any                                  # geosim.prepare.onewarp.ComposedWarp
    grid_transform: tuple[float, ...]          # the site UAV grid
    window: Window                             # the strip, UAV grid, whole satellite px
    phi: int
    step: int                                  # block side, UAV px (a multiple of phi)


def averaged_warp_task(task: AveragedWarpTask) -> tuple[np.ndarray, np.ndarray]:
    """Run an :class:`AveragedWarpTask`: the strip's ``(grey, valid)`` on the satellite grid,
    block by block as :func:`read_averaged_window` reads a raster on the UAV grid."""
    import rasterio

    from geosim.align.phasecorr import as_grey
    from geosim.io.raster import image_band_indexes
    from geosim.prepare.onewarp import read_warped

    win, phi, step = task.window, task.phi, task.step
    grey = np.zeros((int(win.height) // phi, int(win.width) // phi), np.float32)
    valid = np.zeros(grey.shape, bool)
    g = Affine(*task.grid_transform[:6])
    with rasterio.open(task.warp.src_path) as src:
        bands = image_band_indexes(src)[:3]
        for r0 in range(0, int(win.height), step):
            for c0 in range(0, int(win.width), step):
                h, w = min(step, int(win.height) - r0), min(step, int(win.width) - c0)
                t = g @ Affine.translation(int(win.col_off) + c0, int(win.row_off) + r0)
                img, ok = read_warped(task.warp, t, (h, w), src=src, bands=bands)
                a, b = area_average(as_grey(img), ok, phi)
                grey[r0 // phi:(r0 + h) // phi, c0 // phi:(c0 + w) // phi] = a
                valid[r0 // phi:(r0 + h) // phi, c0 // phi:(c0 + w) // phi] = b
    return grey, valid


def read_averaged_through_warp(warp: Any, grid_transform: Affine, window: Window, phi: int,
                               *, block_px: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_averaged_window` of a flight resampled on the fly onto the site UAV grid
    through its composed warp (nothing written), one engine task per strip of blocks.

    The same numbers as warping the window into a raster (``warp_raster_task``) and
    reading that with :func:`read_averaged_window`: the warp of a block does not depend on
    where the block is, and the blocks are the same.

    Returns
    -------
    (grey, valid)
        ``(height / phi, width / phi)`` float32 BT.601 luma means and their mask.
    """
    from geosim.engine import parallel_map

    if any(int(v) % phi for v in (window.col_off, window.row_off, window.width,
                                  window.height)):
        raise ValueError(f"window {window} is not on whole satellite pixels (phi = {phi})")
    step = max(phi, (block_px // phi) * phi)
    strips = [Window(int(window.col_off), int(window.row_off) + r0, int(window.width),
                     min(step, int(window.height) - r0))
              for r0 in range(0, int(window.height), step)]
    parts = parallel_map(averaged_warp_task, [
        AveragedWarpTask(warp, tuple(grid_transform)[:6], s, phi, step) for s in strips],
        desc="anchor reference")
    return (np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]))


def read_satellite_window(path: str | os.PathLike[str], window: Window) -> RasterData:
    """The RGB bands, valid mask and window transform of ``grid/satellite.tif`` (the window
    may reach outside the scene: those pixels are invalid)."""
    with open_raster(path, what="satellite scene on the shared grid") as ds:
        return read_window(ds, window, max_bands=3, boundless=True, path=path)


__all__ = ["AnchorFit", "DARK_FRACTION", "HIGHPASS_SIGMA_PX", "METHOD", "anchor_affine",
           "area_average", "compose_entry", "highpass",
           "prepare_for_satellite", "read_averaged_through_warp", "read_averaged_window",
           "read_satellite_window",
           "register_to_satellite", "stable_mask"]
