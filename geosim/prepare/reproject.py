"""Reproject any raster onto a grid of the site, window by window.

Imagery is resampled with bicubic (default) or Lanczos; the valid-data mask
(alpha band, nodata value or GDAL internal mask of the input, see
:func:`geosim.io.raster.read_valid_mask`) is resampled with nearest neighbour.
Invalid source pixels are excluded from the imagery kernel (GDAL renormalises
the weights), so no nodata value bleeds into valid pixels.

The output keeps the input's data type (8- or 16-bit, or float), drops the alpha
band and stores validity as a GDAL internal mask; invalid pixels are 0.

Memory: one destination window (``block_px``², default 2048²) and the source
window that covers it are in memory at a time, never the whole raster.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.enums import Resampling
from rasterio.warp import reproject, transform_bounds
from rasterio.windows import Window
from rasterio.windows import bounds as window_bounds
from tqdm import tqdm

from geosim.errors import RasterError
from geosim.io.raster import (
    RasterData,
    band_descriptions,
    create_geotiff,
    image_band_indexes,
    open_raster,
    read_valid_mask,
)

SUPPORTED_DTYPES = ("uint8", "uint16", "int16", "uint32", "int32", "float32", "float64")
_RESAMPLING = {"bicubic": Resampling.cubic, "cubic": Resampling.cubic,
               "lanczos": Resampling.lanczos, "bilinear": Resampling.bilinear,
               "nearest": Resampling.nearest}


#: GDAL warp memory per call, MB: with windowed calls this bounds a warp's working set.
WARP_MEM_LIMIT_MB = 256


def warp_threads() -> int:
    """Threads for one GDAL warp or block decode: the running task's budget
    (:func:`geosim.engine.task_threads`: 1 in a task on any engine and in the command's
    own work under ``--workers 1``, every core in a library call, ``GEOSIM_THREADS`` when
    set)."""
    from geosim.engine import task_threads

    return task_threads()


def resampling_method(name: str) -> Resampling:
    """GDAL resampling for a name (``bicubic``, ``lanczos``, ``bilinear``, ``nearest``)."""
    try:
        return _RESAMPLING[name.lower()]
    except KeyError:
        raise RasterError(f"resampling {name!r} is not supported; use one of "
                          f"{sorted(_RESAMPLING)}") from None


def dataset_corner_bounds(ds: rasterio.DatasetReader) -> tuple[float, float, float, float]:
    """Bounding box of a dataset's four pixel-grid corners in its own CRS (rotation-safe)."""
    t = ds.transform
    xs, ys = zip(*(t @ (c, r) for c, r in ((0, 0), (ds.width, 0), (0, ds.height),
                                            (ds.width, ds.height))), strict=True)
    return min(xs), min(ys), max(xs), max(ys)


def bounds_in_crs(ds: rasterio.DatasetReader, crs: CRS | str) -> tuple[float, float, float, float]:
    """Extent of a dataset in another CRS (edges densified, so curved edges are covered)."""
    return tuple(transform_bounds(ds.crs, crs, *dataset_corner_bounds(ds), densify_pts=21))


def source_window_for(src: rasterio.DatasetReader, dst_crs: CRS, dst_bounds: tuple,
                      *, pad_px: int = 4) -> Window | None:
    """Window of ``src`` that covers ``dst_bounds`` (in ``dst_crs``) plus a kernel margin.

    Returns ``None`` when they do not overlap.
    """
    try:
        sb = transform_bounds(dst_crs, src.crs, *dst_bounds, densify_pts=21)
    except Exception:  # outside the projection's domain
        return None
    if not all(map(math.isfinite, sb)):
        return None
    inv = ~src.transform
    cols, rows = zip(*(inv @ (x, y) for x, y in ((sb[0], sb[1]), (sb[0], sb[3]),
                                                  (sb[2], sb[1]), (sb[2], sb[3]))), strict=True)
    c0 = max(0, math.floor(min(cols)) - pad_px)
    r0 = max(0, math.floor(min(rows)) - pad_px)
    c1 = min(src.width, math.ceil(max(cols)) + pad_px)
    r1 = min(src.height, math.ceil(max(rows)) + pad_px)
    if c1 <= c0 or r1 <= r0:
        return None
    return Window(c0, r0, c1 - c0, r1 - r0)


