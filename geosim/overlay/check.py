"""Overlay check: how far raster b's content sits from raster a's, window by window.

Both rasters (any CRS) are resampled once onto one north-up grid over their common
extent (a's CRS when projected, else the UTM zone of the centre; pixel size the coarser
of the two), then :func:`geosim.align.local.local_shift_field` measures the shift by
phase correlation in a grid of windows. A window's shift ``(dx, dy)`` in metres east and
north is the displacement that carries a's content onto b's: ground seen at ``(x, y)``
in a is seen at ``(x + dx, y + dy)`` in b.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS as ProjCRS
from rasterio.crs import CRS
from rasterio.warp import Resampling, calculate_default_transform, reproject, transform_bounds

from geosim.align.local import LocalShiftField, local_shift_field
from geosim.align.phasecorr import MIN_WINDOW_PX
from geosim.errors import AlignmentError, ExtentError
from geosim.io.raster import RasterData, image_band_indexes, open_raster, read_valid_mask

#: Largest side of the common grid in pixels (the check reads it whole); coarsen with gsd_m.
MAX_GRID_PX = 8192

#: Windows whose shifts agree within this many grid pixels form the consensus set.
CONSENSUS_TOL_PX = 0.5

#: Default σ (grid pixels) of the high-pass applied to both images before correlating.
HIGHPASS_SIGMA_PX = 3.0


@dataclass(frozen=True)
class CommonGrid:
    """North-up grid over the common extent of two rasters."""

    crs: CRS
    transform: Affine
    shape: tuple[int, int]   # rows, cols

    @property
    def gsd_m(self) -> float:
        """Pixel size in metres (the CRS is projected in metres)."""
        return float(self.transform.a)


@dataclass(frozen=True)
class OverlayResult:
    """Local shifts between rasters a and b on their common grid."""

    name: str
    a: str
    b: str
    grid: CommonGrid
    field: LocalShiftField

    def shifts_m(self) -> tuple[np.ndarray, np.ndarray]:
        """``(east_m, north_m)`` per window (NaN where not measured)."""
        g = self.grid.gsd_m
        return self.field.dx_px * g, -self.field.dy_px * g

    def centres_xy(self) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinates ``(x, y)`` of the window centres, in the grid CRS."""
        rows, cols = self.field.centres[..., 0], self.field.centres[..., 1]
        t = self.grid.transform
        return t.c + (cols + 0.5) * t.a, t.f + (rows + 0.5) * t.e

    def summary(self) -> dict:
        """JSON-able statistics over the confident windows (metres, east/north)."""
        east, north = self.shifts_m()
        ok = self.field.valid
        mag = np.hypot(east, north)[ok]
        out = {"name": self.name, "a": self.a, "b": self.b,
               "crs": self.grid.crs.to_string(), "gsd_m": self.grid.gsd_m,
               "window_px": self.field.window_px, "step_px": self.field.step_px,
               "n_windows": int(ok.size), "n_confident": int(ok.sum())}
        cons = consensus(east, north, tol_m=CONSENSUS_TOL_PX * self.grid.gsd_m)
        out.update(n_consensus=int(cons.sum()),
                   consensus_shift_m=([float(np.median(east[cons])),
                                       float(np.median(north[cons]))] if cons.any() else None))
        if mag.size:
            out.update(median_shift_m=[float(np.median(east[ok])), float(np.median(north[ok]))],
                       median_m=float(np.median(mag)), p95_m=float(np.percentile(mag, 95)),
                       max_m=float(mag.max()))
            out["median_shift_magnitude_m"] = float(np.hypot(*out["median_shift_m"]))
        else:
            out.update(median_shift_m=None, median_m=None, p95_m=None, max_m=None,
                       median_shift_magnitude_m=None)
        return out


def consensus(east: np.ndarray, north: np.ndarray, *, tol_m: float) -> np.ndarray:
    """Largest set of measured windows whose shifts agree within ``tol_m`` of one another's
    median (mode seeking; confidence not used). Boolean mask of the windows' shape; empty
    when fewer than three windows agree.

    Genuine shifts agree across windows while false peaks (scene change, repetitive
    texture) scatter, so the consensus set is a second, independent reading of the
    overlay next to the median of the confident windows.
    """
    e, n = east.ravel(), north.ravel()
    idx = np.flatnonzero(np.isfinite(e) & np.isfinite(n))
    best = np.zeros(e.size, dtype=bool)
    if idx.size:
        d = np.hypot(e[idx, None] - e[None, idx], n[idx, None] - n[None, idx])
        seed = int(np.argmax((d <= tol_m).sum(axis=1)))
        members = idx[d[seed] <= tol_m]
        ce, cn = np.median(e[members]), np.median(n[members])
        close = idx[np.hypot(e[idx] - ce, n[idx] - cn) <= tol_m]
        if close.size >= 3:
            best[close] = True
    return best.reshape(east.shape)


