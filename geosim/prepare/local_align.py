"""Local co-registration in the pipeline (``parameters.align_model = "local"``).

The pure estimation is :mod:`geosim.align.field`; this module adapts it to rasters:

* :func:`measure_local_shifts` — window shifts between two aligned rasters, read strip by
  strip (memory bounded by ``window_px`` × a column chunk);
* :func:`sample_points` — for the pixel centres of any destination window (given its
  transform), the map points of the *globally corrected* flight to sample: ``p + D(p)``.
  This is the seam a composed, windowed resampler calls per output window;
* :func:`apply_local_alignment` — resample a gridded flight onto the aligned grid once,
  through the composed mapping (aligned point → field → global correction → grid pixel),
  window by window with ``cv2.remap``;
* :func:`write_field_geotiff` / :func:`read_field_geotiff` — the field as a 2-band GeoTIFF
  (``dx_m``, ``dy_m``; the mask marks where it was estimated, masked nodes keep the global
  model), and :func:`move_points` for labels.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window
from tqdm import tqdm

from geosim.align.field import (
    UNMEASURED,
    DisplacementField,
    WindowShifts,
    measure_window_shifts,
)
from geosim.align.local import window_starts
from geosim.errors import InputFileError
from geosim.io.raster import create_geotiff, iter_windows, read_valid_mask, write_geotiff
from geosim.prepare.alignment import read_grey_window

#: Window side and step (UAV px) of the local field's phase correlation.
LOCAL_FIELD_WINDOW_PX = 256
LOCAL_FIELD_STEP_PX = 128

FIELD_BANDS = ("dx_m", "dy_m")


# --------------------------------------------------------------------------- measuring


def measure_local_shifts(ref_path: str | os.PathLike[str], mov_path: str | os.PathLike[str], *,
                         window_px: int = LOCAL_FIELD_WINDOW_PX,
                         step_px: int = LOCAL_FIELD_STEP_PX, windows_per_chunk: int = 16,
                         progress: bool | None = None, what: str = "flight") -> WindowShifts:
    """Window shifts between two rasters on the same grid, over their whole extent.

    Rows of windows are read as strips of ``window_px`` rows, in column chunks of
    ``windows_per_chunk`` windows, so memory does not grow with the raster.

    Returns
    -------
    WindowShifts
        Centres in the rasters' pixel-centre coordinates; every window ``accepted`` or
        ``unmeasured`` (apply :func:`geosim.align.field.reject_outliers` next).
    """
    with rasterio.open(ref_path) as ds:
        width, height = ds.width, ds.height
    sr = window_starts(height, window_px, step_px)
    sc = window_starts(width, window_px, step_px)
    shape = (len(sr), len(sc))
    dx = np.full(shape, np.nan)
    dy = np.full(shape, np.nan)
    conf = np.zeros(shape)
    chunks = [sc[k:k + windows_per_chunk] for k in range(0, len(sc), windows_per_chunk)]
    jobs = [(i, k) for i in range(len(sr)) for k in range(len(chunks))]
    for i, k in tqdm(jobs, desc=f"local field {what}", unit="strip", leave=False,
                     disable=None if progress is None else not progress):
        starts = chunks[k]
        c0 = int(starts[0])
        win = Window(c0, int(sr[i]), int(starts[-1]) - c0 + window_px, window_px)
        rg, rv = read_grey_window(ref_path, win)
        mg, mv = read_grey_window(mov_path, win)
        if not (rv & mv).any():
            continue
        s = measure_window_shifts(rg, mg, valid=rv & mv, window_px=window_px, step_px=step_px)
        j0 = k * windows_per_chunk
        n = s.dx_px.shape[1]
        dx[i, j0:j0 + n] = s.dx_px[0]
        dy[i, j0:j0 + n] = s.dy_px[0]
        conf[i, j0:j0 + n] = s.confidence[0]
    half = (window_px - 1) / 2.0
    yy, xx = np.meshgrid(sr + half, sc + half, indexing="ij")
    status = np.where(np.isfinite(dx), 0, UNMEASURED).astype(np.int8)
    return WindowShifts(xx.astype(float), yy.astype(float), dx, dy, conf, status,
                        int(window_px), int(step_px))


# --------------------------------------------------------------------------- applying


def pixel_centres(dst_transform: Affine, shape: tuple[int, int]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Map coordinates of every pixel centre of a (north-up or not) destination window."""
    rows, cols = shape
    c, r = np.meshgrid(np.arange(cols) + 0.5, np.arange(rows) + 0.5)
    t = dst_transform
    return t.a * c + t.b * r + t.c, t.d * c + t.e * r + t.f


