"""Resample once: original flight file → site grid → alignment correction, in one warp.

A flight's pixels reach the aligned grid (and its tiles) through one composed mapping,
evaluated per destination pixel and interpolated once (bicubic)::

    aligned-grid pixel centre ─(site grid affine)→ aligned-frame map point p
      ─(field, optional)→ p' ─(C⁻¹, the inverse alignment correction)→ stated map point
      ─(site CRS → flight CRS, pyproj)→ flight map point ─(flight affine⁻¹)→ source pixel

instead of two bicubic resamplings (flight → ``grid/<flight>.tif`` → ``aligned/<flight>.tif``).

Determinism: the mapping is evaluated exactly on a lattice of nodes every
``lattice_px`` pixels anchored at the *site grid's* origin, and bilinearly
interpolated between nodes (exact for the affine parts; the projection's curvature
over ``lattice_px`` pixels is far below 1e-6 px). Every pixel's source coordinate
therefore depends only on its global grid index, never on the window it is computed
in: any split into windows (or tasks, on any worker) gives the same bits.

Hook for non-rigid corrections: :attr:`ComposedWarp.field` is an optional picklable
callable ``field(x_m, y_m) -> (x_m, y_m)`` applied to aligned-frame map coordinates
(site CRS, metres) before ``C⁻¹``; it is evaluated on the lattice nodes. For full
control, :meth:`ComposedWarp.source_coords` is the per-window function "destination
window transform → source pixel coordinates" that :func:`read_warped` uses.

Masks: invalid source pixels (alpha, nodata, internal mask) are zeroed before the
bicubic kernel and the output mask is conservative — valid only where every source
pixel under the 4×4 kernel was valid (as the former align step did).
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.windows import Window

from geosim.errors import RasterError
from geosim.io.raster import (
    band_descriptions,
    create_geotiff,
    image_band_indexes,
    iter_windows,
    read_valid_mask,
)

#: Lattice spacing (destination pixels) on which the composed mapping is evaluated exactly.
LATTICE_PX = 16
#: OpenCV's remap resolution (INTER_TAB_SIZE): sub-pixel positions per pixel.
SUBPIXEL = 32
#: Source pixels read beyond the sampled coordinates (bicubic support is ±2).
PAD_PX = 3
_CV_DTYPES = ("uint8", "uint16", "int16", "float32", "float64")
IDENTITY6 = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)

Field = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def _aff(v: tuple[float, ...] | Affine) -> Affine:
    return v if isinstance(v, Affine) else Affine(*v[:6])


@dataclass(frozen=True)
class ComposedWarp:
    """The composed mapping of one flight onto the site grid (picklable).

    Parameters
    ----------
    src_path
        The original flight raster (any CRS).
    src_crs_wkt, src_transform
        Its CRS (WKT) and affine (6 numbers).
    site_crs_wkt
        The site CRS (WKT).
    grid_transform
        The site UAV grid affine (6 numbers, north-up): anchors the lattice.
    aligned_to_stated
        ``C⁻¹``: aligned-frame map point → the flight's stated map point (site CRS,
        metres); the identity puts the flight on the site grid as stated.
    field
        Optional non-rigid correction in the aligned frame (see the module docstring).
    lattice_px
        Lattice spacing in destination pixels.
    """

    src_path: str
    src_crs_wkt: str
    src_transform: tuple[float, ...]
    site_crs_wkt: str
    grid_transform: tuple[float, ...]
    aligned_to_stated: tuple[float, ...] = IDENTITY6
    field: Field | None = None
    lattice_px: int = LATTICE_PX

    @classmethod
    def for_flight(cls, src_path: str | os.PathLike[str], site_crs: CRS,
                   grid_transform: Affine, *, aligned_to_stated: Affine | None = None,
                   field: Field | None = None) -> ComposedWarp:
        """Read the flight's georeference and build its warp."""
        with rasterio.open(src_path) as src:
            if src.crs is None:
                raise RasterError(f"{src_path} has no CRS; georeference the flight")
            crs_wkt, t = src.crs.to_wkt(), tuple(src.transform)[:6]
        a = aligned_to_stated if aligned_to_stated is not None else Affine.identity()
        return cls(str(src_path), crs_wkt, t, CRS.from_user_input(site_crs).to_wkt(),
                   tuple(grid_transform)[:6], tuple(a)[:6], field)

    def with_correction(self, aligned_to_stated: Affine, field: Field | None = None
                        ) -> ComposedWarp:
        """The same flight with another correction ``C⁻¹`` (and field)."""
        return ComposedWarp(self.src_path, self.src_crs_wkt, self.src_transform,
                            self.site_crs_wkt, self.grid_transform, tuple(aligned_to_stated)[:6],
                            field, self.lattice_px)

    # ------------------------------------------------------------------ the mapping
    def _nodes_to_source(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Aligned-frame map points → source pixel-centre coordinates (col, row)."""
        if self.field is not None:
            x_m, y_m = self.field(x_m, y_m)
        c = _aff(self.aligned_to_stated)
        xs = c.a * x_m + c.b * y_m + c.c
        ys = c.d * x_m + c.e * y_m + c.f
        src_crs, site_crs = CRS.from_wkt(self.src_crs_wkt), CRS.from_wkt(self.site_crs_wkt)
        if src_crs != site_crs:
            from pyproj import Transformer

            tr = Transformer.from_crs(site_crs, src_crs, always_xy=True)
            xs, ys = tr.transform(xs, ys, errcheck=False)
            xs, ys = np.asarray(xs, float), np.asarray(ys, float)
        inv = ~_aff(self.src_transform)
        col = inv.a * xs + inv.b * ys + inv.c - 0.5
        row = inv.d * xs + inv.e * ys + inv.f - 0.5
        return col, row

    def _lattice(self, dst_transform: Affine, shape: tuple[int, int]
                 ) -> tuple[_Bilinear, _Bilinear]:
        """The mapping of a destination window as two lattice interpolants (col, row)."""
        g = _aff(self.grid_transform)
        goff = ~g @ (dst_transform.c, dst_transform.f)
        c0, r0 = round(goff[0]), round(goff[1])
        same_gsd = math.isclose(dst_transform.a, g.a) and math.isclose(dst_transform.e, g.e)
        if abs(goff[0] - c0) > 1e-6 or abs(goff[1] - r0) > 1e-6 or not same_gsd:
            raise ValueError(f"window transform {dst_transform} is not the site grid "
                             f"{g} offset by whole pixels")
        h, w = shape
        lat = self.lattice_px
        uc = np.arange(c0, c0 + w) + 0.5          # global grid centre coordinates
        ur = np.arange(r0, r0 + h) + 0.5
        kc = np.arange(math.floor(uc[0] / lat), math.floor(uc[-1] / lat) + 2)
        kr = np.arange(math.floor(ur[0] / lat), math.floor(ur[-1] / lat) + 2)
        ncol, nrow = np.meshgrid(kc * float(lat), kr * float(lat))
        x_m = g.a * ncol + g.b * nrow + g.c
        y_m = g.d * ncol + g.e * nrow + g.f
        scol, srow = self._nodes_to_source(x_m, y_m)
        tc, tr = uc / lat - kc[0], ur / lat - kr[0]
        return _Bilinear.of(scol, tc, tr), _Bilinear.of(srow, tc, tr)

    def source_coords(self, dst_transform: Affine, shape: tuple[int, int]
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Source pixel-centre coordinates of every pixel of a destination window.

        Parameters
        ----------
        dst_transform
            Affine of the window: the site grid's offset by whole pixels.
        shape
            ``(rows, cols)`` of the window.

        Returns
        -------
        (col, row)
            float64 arrays ``(rows, cols)``: source column and row of each destination
            pixel centre (pixel centres at integers); NaN where the projection fails.
        """
        bc, br = self._lattice(dst_transform, shape)
        return bc.rows(0, shape[0]), br.rows(0, shape[0])


@dataclass(frozen=True)
class _Bilinear:
    """Separable bilinear interpolation of lattice nodes, evaluated a strip of rows at a time.

    ``along`` holds the nodes interpolated along the columns (node rows × window columns),
    ``step`` its differences between node rows; a pixel's value is
    ``along[ir] + fr · step[ir]``: the same arithmetic whichever rows are asked together.
    """

    along: np.ndarray
    step: np.ndarray
    ir: np.ndarray
    fr: np.ndarray
    #: Every node finite (then so is every interpolated value).
    finite: bool

    @classmethod
    def of(cls, nodes: np.ndarray, tc: np.ndarray, tr: np.ndarray) -> _Bilinear:
        """Interpolant of ``nodes`` at fractional node indexes ``tc`` (cols), ``tr`` (rows)."""
        ic = np.minimum(np.floor(tc).astype(np.intp), nodes.shape[1] - 2)
        ir = np.minimum(np.floor(tr).astype(np.intp), nodes.shape[0] - 2)
        fc, fr = tc - ic, tr - ir
        along = nodes[:, ic] * (1.0 - fc) + nodes[:, ic + 1] * fc      # (node rows, cols)
        return cls(along, np.diff(along, axis=0), ir, fr, bool(np.isfinite(nodes).all()))

    def rows(self, start: int, stop: int) -> np.ndarray:
        """float64 values of the window rows ``start:stop`` (every column)."""
        ir = self.ir[start:stop]
        out = self.step[ir]                                           # a row gather: a copy
        out *= self.fr[start:stop, None]
        out += self.along[ir]
        return out


# --------------------------------------------------------------------------- pure kernel


def _fixed_maps(col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's fixed-point maps (1/32 px) of float source coordinates (NaN = outside)."""
    mx = np.asarray(col, dtype=np.float32)
    my = np.asarray(row, dtype=np.float32)
    bad = ~(np.isfinite(mx) & np.isfinite(my))
    if bad.any():
        mx, my = np.where(bad, -16.0, mx).astype(np.float32), np.where(bad, -16.0, my).astype(
            np.float32)
    return cv2.convertMaps(mx, my, cv2.CV_16SC2)      # once for all bands (1/32 px, as cv2)


def _remap_mask(valid: np.ndarray, m1: np.ndarray, m2: np.ndarray) -> np.ndarray:
    """Conservative output mask: every source pixel under the 4×4 bicubic kernel valid."""
    core = valid.astype(np.uint8) * 255
    if not valid.all():
        core = cv2.erode(core, np.ones((3, 3), np.uint8))
    return cv2.remap(core, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0) == 255


def remap_window(image: np.ndarray, valid: np.ndarray, col: np.ndarray, row: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Bicubic resampling of a source block at given coordinates (pure).

    Parameters
    ----------
    image
        ``(bands, rows, cols)`` source block, any real dtype. Its invalid pixels are
        set to 0 in place when it is contiguous in a type OpenCV remaps.
    valid
        ``(rows, cols)`` bool source mask.
    col, row
        Destination-shaped source pixel-centre coordinates *relative to the block*
        (NaN = outside).

    Returns
    -------
    (image, valid)
        Output in the input dtype (integers rounded and saturated; 0 where invalid) and
        a conservative mask (every source pixel under the 4×4 kernel valid).
    """
    return remap_fixed(image, valid, *_fixed_maps(col, row))


def remap_fixed(image: np.ndarray, valid: np.ndarray, m1: np.ndarray, m2: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`remap_window` with OpenCV's fixed-point maps (``CV_16SC2`` + ``CV_16UC1``)."""
    dtype = image.dtype
    work = dtype if dtype.name in _CV_DTYPES else np.dtype(np.float64)
    out = np.empty((image.shape[0], *m2.shape), dtype=work)
    invalid = None if valid.all() else ~valid
    for b in range(image.shape[0]):
        src = np.ascontiguousarray(image[b], dtype=work)
        if invalid is not None:
            src[invalid] = 0
        cv2.remap(src, m1, m2, cv2.INTER_CUBIC, dst=out[b], borderMode=cv2.BORDER_CONSTANT,
                  borderValue=0)
    ok = _remap_mask(valid, m1, m2)
    if work != dtype:
        info = np.iinfo(dtype)
        out = np.clip(np.rint(out), info.min, info.max).astype(dtype)
    out[:, ~ok] = 0
    return out, ok


# --------------------------------------------------------------------------- I/O


def source_window(col: np.ndarray, row: np.ndarray, width: int, height: int,
                  pad_px: int = PAD_PX) -> Window | None:
    """Source window covering the finite coordinates plus the kernel pad (None: outside)."""
    fin = np.isfinite(col) & np.isfinite(row)
    if not fin.any():
        return None
    return _padded_window(float(col[fin].min()), float(col[fin].max()),
                          float(row[fin].min()), float(row[fin].max()), width, height, pad_px)


def _padded_window(col_min: float, col_max: float, row_min: float, row_max: float,
                   width: int, height: int, pad_px: int = PAD_PX) -> Window | None:
    c0 = max(0, math.floor(col_min) - pad_px)
    r0 = max(0, math.floor(row_min) - pad_px)
    c1 = min(width, math.ceil(col_max) + pad_px + 1)
    r1 = min(height, math.ceil(row_max) + pad_px + 1)
    if c1 <= c0 or r1 <= r0:
        return None
    return Window(c0, r0, c1 - c0, r1 - r0)


def _window_coords(warp: ComposedWarp, dst_transform: Affine, shape: tuple[int, int],
                   src: rasterio.DatasetReader
                   ) -> tuple[Window, np.ndarray, np.ndarray] | None:
    """Source window and window-relative float32 coordinates of a destination window."""
    col, row = warp.source_coords(dst_transform, shape)
    swin = source_window(col, row, src.width, src.height)
    if swin is None:
        return None
    # OpenCV samples at 1/32 px; quantising the global coordinates first makes the
    # window-relative float32 maps exact, so the bits do not depend on the window
    maps = []
    for a, off in ((col, swin.col_off), (row, swin.row_off)):
        a *= SUBPIXEL
        np.rint(a, out=a)
        a -= off * SUBPIXEL
        a *= 1.0 / SUBPIXEL
        maps.append(a.astype(np.float32))
    return swin, maps[0], maps[1]


#: Destination rows per strip of :func:`_window_maps`: its float64 temporaries (2 × 32 rows
#: × the window's columns) stay in the CPU's cache instead of streaming through memory.
STRIP_ROWS = 32
#: Largest |source coordinate| (px) of the strip path: quantised, it fits an int32 and, window
#: relative, a float32 exactly (beyond it the whole-window path :func:`_window_coords` runs).
_STRIP_MAX_PX = 2.0 ** 18


def _window_maps(warp: ComposedWarp, dst_transform: Affine, shape: tuple[int, int],
                 src: rasterio.DatasetReader
                 ) -> tuple[Window, np.ndarray, np.ndarray] | None:
    """Source window and OpenCV's fixed-point maps of a destination window.

    The same window and maps as :func:`_window_coords` followed by :func:`_fixed_maps`
    (tested bit for bit), computed a strip of rows at a time: the coordinates are
    evaluated, bounded and quantised to 1/32 px per strip (``int32``), and the maps made
    from the integers as ``cv2.convertMaps`` does (``m1 = q >> 5``, ``m2 = (qy & 31) · 32 +
    (qx & 31)``), with no whole-window float64 or float32 coordinate array.
    """
    h, w = shape
    bc, br = warp._lattice(dst_transform, shape)
    finite = bc.finite and br.finite
    qc, qr = np.empty(shape, np.int32), np.empty(shape, np.int32)
    bad = None if finite else np.zeros(shape, dtype=bool)
    lo_c = lo_r = math.inf
    hi_c = hi_r = -math.inf
    for a in range(0, h, STRIP_ROWS):
        b = min(h, a + STRIP_ROWS)
        c, r = bc.rows(a, b), br.rows(a, b)
        if finite:
            ok = None
        else:
            ok = np.isfinite(c) & np.isfinite(r)
            bad[a:b] = ~ok
            if not ok.any():
                continue
        lo, hi = (c.min(), c.max()) if ok is None else (c[ok].min(), c[ok].max())
        lo_c, hi_c = min(lo_c, float(lo)), max(hi_c, float(hi))
        lo, hi = (r.min(), r.max()) if ok is None else (r[ok].min(), r[ok].max())
        lo_r, hi_r = min(lo_r, float(lo)), max(hi_r, float(hi))
        if max(-lo_c, hi_c, -lo_r, hi_r) >= _STRIP_MAX_PX:
            found = _window_coords(warp, dst_transform, shape, src)
            return None if found is None else (found[0], *_fixed_maps(found[1], found[2]))
        for v, q in ((c, qc), (r, qr)):
            if ok is not None:
                v[~ok] = 0.0                     # placeholders: replaced below
            v *= SUBPIXEL
            np.rint(v, out=v)
            q[a:b] = v
    if lo_c > hi_c:
        return None
    swin = _padded_window(lo_c, hi_c, lo_r, hi_r, src.width, src.height)
    if swin is None:
        return None
    # window-relative whole pixels saturate to int16 in cv2.convertMaps; here they fit
    # (the window spans the coordinates), so no clipping is needed: checked, not assumed
    span = max(hi_c - swin.col_off, hi_r - swin.row_off, swin.col_off - lo_c,
               swin.row_off - lo_r, 16.0)
    if span >= 32767 or sys.byteorder != "little":
        found = _window_coords(warp, dst_transform, shape, src)
        return None if found is None else (found[0], *_fixed_maps(found[1], found[2]))
    m1 = np.empty((h, w, 2), np.int16)
    pairs = m1.view(np.int32)[..., 0]            # (x, y) int16 pairs as one little-endian int32
    m2 = np.empty(shape, np.uint16)
    for a in range(0, h, STRIP_ROWS):
        b = min(h, a + STRIP_ROWS)
        ix = qc[a:b] - np.int32(swin.col_off * SUBPIXEL)
        iy = qr[a:b] - np.int32(swin.row_off * SUBPIXEL)
        if bad is not None:                     # outside: (-16, -16) px, as _fixed_maps
            ix[bad[a:b]] = iy[bad[a:b]] = -16 * SUBPIXEL
        m2[a:b] = ((iy & (SUBPIXEL - 1)) * SUBPIXEL) | (ix & (SUBPIXEL - 1))
        ix >>= 5
        ix &= 0xFFFF
        iy >>= 5
        iy <<= 16
        iy |= ix
        pairs[a:b] = iy
    return swin, m1, m2


def read_warped(warp: ComposedWarp, dst_transform: Affine, shape: tuple[int, int], *,
                src: rasterio.DatasetReader | None = None,
                bands: list[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One destination window of a flight through its composed warp.

    Parameters
    ----------
    warp
        The flight's composed mapping.
    dst_transform, shape
        The window (site grid offset by whole pixels) and its ``(rows, cols)``.
    src
        The open source dataset (opened here when None).
    bands
        Source bands (default: the image bands, alpha dropped).

    Returns
    -------
    (image, valid)
        ``(bands, rows, cols)`` in the source dtype and the ``(rows, cols)`` mask.
    """
    if src is None:
        with rasterio.open(warp.src_path) as ds:
            return read_warped(warp, dst_transform, shape, src=ds, bands=bands)
    bands = bands or image_band_indexes(src)
    found = _window_maps(warp, dst_transform, shape, src)
    if found is None:
        return (np.zeros((len(bands), *shape), dtype=src.dtypes[bands[0] - 1]),
                np.zeros(shape, dtype=bool))
    swin, m1, m2 = found
    image = src.read(bands, window=swin)
    valid = read_valid_mask(src, window=swin)
    return remap_fixed(image, valid, m1, m2)


def read_warped_valid(warp: ComposedWarp, dst_transform: Affine, shape: tuple[int, int], *,
                      src: rasterio.DatasetReader) -> np.ndarray:
    """The mask :func:`read_warped` gives for a window, without resampling the image."""
    found = _window_maps(warp, dst_transform, shape, src)
    if found is None:
        return np.zeros(shape, dtype=bool)
    swin, m1, m2 = found
    return _remap_mask(read_valid_mask(src, window=swin), m1, m2)


@dataclass(frozen=True)
class WarpRasterTask:
    """Write one flight through its composed warp onto a grid window, as a GeoTIFF."""

    warp: ComposedWarp
    dst_path: str
    dst_transform: tuple[float, ...]     # site grid offset by whole pixels
    shape: tuple[int, int]               # (rows, cols)
    block_px: int = 2048
    tags: Mapping[str, str] = field(default_factory=dict)
    what: str = "flight"


@dataclass(frozen=True)
class WarpRasterRecord:
    """What :func:`warp_raster_task` wrote."""

    path: str
    valid_px: int
    bands: int
    dtype: str
    source_crs: str


def warp_raster_task(task: WarpRasterTask) -> WarpRasterRecord:
    """Resample a flight once onto ``task``'s grid window, block by block (engine task).

    Memory: one destination block (``block_px``²), its coordinates and the source
    window under it.
    """
    from geosim.prepare.reproject import SUPPORTED_DTYPES

    # OpenCV's threads: the task's budget, set by the engine (geosim.engine.task_limits)
    rows, cols = task.shape
    t = _aff(task.dst_transform)
    with rasterio.open(task.warp.src_path) as src:
        bands = image_band_indexes(src)
        if not bands:
            raise RasterError(f"{task.what}: {task.warp.src_path} has no image band (only "
                              "alpha); give an RGB(A) or grey raster")
        dtypes = {src.dtypes[b - 1] for b in bands}
        if len(dtypes) != 1 or not dtypes <= set(SUPPORTED_DTYPES):
            raise RasterError(f"{task.what}: {task.warp.src_path} has data type(s) "
                              f"{sorted(dtypes)}; use one of {SUPPORTED_DTYPES} for all bands")
        dtype = dtypes.pop()
        valid_px = 0
        with create_geotiff(task.dst_path, width=cols, height=rows, count=len(bands),
                            dtype=dtype, crs=CRS.from_wkt(task.warp.site_crs_wkt), transform=t,
                            band_descriptions=band_descriptions(src, bands),
                            # (no NUM_THREADS: GDAL's threaded writer orders blocks
                            # differently, and files must not depend on the machine)
                            tags=dict(task.tags), internal_mask=True) as dst:
            dst.colorinterp = [src.colorinterp[b - 1] for b in bands]
            for win in iter_windows(cols, rows, block_px=task.block_px):
                wt = t @ Affine.translation(int(win.col_off), int(win.row_off))
                out, ok = read_warped(task.warp, wt, (int(win.height), int(win.width)),
                                      src=src, bands=bands)
                dst.write(out, window=win)
                dst.write_mask(ok.astype(np.uint8) * 255, window=win)
                valid_px += int(ok.sum())
        source_crs = src.crs.to_string()
    return WarpRasterRecord(str(task.dst_path), valid_px, len(bands), dtype, source_crs)


def read_grey_warped(warp: ComposedWarp, dst_transform: Affine, shape: tuple[int, int], *,
                     src: rasterio.DatasetReader | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Grey level (BT.601 luma, float32) and mask of a destination window through ``warp``.

    The same pixels as the window of the raster :func:`warp_raster_task` writes for
    ``warp`` (e.g. a globally aligned flight), without writing it.
    """
    from geosim.align.phasecorr import as_grey

    if src is None:
        with rasterio.open(warp.src_path) as ds:
            return read_grey_warped(warp, dst_transform, shape, src=ds)
    bands = image_band_indexes(src)
    bands = bands[:3] if len(bands) >= 3 else bands[:1]
    img, valid = read_warped(warp, dst_transform, shape, src=src, bands=bands)
    return as_grey(img), valid


@dataclass(frozen=True)
class WarpedGreyReader:
    """Picklable ``window -> (grey, valid)`` of a flight through its warp onto a grid window.

    ``transform`` is the destination raster's affine (the site grid offset by whole pixels);
    windows are in its pixels.
    """

    warp: ComposedWarp
    transform: tuple[float, ...]

    def __call__(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        t = _aff(self.transform) @ Affine.translation(int(window.col_off), int(window.row_off))
        return read_grey_warped(self.warp, t, (int(window.height), int(window.width)))


def read_grey_on_grid(warp: ComposedWarp, window: Window) -> tuple[np.ndarray, np.ndarray]:
    """Grey level (BT.601 luma, float32) and mask of a site-grid window, read on the fly.

    Replaces reading ``grid/<flight>.tif`` for registration: the same composed warp
    with the identity correction.
    """
    g = _aff(warp.grid_transform)
    t = g @ Affine.translation(int(window.col_off), int(window.row_off))
    return read_grey_warped(warp.with_correction(Affine.identity()), t,
                            (int(window.height), int(window.width)))


def describe(warp: ComposedWarp) -> dict[str, Any]:
    """JSON-able description of a composed warp (for provenance)."""
    return {"source": warp.src_path, "aligned_to_stated": list(warp.aligned_to_stated),
            "field": None if warp.field is None else repr(warp.field),
            "lattice_px": warp.lattice_px, "kernel": "bicubic (OpenCV, a = -0.75), once"}