def reproject_window(image: np.ndarray, valid: np.ndarray, *, src_transform: Affine,
                     src_crs: CRS, dst_transform: Affine, dst_crs: CRS,
                     dst_shape: tuple[int, int], resampling: Resampling = Resampling.cubic,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Reproject one in-memory window (pure: arrays in, arrays out).

    Parameters
    ----------
    image
        Source pixels, ``(bands, rows, cols)``, any real dtype.
    valid
        Source valid mask ``(rows, cols)``, True = valid.
    src_transform, src_crs
        Georeference of ``image``.
    dst_transform, dst_crs, dst_shape
        Destination grid: affine, CRS and ``(rows, cols)``.
    resampling
        Kernel for the imagery; the mask always uses nearest neighbour.

    Returns
    -------
    (image, valid)
        Destination pixels ``(bands, rows, cols)`` in the input dtype (rounded and
        clipped to its range for integers; 0 where invalid) and the destination mask.
    """
    dtype = image.dtype
    src = image.astype(np.float32, copy=True)
    src[:, ~valid] = np.nan
    dst = np.full((image.shape[0], *dst_shape), np.nan, dtype=np.float32)
    reproject(src, dst, src_transform=src_transform, src_crs=src_crs, src_nodata=np.nan,
              dst_transform=dst_transform, dst_crs=dst_crs, dst_nodata=np.nan,
              resampling=resampling, num_threads=warp_threads(),
              warp_mem_limit=WARP_MEM_LIMIT_MB)
    dst_valid = np.zeros(dst_shape, dtype=np.uint8)
    reproject(valid.astype(np.uint8), dst_valid, src_transform=src_transform, src_crs=src_crs,
              src_nodata=None, dst_transform=dst_transform, dst_crs=dst_crs, dst_nodata=None,
              resampling=Resampling.nearest, num_threads=warp_threads(),
              warp_mem_limit=WARP_MEM_LIMIT_MB)
    ok = (dst_valid > 0) & np.all(np.isfinite(dst), axis=0)
    dst[:, ~ok] = 0
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        dst = np.clip(np.rint(dst), info.min, info.max)
    return dst.astype(dtype), ok


def reproject_to_grid(src_path: str | os.PathLike[str], dst_path: str | os.PathLike[str], *,
                      crs: CRS, transform: Affine, shape: tuple[int, int],
                      resampling: str = "bicubic", block_px: int = 2048,
                      what: str = "raster", tags: Mapping[str, str] | None = None,
                      progress: bool | None = None) -> dict[str, Any]:
    """Reproject a raster file onto a grid, window by window, keeping its valid mask.

    Parameters
    ----------
    src_path
        Input raster in any CRS (projected, Web/World Mercator, lon/lat), 8/16-bit or
        float, RGB or RGBA; its mask comes from alpha, nodata or an internal mask.
    dst_path
        Output GeoTIFF (tiled, deflate, internal mask), written atomically.
    crs, transform, shape
        Destination grid: CRS, affine and ``(rows, cols)``.
    resampling
        ``bicubic`` (default) or ``lanczos`` for the imagery.
    block_px
        Destination window side in pixels (memory bound).
    what
        Name of the input in error messages (``"flight PA1"``).
    tags
        Provenance tags for the output.
    progress
        tqdm ``disable`` is ``not progress``; ``None`` = show on a TTY only.

    Returns
    -------
    dict
        ``valid_px`` (valid output pixels), ``bands``, ``dtype``, ``source_crs``.
    """
    kernel = resampling_method(resampling)
    rows, cols = shape
    with open_raster(src_path, what=what) as src:
        bands = image_band_indexes(src)
        if not bands:
            raise RasterError(f"{what}: {src_path} has no image band (only alpha); give an "
                              "RGB(A) or grey raster")
        dtype = src.dtypes[bands[0]- 1]
        if dtype not in SUPPORTED_DTYPES or len({src.dtypes[b - 1] for b in bands}) != 1:
            raise RasterError(f"{what}: {src_path} has data type(s) "
                              f"{sorted({src.dtypes[b - 1] for b in bands})}; use one of "
                              f"{SUPPORTED_DTYPES} for all bands")
        descriptions = band_descriptions(src, bands)
        colorinterp = [src.colorinterp[b - 1] for b in bands]
        valid_px = 0
        windows = list(_iter_windows(cols, rows, block_px))
        with create_geotiff(dst_path, width=cols, height=rows, count=len(bands), dtype=dtype,
                            crs=crs, transform=transform, band_descriptions=descriptions,
                            tags=tags, internal_mask=True) as dst:
            dst.colorinterp = colorinterp
            for win in tqdm(windows, desc=f"reproject {what}", unit="block",
                            disable=None if progress is None else not progress, leave=False):
                h, w = int(win.height), int(win.width)
                dst_t = transform @ Affine.translation(int(win.col_off), int(win.row_off))
                swin = source_window_for(src, crs, window_bounds(win, transform))
                if swin is None:
                    out = np.zeros((len(bands), h, w), dtype=dtype)
                    ok = np.zeros((h, w), dtype=bool)
                else:
                    image = src.read(bands, window=swin)
                    valid = read_valid_mask(src, window=swin)
                    if not valid.any():
                        out = np.zeros((len(bands), h, w), dtype=dtype)
                        ok = np.zeros((h, w), dtype=bool)
                    else:
                        out, ok = reproject_window(
                            image, valid, src_transform=src.window_transform(swin),
                            src_crs=src.crs, dst_transform=dst_t, dst_crs=crs,
                            dst_shape=(h, w), resampling=kernel)
                dst.write(out, window=win)
                dst.write_mask(ok.astype(np.uint8) * 255, window=win)
                valid_px += int(ok.sum())
        source_crs = src.crs.to_string()
    return {"path": str(Path(dst_path)), "valid_px": valid_px, "bands": len(bands),
            "dtype": dtype, "source_crs": source_crs}


def _iter_windows(width: int, height: int, block_px: int):
    from geosim.io.raster import iter_windows

    return iter_windows(width, height, block_px=block_px)


def reproject_to_array(src_path: str | os.PathLike[str], *, crs: CRS, transform: Affine,
                       shape: tuple[int, int], max_bands: int | None = None,
                       resampling: str = "bicubic", what: str = "raster") -> RasterData:
    """Reproject a raster file onto a (small) grid held in memory, as float32.

    The same regridding as :func:`reproject_to_grid` (:func:`reproject_window`: invalid
    source pixels excluded from the kernel, nearest-neighbour mask), for callers that need
    the pixels rather than a file (e.g. standalone diagnosis); values are not rounded.

    Returns
    -------
    RasterData
        ``array`` ``(bands, rows, cols)`` float32 (0 where invalid), ``valid`` the
        ``(rows, cols)`` mask, on the grid ``transform`` / ``crs``, with the source's band
        descriptions.
    """
    rows, cols = shape
    with open_raster(src_path, what=what) as src:
        bands = image_band_indexes(src)[:max_bands]
        names = tuple(src.descriptions[i - 1] for i in bands)
        swin = source_window_for(src, crs, window_bounds(Window(0, 0, cols, rows), transform))
        if swin is None:
            image = np.zeros((len(bands), rows, cols), np.float32)
            valid = np.zeros((rows, cols), dtype=bool)
        else:
            image, valid = reproject_window(
                src.read(bands, window=swin).astype(np.float32),
                read_valid_mask(src, window=swin), src_transform=src.window_transform(swin),
                src_crs=src.crs, dst_transform=transform, dst_crs=crs,
                dst_shape=(rows, cols), resampling=resampling_method(resampling))
    return RasterData(array=image, valid=valid, transform=transform, crs=CRS.from_user_input(crs),
                      band_names=names, path=Path(src_path))