def sample_points(field: DisplacementField | None, dst_transform: Affine,
                  shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Where to sample the globally corrected flight for each destination pixel centre.

    Parameters
    ----------
    field
        The flight's local field (``None``: the identity, i.e. the global model).
    dst_transform, shape
        Transform and ``(rows, cols)`` of the destination window (aligned frame).

    Returns
    -------
    tuple of numpy.ndarray
        ``(x_m, y_m)`` map coordinates of shape ``shape``: ``p + D(p)``. Apply the inverse
        global correction (and the source CRS transform) to them to reach source pixels.
    """
    x, y = pixel_centres(dst_transform, shape)
    return (x, y) if field is None else field.apply(x, y)


def remap_block(image: np.ndarray, valid: np.ndarray, map_x: np.ndarray, map_y: np.ndarray, *,
                interpolation: int = cv2.INTER_CUBIC) -> tuple[np.ndarray, np.ndarray]:
    """Resample one block at per-pixel source positions (pixel centres at integers).

    Parameters
    ----------
    image
        ``(bands, rows, cols)`` source block.
    valid
        ``(rows, cols)`` bool source mask.
    map_x, map_y
        ``(out_rows, out_cols)`` source column / row of each output pixel (float32).

    Returns
    -------
    (image, valid)
        Output pixels (input dtype, 0 where invalid) and a conservative mask: valid only
        where every source pixel under the bicubic kernel was valid.
    """
    mx = np.ascontiguousarray(map_x, dtype=np.float32)
    my = np.ascontiguousarray(map_y, dtype=np.float32)
    bands = [cv2.remap(np.ascontiguousarray(image[b]), mx, my, interpolation,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0)
             for b in range(image.shape[0])]
    out = np.stack(bands)
    core = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) if not valid.all() \
        else valid.astype(np.uint8)
    mw = cv2.remap(core.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                   borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    ok = mw >= 0.999
    out[:, ~ok] = 0
    return out, ok


def _source_coords(field: DisplacementField, m_grid: np.ndarray, grid_transform: Affine,
                   gwin: Window) -> tuple[np.ndarray, np.ndarray]:
    """Grid corner coordinates of the flight to sample for each pixel of ``gwin``."""
    dst_t = grid_transform * Affine.translation(gwin.col_off, gwin.row_off)
    x, y = sample_points(field, dst_t, (int(gwin.height), int(gwin.width)))
    inv = ~grid_transform
    gc = inv.a * x + inv.b * y + inv.c
    gr = inv.d * x + inv.e * y + inv.f
    m = np.asarray(m_grid, dtype=float)
    return m[0, 0] * gc + m[0, 1] * gr + m[0, 2], m[1, 0] * gc + m[1, 1] * gr + m[1, 2]


def apply_local_alignment(src_path: str | os.PathLike[str], dst_path: str | os.PathLike[str], *,
                          m_grid: np.ndarray, field: DisplacementField, out_window: Window,
                          block_px: int = 2048, tags: Mapping[str, str] | None = None,
                          what: str = "flight", progress: bool | None = None
                          ) -> dict[str, Any]:
    """Resample a gridded flight onto the aligned grid through global correction + field.

    One interpolation per pixel: aligned pixel centre ``p`` → ``p + D(p)`` (field) →
    ``m_grid`` (global correction, grid corner coordinates) → source pixel; bicubic,
    window by window, conservative mask (as :func:`geosim.prepare.alignment.apply_alignment`).

    Returns
    -------
    dict
        ``path``, ``valid_px``.
    """
    valid_px = 0
    with rasterio.open(src_path) as src:
        gt = src.transform
        # the field moves sources by at most its largest displacement: pad the read by it
        pad = 4 + int(math.ceil(float(field.magnitude_m().max(initial=0.0)) / abs(gt.a)))
        grid_shape = (src.height, src.width)
        transform = gt * Affine.translation(int(out_window.col_off), int(out_window.row_off))
        with create_geotiff(dst_path, width=int(out_window.width), height=int(out_window.height),
                            count=src.count, dtype=src.dtypes[0], crs=src.crs,
                            transform=transform, band_descriptions=[
                                d or f"band {i}" for i, d in enumerate(src.descriptions, 1)],
                            tags=tags, internal_mask=True) as dst:
            dst.colorinterp = list(src.colorinterp)
            blocks = list(iter_windows(int(out_window.width), int(out_window.height),
                                       block_px=block_px))
            for blk in tqdm(blocks, desc=f"align {what} (local)", unit="block", leave=False,
                            disable=None if progress is None else not progress):
                gwin = Window(out_window.col_off + blk.col_off, out_window.row_off + blk.row_off,
                              blk.width, blk.height)
                h, w = int(blk.height), int(blk.width)
                sx, sy = _source_coords(field, m_grid, gt, gwin)
                c0 = max(0, math.floor(float(sx.min())) - pad)
                r0 = max(0, math.floor(float(sy.min())) - pad)
                c1 = min(grid_shape[1], math.ceil(float(sx.max())) + pad)
                r1 = min(grid_shape[0], math.ceil(float(sy.max())) + pad)
                if c1 <= c0 or r1 <= r0:
                    out = np.zeros((src.count, h, w), dtype=src.dtypes[0])
                    ok = np.zeros((h, w), dtype=bool)
                else:
                    swin = Window(c0, r0, c1 - c0, r1 - r0)
                    img = src.read(window=swin)
                    valid = read_valid_mask(src, window=swin)
                    out, ok = remap_block(img, valid, sx - (c0 + 0.5), sy - (r0 + 0.5))
                dst.write(out, window=blk)
                dst.write_mask(ok.astype(np.uint8) * 255, window=blk)
                valid_px += int(ok.sum())
    return {"path": str(dst_path), "valid_px": valid_px}


# --------------------------------------------------------------------------- the field file


def write_field_geotiff(path: str | os.PathLike[str], field: DisplacementField, crs: Any, *,
                        tags: Mapping[str, str] | None = None) -> None:
    """The field as a 2-band float64 GeoTIFF (``dx_m``, ``dy_m``; east, north; metres).

    A pixel is a node of the field (its transform is :attr:`DisplacementField.node_transform`);
    the internal mask is valid where the field was estimated or faded (``support > 0``) and
    masked where the global model is kept (value 0).
    """
    arr = np.stack([field.dx_m, field.dy_m]).astype(np.float64)
    write_geotiff(path, arr, transform=field.node_transform, crs=crs,
                  mask=field.support > 0, band_descriptions=list(FIELD_BANDS), tags=tags)


def read_field_geotiff(path: str | os.PathLike[str]) -> DisplacementField:
    """A :class:`DisplacementField` from :func:`write_field_geotiff`'s file."""
    if not os.path.isfile(path):
        raise InputFileError(f"{path} not found: the local alignment field is written by "
                             "'geosim align' with align_model = \"local\"; re-run it")
    with rasterio.open(path) as ds:
        arr = ds.read().astype(np.float64)
        support = (ds.read_masks(1) > 0).astype(float)
        transform = ds.transform
    return DisplacementField(transform, arr[0], arr[1], support)


def move_points(field: DisplacementField, x_m: np.ndarray, y_m: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Move points of the globally corrected flight (label centres) into the aligned frame."""
    return field.invert(x_m, y_m)


def field_record(field: DisplacementField, shifts: WindowShifts, path: str) -> dict[str, Any]:
    """The ``local_field`` entry of a flight in ``alignment.json`` (JSON-able).

    ``before`` summarises the accepted window shifts (what the global model left, px);
    ``fallback`` says where the global model is kept: the fraction of field nodes without a
    measurement within reach and their bounding box in map metres (the GeoTIFF's mask shows
    them node by node).
    """
    acc = shifts.accepted
    mag = np.hypot(shifts.dx_px, shifts.dy_px)[acc]
    t = field.node_transform
    unsup = np.argwhere(field.support <= 0)
    bounds = None
    if unsup.size:
        (r0, c0), (r1, c1) = unsup.min(axis=0), unsup.max(axis=0) + 1
        x0, y0 = t * (c0, r0)
        x1, y1 = t * (c1, r1)
        bounds = [float(min(x0, x1)), float(min(y0, y1)), float(max(x0, x1)), float(max(y0, y1))]
    return {
        "model": "local",
        "path": path,
        "bands": list(FIELD_BANDS),
        "node_grid": {"transform": [float(v) for v in list(t)[:6]],
                      "shape": [int(v) for v in field.shape],
                      "spacing_m": field.spacing_m},
        "before": {"n_accepted": int(mag.size),
                   "median_shift_px": float(np.median(mag)) if mag.size else None,
                   "max_shift_px": float(mag.max()) if mag.size else None},
        "fit": field.stats,
        "fallback": {"node_fraction": float(np.mean(field.support <= 0)),
                     "bounds_m": bounds,
                     "meaning": "nodes with no accepted window within reach keep the global "
                                "similarity (field 0, masked in the GeoTIFF)"},
        "convention": ("D(p) = (dx_m, dy_m) at aligned-frame point p (site CRS, m, east/north): "
                       "the ground at p in the reference is at p + D(p) in the globally "
                       "corrected flight; aligned pixels sample it there; a point of the "
                       "globally corrected flight q moves to p with p + D(p) = q. Between nodes "
                       "D is the cubic B-spline of the node values (scipy.ndimage order 3, "
                       "mode 'nearest')."),
    }


def label_moves(labels: Any, out_dir: str | os.PathLike[str]) -> Any:
    """Translate label geometries (a GeoDataFrame with a ``flight`` column, aligned frame
    of the global model) by the local field of their flight, read from ``alignment.json``.

    Each geometry's centroid ``q`` moves to ``p`` with ``p + D(p) = q``; flights without a
    ``local_field`` entry (the similarity model) are returned unchanged.
    """
    import json

    import shapely
    from shapely.affinity import translate

    path = os.path.join(out_dir, "alignment.json")
    if not os.path.isfile(path):
        return labels
    with open(path) as fh:
        entries = json.load(fh).get("flights", {})
    out = labels.copy()
    geoms = np.asarray(out.geometry.values, dtype=object).copy()
    moved = False
    for fid, pos in out.groupby("flight", sort=False).indices.items():
        rec = entries.get(fid, {}).get("local_field")
        if not rec:
            continue
        field = read_field_geotiff(os.path.join(out_dir, rec["path"]))
        c = shapely.get_coordinates(shapely.centroid(geoms[pos])).reshape(-1, 2)
        px, py = move_points(field, c[:, 0], c[:, 1])
        geoms[pos] = [translate(g, xoff=float(dx), yoff=float(dy))
                      for g, dx, dy in zip(geoms[pos], px - c[:, 0], py - c[:, 1], strict=True)]
        moved = True
    if not moved:
        return labels
    return out.set_geometry(type(out.geometry)(list(geoms), crs=out.crs, index=out.index))