def highpass(grey: np.ndarray, valid: np.ndarray, sigma_px: float) -> np.ndarray:
    """Grey minus its Gaussian blur (σ in pixels), invalid pixels filled with the valid mean.

    Removes what differs most between acquisitions at large scale (illumination, shadows
    of another sun, haze gradients) before correlating; 0 returns the image unchanged.
    """
    import cv2

    if sigma_px <= 0:
        return grey
    filled = np.where(valid, grey, np.float32(grey[valid].mean() if valid.any() else 0.0))
    return (filled - cv2.GaussianBlur(filled, (0, 0), sigma_px)).astype(np.float32)


def working_crs(a: rasterio.DatasetReader, b: rasterio.DatasetReader) -> CRS:
    """a's CRS if projected, else b's, else the UTM zone of a's centre."""
    for ds in (a, b):
        if ds.crs.is_projected and ds.crs.linear_units_factor[1] == 1.0:
            return ds.crs
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    w, s, e, n = transform_bounds(a.crs, "EPSG:4326", *a.bounds)
    info = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(w, s, e, n))
    return CRS.from_wkt(ProjCRS.from_authority(info[0].auth_name, info[0].code).to_wkt())


def common_grid(a: rasterio.DatasetReader, b: rasterio.DatasetReader, *,
                gsd_m: float | None = None) -> CommonGrid:
    """The grid of the check: working CRS, coarser pixel size, intersection of the extents.

    The grid is snapped to a's pixel grid when a is already in the working CRS at that
    pixel size, so a is not resampled.
    """
    crs = working_crs(a, b)
    res = []
    for ds in (a, b):
        t, _, _ = calculate_default_transform(ds.crs, crs, ds.width, ds.height, *ds.bounds)
        res.append(abs(t.a))
    g = float(gsd_m) if gsd_m else max(res)
    ba = transform_bounds(a.crs, crs, *a.bounds, densify_pts=21)
    bb = transform_bounds(b.crs, crs, *b.bounds, densify_pts=21)
    left, bottom = max(ba[0], bb[0]), max(ba[1], bb[1])
    right, top = min(ba[2], bb[2]), min(ba[3], bb[3])
    if right - left < MIN_WINDOW_PX * g or top - bottom < MIN_WINDOW_PX * g:
        raise ExtentError(f"{a.name} and {b.name}: their common extent "
                          f"({max(right - left, 0):.1f} × {max(top - bottom, 0):.1f} m) is "
                          f"smaller than one {MIN_WINDOW_PX}-pixel window at {g:g} m; check "
                          "that the two rasters cover the same ground")
    if a.crs == crs and math.isclose(abs(a.transform.a), g, rel_tol=1e-9):
        x0, y0 = a.transform.c, a.transform.f   # snap to a's grid
        left = x0 + math.ceil((left - x0) / g - 1e-9) * g
        top = y0 - math.ceil((y0 - top) / g - 1e-9) * g
    cols, rows = int((right - left) / g + 1e-9), int((top - bottom) / g + 1e-9)
    if max(rows, cols) > MAX_GRID_PX:
        raise ExtentError(f"{a.name} and {b.name}: the common extent is {cols} × {rows} px at "
                          f"{g:g} m, more than {MAX_GRID_PX} px; give a coarser gsd_m "
                          f"(--gsd-m {g * max(rows, cols) / MAX_GRID_PX:.3g} or more)")
    return CommonGrid(crs, Affine(g, 0.0, left, 0.0, -g, top), (rows, cols))


