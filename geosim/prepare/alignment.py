"""Alignment of the flights in map coordinates (the paper's method, on the shared grid).

1. **Crop** to the common extent: the *aligned grid* is the site UAV grid cut to the
   common extent's bounding box, snapped outward to whole satellite pixels, so pixel
   ``(0, 0)`` of every ``aligned/<flight>.tif`` is the same ground, and its transform
   is the site grid transform offset by whole pixels.
2. **Register** each flight to the reference flight on one central window of
   ``align_window_px`` (Fourier–Mellin: rotation, scale, translation;
   :func:`geosim.align.register_similarity`). Low confidence is refused.
3. **Apply** by resampling each flight once, from its original file, onto the aligned
   grid (:mod:`geosim.prepare.onewarp`: bicubic imagery, conservative mask; the
   correction is composed with the reprojection; :func:`apply_alignment` is the former
   second warp of a gridded flight, kept for comparison).
   With ``site.anchor = "satellite"`` the reference flight is first registered to
   the satellite scene (:mod:`geosim.prepare.anchor`) and that transform ``T`` is
   composed into every correction (``C' = T ∘ C``): the aligned frame is then the
   satellite's, and the reference flight is resampled too.
4. **Check** locally: phase correlation in a grid of windows between each aligned
   flight and the aligned reference (:func:`geosim.align.local_shift_field`); what
   is left are stitching warps, reported as statistics and GeoJSON arrows.

Conventions of ``alignment.json``
---------------------------------
For each flight the *correction* ``C`` is the similarity transform, in map
coordinates of the site CRS (x east, y north, metres), that takes a point's
coordinates **as stated by that flight's own georeference** to its coordinates in
the **aligned frame** (the reference flight's georeference)::

    C(p) = center_m + shift_m + scale · R(rotation_deg) · (p − center_m)

* ``center_m`` — the centre of the registration window, map metres ``[x, y]``;
* ``shift_m`` — ``[dx, dy]`` in metres: how far the flight must move (east, north)
  at ``center_m`` to land on the reference;
* ``rotation_deg`` — rotation of the correction, degrees, **counter-clockwise as
  seen on a north-up map** (x east, y north);
* ``scale`` — dimensionless scale of the correction (> 1 enlarges the flight).

A flight whose stated georeference is displaced by ``+e`` relative to the
reference gets ``shift_m ≈ −e``; the reference itself gets the identity.
With the satellite anchor the entries hold the full correction ``C' = T ∘ C``
(stated → satellite frame; the flight → reference part is kept under
``to_reference``) and ``alignment.json["anchor"]`` holds ``T`` in the same form
(``to``, ``shift_m``, ``rotation_deg``, ``scale``, ``center_m``, ``confidence``,
``method``); with the default anchor ``"reference_flight"`` it is the identity.
:func:`correction_affine` turns an entry into an :class:`affine.Affine` (map →
map) that moves label geometries the same way. ``matrix_px`` is the kernel's 2×3
matrix in window pixel coordinates (pixel centres at integers, reference pixel
``p`` → moving pixel ``M @ [x, y, 1]``); ``matrix_grid_px`` is the same map in
site-UAV-grid corner coordinates (``col, row`` with ``(0, 0)`` the grid's
north-west corner).
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window
from rasterio.windows import from_bounds as window_from_bounds
from shapely.geometry import box
from shapely.geometry.base import BaseGeometry
from tqdm import tqdm

from geosim.errors import AlignmentError
from geosim.io.raster import (
    create_geotiff,
    iter_windows,
    open_raster,
    read_valid_mask,
    read_window,
)
from geosim.prepare.grid import SiteGrid, snap_window_to_sat

#: A raster path, or a reader ``window -> (grey float32, valid bool)``.
GreySource = str | os.PathLike[str] | Callable[[Window], tuple[np.ndarray, np.ndarray]]

# --------------------------------------------------------------------------- pure helpers


def aligned_window(common: BaseGeometry, grid: SiteGrid) -> Window:
    """UAV-grid window of the common extent's bounding box, snapped to whole sat pixels.

    Parameters
    ----------
    common
        Common extent polygon in the site CRS.
    grid
        The site grid.

    Returns
    -------
    Window
        Offsets and sizes are multiples of ``phi``; clipped to the grid.
    """
    if common.is_empty:
        raise AlignmentError("the common extent is empty; run the footprints step first and "
                             "check the flights overlap")
    w = window_from_bounds(*common.bounds, transform=grid.uav_transform)
    w = Window(math.floor(w.col_off + 1e-6), math.floor(w.row_off + 1e-6),
               math.ceil(w.col_off + w.width - 1e-6) - math.floor(w.col_off + 1e-6),
               math.ceil(w.row_off + w.height - 1e-6) - math.floor(w.row_off + 1e-6))
    return snap_window_to_sat(w, grid.phi, grid.uav_shape)


def registration_window(common: BaseGeometry, grid: SiteGrid, within: Window,
                        size_px: int) -> Window:
    """Square window of ``size_px`` (or less if the extent is smaller) inside the common extent.

    Centred on the middle of ``within`` (the paper's central window) when that
    square lies inside the common extent; otherwise on the common extent's pole of
    inaccessibility (the point farthest from its edges). Clipped to ``within``.
    """
    from shapely.ops import polylabel

    side = int(min(size_px, within.width, within.height))
    cx = within.col_off + within.width / 2.0
    cy = within.row_off + within.height / 2.0

    def square(cx: float, cy: float) -> Window:
        c0 = int(round(cx - side / 2.0))
        r0 = int(round(cy - side / 2.0))
        c0 = min(max(c0, int(within.col_off)), int(within.col_off + within.width) - side)
        r0 = min(max(r0, int(within.row_off)), int(within.row_off + within.height) - side)
        return Window(c0, r0, side, side)

    win = square(cx, cy)
    t = grid.uav_transform

    def footprint(w: Window) -> BaseGeometry:
        x0, y0 = t @ (w.col_off, w.row_off)
        x1, y1 = t @ (w.col_off + w.width, w.row_off + w.height)
        return box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1))

    fp = footprint(win)
    if common.intersection(fp).area >= 0.95 * fp.area:
        return win
    poly = common if common.geom_type == "Polygon" else max(common.geoms, key=lambda g: g.area)
    pole = polylabel(poly, tolerance=grid.uav_gsd_m * 10)
    pc, pr = ~t @ (pole.x, pole.y)
    return square(pc, pr)


def window_to_grid_matrix(matrix_px: np.ndarray, window: Window) -> np.ndarray:
    """Lift a window-pixel-centre matrix to site-grid corner coordinates (3×3).

    ``matrix_px`` maps reference window pixel centres ``(x, y)`` (integers at centres)
    to moving window pixel centres. The result maps grid corner coordinates
    ``(col, row)`` of the reference to those of the moving flight (both on the same grid).
    """
    m = np.vstack([np.asarray(matrix_px, dtype=float).reshape(2, 3), [0.0, 0.0, 1.0]])
    k = np.array([[1.0, 0.0, window.col_off + 0.5], [0.0, 1.0, window.row_off + 0.5],
                  [0.0, 0.0, 1.0]])
    return k @ m @ np.linalg.inv(k)


def _affine_from_3x3(m: np.ndarray) -> Affine:
    return Affine(m[0, 0], m[0, 1], m[0, 2], m[1, 0], m[1, 1], m[1, 2])


def _3x3(a: Affine) -> np.ndarray:
    return np.array([[a.a, a.b, a.c], [a.d, a.e, a.f], [0.0, 0.0, 1.0]])


def correction_from_matrix(matrix_px: np.ndarray, window: Window, grid_transform: Affine
                           ) -> dict[str, Any]:
    """Map-unit correction of a flight from the kernel's pixel matrix.

    Parameters
    ----------
    matrix_px
        2×3 matrix: reference window pixel ``p`` → moving window pixel ``M @ [x, y, 1]``
        (pixel centres at integer coordinates).
    window
        The registration window on the site UAV grid (same for both flights).
    grid_transform
        The site UAV grid affine (north-up).

    Returns
    -------
    dict
        ``shift_m``, ``rotation_deg``, ``scale``, ``center_m`` (see the module
        docstring), ``correction_affine`` (6 numbers, map → map) and
        ``matrix_grid_px`` (2×3, grid corner coordinates).
    """
    m_grid = window_to_grid_matrix(matrix_px, window)
    g = _3x3(grid_transform)
    corr = g @ np.linalg.inv(m_grid) @ np.linalg.inv(g)       # stated map → aligned map
    a = corr[:2, :2]
    scale = math.sqrt(abs(float(np.linalg.det(a))))
    rotation_deg = math.degrees(math.atan2(a[1, 0] - a[0, 1], a[0, 0] + a[1, 1]))
    center = grid_transform @ (window.col_off + window.width / 2.0,
                               window.row_off + window.height / 2.0)
    moved = corr @ np.array([center[0], center[1], 1.0])
    return {
        "shift_m": [float(moved[0] - center[0]), float(moved[1] - center[1])],
        "rotation_deg": rotation_deg,
        "scale": scale,
        "center_m": [float(center[0]), float(center[1])],
        "correction_affine": [float(v) for v in corr[:2].ravel()],
        "matrix_grid_px": m_grid[:2].tolist(),
    }


def correction_affine(entry: Mapping[str, Any], grid: SiteGrid | None = None) -> Affine:
    """The map → map correction of one ``alignment.json`` flight entry.

    Maps a point's coordinates as stated by the flight's own georeference (site CRS,
    metres) to its coordinates in the aligned frame; apply it to label geometries
    with ``shapely.affinity.affine_transform(geom, [a, b, d, e, c, f])``.

    Parameters
    ----------
    entry
        ``alignment.json["flights"][flight_id]``: ``shift_m``, ``rotation_deg``,
        ``scale`` and ``center_m`` (or ``window`` plus ``grid`` to find the centre).
    grid
        The site grid; needed only when ``center_m`` is absent.

    Returns
    -------
    affine.Affine
        ``C(p) = center + shift + scale · R(rotation) · (p − center)``, rotation
        counter-clockwise on a north-up map.
    """
    if "center_m" in entry:
        cx, cy = (float(v) for v in entry["center_m"])
    elif grid is not None and "window" in entry:
        w = entry["window"]
        cx, cy = grid.uav_transform @ (w["col_off"] + w["width"] / 2.0,
                                       w["row_off"] + w["height"] / 2.0)
    else:
        raise AlignmentError("alignment entry has neither center_m nor window; re-run the "
                             "align step")
    dx, dy = (float(v) for v in entry["shift_m"])
    s = float(entry["scale"])
    th = math.radians(float(entry["rotation_deg"]))
    lin = Affine(s * math.cos(th), -s * math.sin(th), 0.0, s * math.sin(th), s * math.cos(th), 0.0)
    return Affine.translation(cx + dx, cy + dy) @ lin @ Affine.translation(-cx, -cy)


def identity_entry(window: Window, grid_transform: Affine) -> dict[str, Any]:
    """The reference flight's entry: the identity correction."""
    entry = correction_from_matrix(np.array([[1.0, 0, 0], [0, 1.0, 0]]), window, grid_transform)
    entry.update(confidence=1.0, matrix_px=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    return entry


def warp_block(image: np.ndarray, valid: np.ndarray, matrix: np.ndarray,
               out_shape: tuple[int, int], *, interpolation: int = cv2.INTER_CUBIC,
               ) -> tuple[np.ndarray, np.ndarray]:
    """Resample one block: ``out(q) = image(matrix @ [q, 1])`` (pixel centres at integers).

    Parameters
    ----------
    image
        ``(bands, rows, cols)`` source block (uint8, uint16, int16 or float32).
    valid
        ``(rows, cols)`` bool source mask.
    matrix
        2×3 output pixel → source pixel matrix.
    out_shape
        ``(rows, cols)`` of the output block.

    Returns
    -------
    (image, valid)
        Output pixels (input dtype, 0 where invalid) and a conservative mask: valid
        only where every source pixel under the bicubic kernel was valid.
    """
    h, w = out_shape
    m = np.asarray(matrix, dtype=np.float64).reshape(2, 3)
    flags = interpolation | cv2.WARP_INVERSE_MAP
    bands = []
    for b in range(image.shape[0]):  # per band: any count, dtype kept
        bands.append(cv2.warpAffine(np.ascontiguousarray(image[b]), m, (w, h), flags=flags,
                                    borderMode=cv2.BORDER_CONSTANT, borderValue=0))
    out = np.stack(bands)
    core = cv2.erode(valid.astype(np.uint8), np.ones((3, 3), np.uint8)) if not valid.all() \
        else valid.astype(np.uint8)
    mw = cv2.warpAffine(core.astype(np.float32), m, (w, h),
                        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    ok = mw >= 0.999
    out[:, ~ok] = 0
    return out, ok


def _source_window(m_grid: np.ndarray, out_win: Window, grid_shape: tuple[int, int],
                   pad_px: int = 4) -> Window | None:
    """Grid window covering the source of an output window under ``m_grid`` (corner coords)."""
    c0, r0 = out_win.col_off, out_win.row_off
    corners = np.array([[c0, r0, 1], [c0 + out_win.width, r0, 1], [c0, r0 + out_win.height, 1],
                        [c0 + out_win.width, r0 + out_win.height, 1]], dtype=float).T
    src = m_grid @ corners
    rows, cols = grid_shape
    sc0 = max(0, math.floor(src[0].min()) - pad_px)
    sr0 = max(0, math.floor(src[1].min()) - pad_px)
    sc1 = min(cols, math.ceil(src[0].max()) + pad_px)
    sr1 = min(rows, math.ceil(src[1].max()) + pad_px)
    if sc1 <= sc0 or sr1 <= sr0:
        return None
    return Window(sc0, sr0, sc1 - sc0, sr1 - sr0)


# --------------------------------------------------------------------------- I/O


def grid_shape(ref: Any, shape: tuple[int, int] | None, *, caller: str) -> tuple[int, int]:
    """``(rows, cols)`` of the grid a reference is read on: ``shape`` when given, else the
    size of the raster file ``ref`` (a reader callable has no size of its own)."""
    if shape is None:
        if callable(ref):
            raise TypeError(f"{caller}: give shape when ref is a reader")
        with rasterio.open(ref) as ds:
            shape = (ds.height, ds.width)
    return int(shape[0]), int(shape[1])


def read_grey_window(path: str | os.PathLike[str], window: Window
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Grey level (BT.601 luma of RGB, float32) and valid mask of a window of a raster
    (the window may reach outside it: those pixels are invalid)."""
    from geosim.align.phasecorr import as_grey

    with open_raster(path, what="raster to register", require_crs=False) as ds:
        data = read_window(ds, window, bands=[1, 2, 3] if ds.count >= 3 else [1],
                           boundless=True, path=path)
    return as_grey(data.array), data.valid


def apply_alignment(src_path: str | os.PathLike[str], dst_path: str | os.PathLike[str], *,
                    m_grid: np.ndarray, out_window: Window, block_px: int = 2048,
                    tags: Mapping[str, str] | None = None, what: str = "flight",
                    progress: bool | None = None) -> dict[str, Any]:
    """Resample a gridded flight onto the aligned grid window by window.

    Parameters
    ----------
    src_path
        ``grid/<flight>.tif`` (site UAV grid, internal mask).
    dst_path
        ``aligned/<flight>.tif``; covers ``out_window`` of the site grid.
    m_grid
        3×3 map from reference grid corner coordinates to this flight's grid corner
        coordinates (identity for the reference: then pixels are copied exactly).
    out_window
        The aligned grid window on the site UAV grid.

    Returns
    -------
    dict
        ``path``, ``valid_px``.
    """
    identity = np.allclose(m_grid, np.eye(3), atol=1e-12, rtol=0)
    valid_px = 0
    with rasterio.open(src_path) as src:
        grid_shape = (src.height, src.width)
        transform = src.transform @ Affine.translation(int(out_window.col_off),
                                                       int(out_window.row_off))
        descriptions = list(src.descriptions)
        colorinterp = list(src.colorinterp)
        with create_geotiff(dst_path, width=int(out_window.width), height=int(out_window.height),
                            count=src.count, dtype=src.dtypes[0], crs=src.crs,
                            transform=transform, band_descriptions=[
                                d or f"band {i}" for i, d in enumerate(descriptions, 1)],
                            tags=tags, internal_mask=True) as dst:
            dst.colorinterp = colorinterp
            blocks = list(iter_windows(int(out_window.width), int(out_window.height),
                                       block_px=block_px))
            for blk in tqdm(blocks, desc=f"align {what}", unit="block", leave=False,
                            disable=None if progress is None else not progress):
                gwin = Window(out_window.col_off + blk.col_off, out_window.row_off + blk.row_off,
                              blk.width, blk.height)
                h, w = int(blk.height), int(blk.width)
                if identity:
                    out = src.read(window=gwin)
                    ok = read_valid_mask(src, window=gwin)
                else:
                    swin = _source_window(m_grid, gwin, grid_shape)
                    if swin is None:
                        out = np.zeros((src.count, h, w), dtype=src.dtypes[0])
                        ok = np.zeros((h, w), dtype=bool)
                    else:
                        img = src.read(window=swin)
                        valid = read_valid_mask(src, window=swin)
                        # block output centre index q → grid corner coords → source centre idx
                        to_grid = np.array([[1.0, 0, gwin.col_off + 0.5],
                                            [0, 1.0, gwin.row_off + 0.5], [0, 0, 1.0]])
                        to_src = np.array([[1.0, 0, -(swin.col_off + 0.5)],
                                           [0, 1.0, -(swin.row_off + 0.5)], [0, 0, 1.0]])
                        mat = (to_src @ m_grid @ to_grid)[:2]
                        out, ok = warp_block(img, valid, mat, (h, w))
                dst.write(out, window=blk)
                dst.write_mask(ok.astype(np.uint8) * 255, window=blk)
                valid_px += int(ok.sum())
    return {"path": str(dst_path), "valid_px": valid_px}


# --------------------------------------------------------------------------- kernels adapters


#: Largest rotation searched between georeferenced, north-up flights, degrees.
MAX_ROTATION_DEG = 10.0
# flights are already resampled to one GSD on the shared grid, so their residual scale
# error is a georeferencing error of well under 10 %; a narrow range means fewer false peaks
SCALE_RANGE = (0.9, 1.1)


def register_pair(ref_grey: np.ndarray, ref_valid: np.ndarray, mov_grey: np.ndarray,
                  mov_valid: np.ndarray, *, min_confidence: float = 0.1,
                  what: str = "flight") -> dict[str, Any]:
    """Run :func:`geosim.align.register_similarity` on two windows of the same grid.

    Returns ``matrix_px`` (reference window pixel → moving window pixel),
    ``confidence`` and the kernel's own numbers (pixel units, display convention).

    Raises
    ------
    AlignmentError
        Registration failed or its confidence is below ``min_confidence``; the
        message names ``what``.
    """
    from geosim.align import register_similarity

    try:
        res = register_similarity(ref_grey, mov_grey, valid_reference=ref_valid,
                                  valid_moving=mov_valid, max_rotation_deg=MAX_ROTATION_DEG,
                                  scale_range=SCALE_RANGE, min_confidence=min_confidence)
    except AlignmentError as exc:
        raise AlignmentError(f"{what}: {exc}") from exc
    return {
        "matrix_px": np.asarray(res.matrix, dtype=float).reshape(2, 3).tolist(),
        "confidence": float(res.confidence),
        "kernel": {"rotation_deg": float(res.rotation_deg), "scale": float(res.scale),
                   "shift_px": [float(v) for v in res.shift_px],
                   "centre_px": [float(v) for v in res.centre_px],
                   # NaN (too few refinement windows) is not valid JSON: write null
                   "residual_px": (float(res.residual_px) if np.isfinite(res.residual_px)
                                   else None),
                   "n_windows": int(res.n_windows)},
    }


@dataclass(frozen=True)
class RegistrationTask:
    """One flight registered to the reference over the registration window (an engine task).

    ``ref`` and ``mov`` are grey sources on the same grid (raster paths or picklable readers
    ``window -> (grey, valid)``, e.g. :class:`geosim.prepare.onewarp.WarpedGreyReader`);
    each task reads both windows itself, so flights register in parallel and the driver
    only gathers the small records.
    """

    ref: Any                                   # GreySource
    mov: Any                                   # GreySource
    window: Window
    min_confidence: float
    what: str


def registration_task(task: RegistrationTask) -> dict[str, Any]:
    """Run a :class:`RegistrationTask`: :func:`register_pair` on the two windows read."""
    ref_grey, ref_valid = _grey_source(task.ref)(task.window)
    mov_grey, mov_valid = _grey_source(task.mov)(task.window)
    return register_pair(ref_grey, ref_valid, mov_grey, mov_valid,
                         min_confidence=task.min_confidence, what=task.what)


def local_field_stats(shifts_px: np.ndarray, confident: np.ndarray, gsd_m: float
                      ) -> dict[str, Any]:
    """Summary of a local shift field: magnitudes in UAV px and metres over confident windows."""
    mag = np.hypot(shifts_px[:, 0], shifts_px[:, 1])[confident] if len(shifts_px) else \
        np.zeros(0)
    n = int(mag.size)
    def q(p: float) -> float | None:
        return float(np.percentile(mag, p)) if n else None
    return {
        "n_windows": int(len(shifts_px)), "n_confident": n,
        "median_shift_px": q(50), "p90_shift_px": q(90),
        "max_shift_px": float(mag.max()) if n else None,
        "median_shift_m": None if not n else q(50) * gsd_m,
        "mean_dx_px": float(shifts_px[confident, 0].mean()) if n else None,
        "mean_dy_px": float(shifts_px[confident, 1].mean()) if n else None,
    }


def local_check(ref: GreySource, mov: GreySource, *, window_px: int, block_px: int = 2048,
                min_confidence: float = 0.1, progress: bool | None = None,
                what: str = "flight", shape: tuple[int, int] | None = None
                ) -> list[dict[str, Any]]:
    """Local shift field between two flights on the aligned grid, block by block.

    ``ref`` and ``mov`` are each a raster path or a reader ``window -> (grey, valid)``
    (e.g. :class:`geosim.prepare.onewarp.WarpedGreyReader`: a flight read through its
    composed warp); ``shape = (rows, cols)`` of the grid is needed when ``ref`` is a reader.

    Returns one record per window: ``col``, ``row`` (window centre, aligned-grid
    corner coordinates), ``dx_px``, ``dy_px`` (moving content relative to the
    reference, x right, y down), ``confidence``.
    """
    return local_checks(ref, {what: mov}, window_px=window_px, block_px=block_px,
                        min_confidence=min_confidence, shape=shape)[what]


@dataclass(frozen=True)
class LocalCheckTask:
    """One block of the local check: the reference and every other flight (an engine task)."""

    ref: Any                                   # GreySource
    movs: tuple[tuple[str, Any], ...]          # (flight, GreySource)
    block: Window
    window_px: int
    min_confidence: float


def local_check_task(task: LocalCheckTask) -> dict[str, list[dict[str, Any]]]:
    """Run a :class:`LocalCheckTask`: the reference block is read once for all flights."""
    from geosim.align.local import local_shift_fields

    blk = task.block
    rg, rv = _grey_source(task.ref)(blk)
    out: dict[str, list[dict[str, Any]]] = {fid: [] for fid, _ in task.movs}
    measured = []
    for fid, mov in task.movs:
        mg, mv = _grey_source(mov)(blk)
        if (rv & mv).any():
            measured.append((fid, (mg, rv & mv)))
    if not measured:
        return out
    # every flight in one pass over the windows: each reference window prepared once
    fields = local_shift_fields(rg, [m for _, m in measured], window_px=task.window_px,
                                step_px=task.window_px, min_confidence=task.min_confidence)
    for (fid, _), field in zip(measured, fields, strict=True):
        for rec in _field_records(field):
            rec["col"] += blk.col_off
            rec["row"] += blk.row_off
            out[fid].append(rec)
    return out


def _grey_source(source: GreySource) -> Callable[[Window], tuple[np.ndarray, np.ndarray]]:
    return source if callable(source) else functools.partial(read_grey_window, source)


def local_checks(ref: GreySource, movs: Mapping[str, GreySource], *, window_px: int,
                 block_px: int = 2048, min_confidence: float = 0.1,
                 shape: tuple[int, int] | None = None) -> dict[str, list[dict[str, Any]]]:
    """:func:`local_check` of several flights against one reference, block by block.

    Each block is one engine task (:func:`geosim.engine.parallel_map`) that reads the
    reference once for every flight. Readers must be picklable for a multi-process engine
    (paths and :class:`geosim.prepare.onewarp.WarpedGreyReader` are). Returns the records
    per flight, in block order.
    """
    from geosim.engine import parallel_map

    block = max(window_px, (block_px // window_px) * window_px)
    height, width = grid_shape(ref, shape, caller="local_checks")
    tasks = [LocalCheckTask(ref, tuple(movs.items()), blk, window_px, min_confidence)
             for blk in iter_windows(width, height, block_px=block)
             if blk.width >= window_px and blk.height >= window_px]
    records: dict[str, list[dict[str, Any]]] = {fid: [] for fid in movs}
    for done in parallel_map(local_check_task, tasks, desc="local check"):
        for fid, recs in done.items():
            records[fid].extend(recs)
    return records


def _field_records(field: Any) -> list[dict[str, Any]]:
    """Flatten a :class:`geosim.align.local.LocalShiftField` into records.

    Window centres are converted from pixel-centre ``(row, col)`` to corner
    coordinates ``(col, row)``; unmeasured windows are dropped.
    """
    out = []
    centres = np.asarray(field.centres, dtype=float)
    for (i, j), dx in np.ndenumerate(np.asarray(field.dx_px, dtype=float)):
        dy = float(field.dy_px[i, j])
        if not (np.isfinite(dx) and np.isfinite(dy)):
            continue
        r, c = centres[i, j]
        out.append({"col": float(c) + 0.5, "row": float(r) + 0.5, "dx_px": float(dx),
                    "dy_px": dy, "confidence": float(field.confidence[i, j]),
                    "confident": bool(field.valid[i, j])})
    return out


def arrows_gdf(records: Sequence[Mapping[str, Any]], transform: Affine, crs: Any,
               flight: str, *, exaggeration: float = 50.0):
    """GeoDataFrame of arrows (LineStrings) from window centres along the local shift.

    The arrow length is the shift times ``exaggeration`` (shifts are centimetres);
    properties hold the true shift in px and m.
    """
    import geopandas as gpd
    from shapely.geometry import LineString

    gsd = abs(transform.a)
    rows = []
    for r in records:
        x0, y0 = transform @ (r["col"], r["row"])
        dx_m, dy_m = r["dx_px"] * gsd, -r["dy_px"] * gsd
        rows.append({"flight": flight, "dx_px": r["dx_px"], "dy_px": r["dy_px"],
                     "dx_m": dx_m, "dy_m": dy_m, "shift_px": math.hypot(r["dx_px"], r["dy_px"]),
                     "confidence": r["confidence"], "confident": r["confident"],
                     "exaggeration": exaggeration,
                     "geometry": LineString([(x0, y0), (x0 + exaggeration * dx_m,
                                                        y0 + exaggeration * dy_m)])})
    return gpd.GeoDataFrame(rows, geometry="geometry", crs=crs) if rows else \
        gpd.GeoDataFrame({"flight": [], "geometry": []}, geometry="geometry", crs=crs)
