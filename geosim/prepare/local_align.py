"""Local co-registration in the pipeline (``parameters.align_model = "local"``).

The pure estimation is :mod:`geosim.align.field`; this module adapts it to rasters:

* :func:`measure_local_shifts` — window shifts between two aligned rasters (files, or read
  on the fly through a flight's composed warp), strip by strip (memory bounded by
  ``window_px`` × a column chunk);
* :func:`sample_points` — for the pixel centres of any destination window (given its
  transform), the map points of the *globally corrected* flight to sample: ``p + D(p)``;
* :func:`with_field` — the flight's composed warp (:class:`geosim.prepare.onewarp.ComposedWarp`)
  with the field plugged in, so the flight is resampled **once**, from its original file,
  onto the aligned grid (aligned pixel → map → field → inverse global correction → flight
  CRS → source pixel), window by window, by :func:`geosim.prepare.onewarp.warp_raster_task`;
* :func:`write_field_geotiff` / :func:`read_field_geotiff` — the field as a 2-band GeoTIFF
  (``dx_m``, ``dy_m``; the mask marks where it was estimated, masked nodes keep the global
  model), and :func:`move_points` for labels.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window

from geosim.align.field import (
    UNMEASURED,
    DisplacementField,
    WindowShifts,
    measure_window_shifts,
)
from geosim.align.local import window_starts
from geosim.errors import InputFileError
from geosim.io.raster import write_geotiff
from geosim.prepare.alignment import grid_shape, read_grey_window
from geosim.prepare.onewarp import ComposedWarp

#: Window side and step (UAV px) of the local field's phase correlation.
LOCAL_FIELD_WINDOW_PX = 256
LOCAL_FIELD_STEP_PX = 128

FIELD_BANDS = ("dx_m", "dy_m")


# --------------------------------------------------------------------------- measuring


GreySource = str | os.PathLike[str] | Callable[[Window], tuple[np.ndarray, np.ndarray]]


def _grey_reader(source: GreySource) -> Callable[[Window], tuple[np.ndarray, np.ndarray]]:
    # a partial, not a lambda: readers travel to worker processes inside the tasks
    return source if callable(source) else functools.partial(read_grey_window, source)


#: Rows of windows measured by one engine task (a strip of about 1 000 px at the defaults).
ROWS_PER_TASK = 8


@dataclass(frozen=True)
class ShiftRowsTask:
    """Rows of windows of one flight against the reference (an engine task)."""

    ref: Any                                   # GreySource
    mov: Any                                   # GreySource
    row_starts: tuple[int, ...]                # first pixel row of each row of windows
    chunks: tuple[tuple[int, ...], ...]        # first pixel column of each window, by chunk
    window_px: int
    step_px: int


def shift_rows_task(task: ShiftRowsTask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run a :class:`ShiftRowsTask`: ``(dx_px, dy_px, confidence)``, each (rows, windows),
    NaN / 0 where a chunk has no valid pixel in both."""
    read_ref, read_mov = _grey_reader(task.ref), _grey_reader(task.mov)
    n = sum(len(c) for c in task.chunks)
    dx = np.full((len(task.row_starts), n), np.nan)
    dy = np.full((len(task.row_starts), n), np.nan)
    conf = np.zeros((len(task.row_starts), n))
    for i, row in enumerate(task.row_starts):
        j0 = 0
        for starts in task.chunks:
            c0 = int(starts[0])
            win = Window(c0, int(row), int(starts[-1]) - c0 + task.window_px, task.window_px)
            rg, rv = read_ref(win)
            mg, mv = read_mov(win)
            if (rv & mv).any():
                s = measure_window_shifts(rg, mg, valid=rv & mv, window_px=task.window_px,
                                          step_px=task.step_px)
                k = s.dx_px.shape[1]
                dx[i, j0:j0 + k] = s.dx_px[0]
                dy[i, j0:j0 + k] = s.dy_px[0]
                conf[i, j0:j0 + k] = s.confidence[0]
            j0 += len(starts)
    return dx, dy, conf


