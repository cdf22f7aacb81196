"""Valid-data footprints (polygons traced from masks) and the common extent.

A footprint is the polygon of a raster's valid pixels (alpha, nodata or internal
mask), traced with :func:`rasterio.features.shapes` and simplified to a tolerance
in metres — not its bounding box. The common extent is the intersection of all
flights' footprints; an empty or tiny intersection raises :class:`ExtentError`
naming the flights that do not overlap.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Mapping

import numpy as np
import rasterio
import rasterio.features
import shapely
from affine import Affine
from shapely.geometry import Polygon, shape
from shapely.geometry.base import BaseGeometry

from geosim.errors import ExtentError
from geosim.io.raster import read_valid_mask


def reduce_mask(mask: np.ndarray, factor_px: int) -> np.ndarray:
    """Majority-reduce a boolean mask by whole blocks of ``factor_px × factor_px``.

    A reduced cell is valid when at least half of its block is valid, so the traced
    area stays unbiased. Rows/cols beyond a whole block are dropped.
    """
    if factor_px == 1:
        return mask.astype(bool)
    r, c = mask.shape[0] // factor_px, mask.shape[1] // factor_px
    blocks = mask[: r * factor_px, : c * factor_px].reshape(r, factor_px, c, factor_px)
    return blocks.mean(axis=(1, 3)) >= 0.5


def mask_to_footprint(mask: np.ndarray, transform: Affine, *,
                      simplify_m: float = 0.0) -> BaseGeometry:
    """Polygon(s) covering the True pixels of a mask, in map units.

    Parameters
    ----------
    mask
        ``(rows, cols)`` bool, True = valid.
    transform
        Affine of the mask's pixel grid (outer corners) in map units.
    simplify_m
        Douglas–Peucker tolerance in map units (metres), topology preserved; 0 = none.

    Returns
    -------
    shapely Polygon or MultiPolygon (empty when no pixel is valid), holes kept.
    """
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    if not m.any():
        return Polygon()
    polys = [shape(geom) for geom, value in
             rasterio.features.shapes(m, mask=m.astype(bool), transform=transform,
                                      connectivity=4) if value == 1]
    geom = shapely.union_all(polys)
    if simplify_m > 0:
        geom = geom.simplify(simplify_m, preserve_topology=True)
    geom = shapely.make_valid(geom)
    if geom.geom_type == "GeometryCollection":  # drop slivers make_valid may leave
        geom = shapely.union_all([g for g in geom.geoms
                                  if g.geom_type in ("Polygon", "MultiPolygon")])
    return geom


def raster_footprint(path: str | os.PathLike[str], *, reduce_px: int = 1,
                     simplify_m: float = 0.0, block_px: int = 2048) -> BaseGeometry:
    """Footprint of a raster file, read window by window.

    Parameters
    ----------
    path
        Raster with alpha, nodata or an internal mask (its own CRS is the output's).
    reduce_px
        Trace the mask majority-reduced by this factor (e.g. ``phi`` = trace at
        the satellite pixel); limits memory to ``(rows/reduce_px) × (cols/reduce_px)``.
    simplify_m
        Simplification tolerance in map units (metres).
    block_px
        Read-window side in pixels (rounded down to a multiple of ``reduce_px``).
    """
    from geosim.io.raster import iter_windows

    block = max(reduce_px, (block_px // reduce_px) * reduce_px)
    with rasterio.open(path) as ds:
        rows, cols = ds.height // reduce_px, ds.width // reduce_px
        small = np.zeros((rows, cols), dtype=bool)
        for win in iter_windows(cols * reduce_px, rows * reduce_px, block_px=block):
            m = read_valid_mask(ds, window=win)
            r0, c0 = int(win.row_off) // reduce_px, int(win.col_off) // reduce_px
            red = reduce_mask(m, reduce_px)
            small[r0:r0 + red.shape[0], c0:c0 + red.shape[1]] = red
        transform = ds.transform @ Affine.scale(reduce_px)
    return mask_to_footprint(small, transform, simplify_m=simplify_m)


def source_footprint(path: str | os.PathLike[str], site_crs, *, cell_m: float,
                     simplify_m: float = 0.0, block_px: int = 2048) -> BaseGeometry:
    """Footprint of a raster in another (projected) CRS, traced in the raster's own pixels.

    The mask is traced on the raster's own grid, majority-reduced to cells of about
    ``cell_m`` metres, and the polygon is densified and projected to ``site_crs``.
    Nothing is resampled, so no intermediate copy of the raster on the site grid is
    needed (the flights reach the site grid only through the one composed warp).

    Parameters
    ----------
    path
        Raster with alpha, nodata or an internal mask, any CRS.
    site_crs
        Target CRS (projected, metres).
    cell_m
        Tracing cell size, metres (e.g. the satellite GSD).
    simplify_m
        Simplification tolerance in the site CRS, metres (applied after projecting).
    """
    from pyproj import Transformer

    with rasterio.open(path) as ds:
        src_crs = ds.crs
        # the raster's pixel size in metres, measured in the site CRS
        tr = Transformer.from_crs(src_crs, site_crs, always_xy=True)
        cx, cy = ds.transform @ (ds.width / 2.0, ds.height / 2.0)
        px, py = ds.transform @ (ds.width / 2.0 + 1.0, ds.height / 2.0)
        (x0, x1), (y0, y1) = tr.transform([cx, px], [cy, py])
        px_m = float(np.hypot(x1 - x0, y1 - y0)) or 1.0
        src_px = abs(ds.transform.a) or 1.0
    reduce_px = max(1, int(round(cell_m / px_m)))
    geom = raster_footprint(path, reduce_px=reduce_px, block_px=block_px)
    if geom.is_empty:
        return geom
    if _same_crs(src_crs, site_crs):
        out = geom
    else:
        dense = shapely.segmentize(geom, max_segment_length=src_px * reduce_px * 4)
        out = shapely.make_valid(shapely.transform(
            dense, lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1]))))
    if simplify_m > 0:
        out = shapely.make_valid(out.simplify(simplify_m, preserve_topology=True))
    return _polygonal(out)


def _same_crs(a, b) -> bool:
    """True when two CRS definitions are the same CRS."""
    from rasterio.crs import CRS

    return CRS.from_user_input(a) == CRS.from_user_input(b)


def _polygonal(geom: BaseGeometry) -> BaseGeometry:
    if geom.is_empty:
        return Polygon()
    if geom.geom_type in ("Polygon", "MultiPolygon"):
        return geom
    parts = [g for g in getattr(geom, "geoms", []) if g.geom_type in ("Polygon", "MultiPolygon")]
    return shapely.union_all(parts) if parts else Polygon()


def common_extent(footprints: Mapping[str, BaseGeometry], *, min_area_m2: float,
                  what: str = "flights") -> BaseGeometry:
    """Intersection of all footprints, refusing an empty or tiny one.

    Parameters
    ----------
    footprints
        ``{flight id: footprint}`` in one projected CRS (metres).
    min_area_m2
        Smallest acceptable intersection area in m².
    what
        Word for the inputs in messages.

    Raises
    ------
    ExtentError
        When the intersection is empty or smaller than ``min_area_m2``; the message
        names the pairs of flights that do not overlap (or overlap least).
    """
    ids = list(footprints)
    if not ids:
        raise ExtentError(f"no {what} to intersect; add [[flights]] to the site file")
    inter = footprints[ids[0]]
    for i in ids[1:]:
        inter = inter.intersection(footprints[i])
    inter = _polygonal(inter)
    if inter.is_empty or inter.area < min_area_m2:
        pair_areas = {(a, b): footprints[a].intersection(footprints[b]).area
                      for a, b in itertools.combinations(ids, 2)}
        disjoint = [f"{a}∩{b}" for (a, b), area in pair_areas.items() if area <= 0]
        detail = (f"these do not overlap at all: {', '.join(disjoint)}" if disjoint else
                  "smallest pairwise overlaps: " + ", ".join(
                      f"{a}∩{b} = {area:.1f} m²" for (a, b), area in
                      sorted(pair_areas.items(), key=lambda kv: kv[1])[:3]))
        raise ExtentError(
            f"the common extent of {what} {', '.join(ids)} is "
            f"{'empty' if inter.is_empty else f'{inter.area:.1f} m²'} (minimum "
            f"{min_area_m2:.0f} m²); {detail}. Remove the flights that do not cover the "
            "same ground from the site file, or split the site")
    return inter