def read_on_grid(ds: rasterio.DatasetReader, grid: CommonGrid) -> RasterData:
    """Grey image (mean of the image bands) and valid mask resampled onto ``grid``.

    Pixels are averaged (area-weighted) from sources more than 1.5× finer than the grid and
    interpolated (cubic) otherwise; a grid pixel is valid only when every source pixel
    under it is valid.

    Returns
    -------
    RasterData
        One band ``"grey"``, ``(1, rows, cols)`` float32, with the grid's transform and
        CRS (not the source's).
    """
    bands = image_band_indexes(ds)
    src_t, _, _ = calculate_default_transform(ds.crs, grid.crs, ds.width, ds.height, *ds.bounds)
    # a finer source is averaged (what a coarser sensor sees); a similar one is interpolated,
    # which keeps sub-pixel positions (averaging at ~1:1 snaps towards whole pixels)
    finer = abs(src_t.a) < grid.gsd_m / 1.5
    resampling = Resampling.average if finer else Resampling.cubic
    grey = np.zeros(grid.shape, np.float32)
    for b in bands:
        out = np.zeros(grid.shape, np.float32)
        reproject(rasterio.band(ds, b), out, dst_transform=grid.transform, dst_crs=grid.crs,
                  resampling=resampling, src_nodata=ds.nodata, dst_nodata=np.nan)
        grey += out / len(bands)
    mask = (read_valid_mask(ds) * 255).astype(np.uint8)
    valid = np.zeros(grid.shape, np.uint8)
    reproject(mask, valid, src_transform=ds.transform, src_crs=ds.crs,
              dst_transform=grid.transform, dst_crs=grid.crs, resampling=Resampling.min,
              dst_nodata=0)
    ok = (valid > 0) & np.isfinite(grey)
    return RasterData(array=grey[np.newaxis], valid=ok, transform=grid.transform,
                      crs=grid.crs, band_names=("grey",), path=Path(ds.name))


def auto_window_px(shape: tuple[int, int], window_px: int) -> int:
    """``window_px`` shrunk so that at least three windows fit along the shorter side."""
    fit = max(MIN_WINDOW_PX, min(shape) // 2)
    return int(min(window_px, fit))


def overlay_check(a_path: str | os.PathLike[str], b_path: str | os.PathLike[str], *,
                  name: str | None = None, window_px: int = 128, step_px: int | None = None,
                  gsd_m: float | None = None, min_confidence: float | None = None,
                  highpass_sigma_px: float = HIGHPASS_SIGMA_PX) -> OverlayResult:
    """Measure the local shifts that carry raster a's content onto raster b's.

    Parameters
    ----------
    a_path, b_path
        Georeferenced rasters (any CRS, any pixel size) that overlap.
    name
        Name of the pair in reports (default ``"<a stem> -> <b stem>"``).
    window_px
        Phase-correlation window side on the common grid, in pixels (shrunk to fit at
        least three windows along the shorter side; at least 32).
    step_px
        Distance between windows in pixels (default ``window_px // 2``).
    gsd_m
        Pixel size of the common grid in metres (default: the coarser of the two).
    min_confidence
        Windows below this phase-correlation confidence are not counted (default:
        :data:`geosim.align.phasecorr.DEFAULT_MIN_CONFIDENCE`).
    highpass_sigma_px
        σ in grid pixels of the high-pass (:func:`highpass`) applied to both images; 0 off.
    """
    from geosim.align.phasecorr import DEFAULT_MIN_CONFIDENCE

    with open_raster(a_path, what="overlay raster a") as a, \
            open_raster(b_path, what="overlay raster b") as b:
        grid = common_grid(a, b, gsd_m=gsd_m)
        on_a, on_b = read_on_grid(a, grid), read_on_grid(b, grid)
    ga, va, gb, vb = on_a.array[0], on_a.valid, on_b.array[0], on_b.valid
    both = va & vb
    if both.mean() < 0.05:
        raise AlignmentError(f"{a_path} and {b_path}: less than 5 % of their common extent is "
                             "valid in both; check their masks and footprints")
    win = auto_window_px(grid.shape, window_px)
    step = int(step_px) if step_px else max(1, win // 2)
    ga, gb = highpass(ga, both, highpass_sigma_px), highpass(gb, both, highpass_sigma_px)
    field = local_shift_field(np.where(both, ga, np.nan), np.where(both, gb, np.nan),
                              valid=both, window_px=win, step_px=step,
                              min_confidence=(DEFAULT_MIN_CONFIDENCE if min_confidence is None
                                              else min_confidence))
    label = name or f"{Path(a_path).stem} -> {Path(b_path).stem}"
    return OverlayResult(label, str(a_path), str(b_path), grid, field)


__all__ = ["CommonGrid", "OverlayResult", "common_grid", "overlay_check", "read_on_grid",
           "working_crs"]