def measure_local_shifts_many(ref: GreySource, movs: Mapping[str, GreySource], *,
                              shape: tuple[int, int] | None = None,
                              window_px: int = LOCAL_FIELD_WINDOW_PX,
                              step_px: int = LOCAL_FIELD_STEP_PX, windows_per_chunk: int = 16
                              ) -> dict[str, WindowShifts]:
    """:func:`measure_local_shifts` of several flights against one reference.

    Every flight's rows of windows are engine tasks (:data:`ROWS_PER_TASK` rows each,
    :func:`geosim.engine.parallel_map`), all flights in one round, so that the workers
    share them; the sources must be picklable for a multi-process engine (paths and
    :class:`geosim.prepare.onewarp.WarpedGreyReader` are).
    """
    from geosim.engine import parallel_map

    height, width = grid_shape(ref, shape, caller="measure_local_shifts")
    sr = window_starts(height, window_px, step_px)
    sc = window_starts(width, window_px, step_px)
    chunks = tuple(tuple(int(c) for c in sc[k:k + windows_per_chunk])
                   for k in range(0, len(sc), windows_per_chunk))
    groups = [tuple(int(r) for r in sr[i:i + ROWS_PER_TASK])
              for i in range(0, len(sr), ROWS_PER_TASK)]
    jobs = [(fid, g) for fid in movs for g in groups]
    done = parallel_map(shift_rows_task, [
        ShiftRowsTask(ref, movs[fid], g, chunks, int(window_px), int(step_px))
        for fid, g in jobs], desc="local field")
    half = (window_px - 1) / 2.0
    yy, xx = np.meshgrid(sr + half, sc + half, indexing="ij")
    out = {}
    for fid in movs:
        parts = [d for (f, _), d in zip(jobs, done, strict=True) if f == fid]
        dx = np.concatenate([d[0] for d in parts]).reshape(len(sr), len(sc))
        dy = np.concatenate([d[1] for d in parts]).reshape(len(sr), len(sc))
        conf = np.concatenate([d[2] for d in parts]).reshape(len(sr), len(sc))
        status = np.where(np.isfinite(dx), 0, UNMEASURED).astype(np.int8)
        out[fid] = WindowShifts(xx.astype(float), yy.astype(float), dx, dy, conf, status,
                                int(window_px), int(step_px))
    return out


def measure_local_shifts(ref: GreySource, mov: GreySource, *, shape: tuple[int, int] | None = None,
                         window_px: int = LOCAL_FIELD_WINDOW_PX,
                         step_px: int = LOCAL_FIELD_STEP_PX, windows_per_chunk: int = 16,
                         progress: bool | None = None, what: str = "flight") -> WindowShifts:
    """Window shifts between two rasters on the same grid, over their whole extent.

    Rows of windows are read as strips of ``window_px`` rows, in column chunks of
    ``windows_per_chunk`` windows, so memory does not grow with the raster; groups of rows
    are engine tasks (:func:`measure_local_shifts_many`).

    Parameters
    ----------
    ref, mov
        Each a raster path or a reader ``window -> (grey float32, valid bool)`` (e.g.
        :class:`geosim.prepare.onewarp.WarpedGreyReader`: the globally aligned flight read
        on the fly through its composed warp, nothing written).
    shape
        ``(rows, cols)`` of the grid (default: read from ``ref``, which must then be a path).
    progress, what
        Kept for callers; the engine shows the progress of the tasks.

    Returns
    -------
    WindowShifts
        Centres in the rasters' pixel-centre coordinates; every window ``accepted`` or
        ``unmeasured`` (apply :func:`geosim.align.field.reject_outliers` next).
    """
    return measure_local_shifts_many(ref, {what: mov}, shape=shape, window_px=window_px,
                                     step_px=step_px, windows_per_chunk=windows_per_chunk)[what]


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


def with_field(warp: ComposedWarp, field: DisplacementField) -> ComposedWarp:
    """The flight's composed warp (global correction ``C⁻¹`` already set) with its field.

    Aligned pixel centre ``p`` → ``p + D(p)`` (:meth:`DisplacementField.apply`, the field
    convention) → ``C⁻¹`` → flight CRS → source pixel of the *original* flight: one bicubic
    interpolation (:func:`geosim.prepare.onewarp.warp_raster_task`), the field evaluated on
    the warp's lattice nodes. Picklable (the field pickles with its arrays), so it runs as an
    engine task on any worker.
    """
    return warp.with_correction(Affine(*warp.aligned_to_stated[:6]), field.apply)


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
