"""Boxes <-> map polygons through an image's affine georeference (pure).

Conventions
-----------
- A YOLO box is ``cx, cy, w, h`` normalised to the image width and height.
- Pixel coordinates are ``(col, row)`` of the pixel *corner* grid, as in
  rasterio/GDAL: pixel (0, 0) covers [0, 1) x [0, 1) and ``transform * (0, 0)``
  is the outer corner of the image. So a box ``x0 = (cx - w/2) * width_px``
  etc. maps to the map through the transform with no half-pixel shift.
- A box becomes a four-corner polygon in map coordinates, corners in the order
  top-left, top-right, bottom-right, bottom-left *of the image* (so edge 0-1
  runs along image columns: the box "width"). Through a rotated or sheared
  transform the polygon is a parallelogram, not an axis-aligned rectangle.
- Going back, a polygon becomes the axis-aligned bounding box, in the target
  image's pixel grid, of its corners. For a polygon that came from a box of the
  same image this is exact (up to float64 rounding).

Precision: an affine map and its inverse in float64 lose about 1e-16 of the
coordinate magnitude (1e-9 m at a UTM northing of 6e6 m, i.e. 2e-8 of a
0.05 m pixel). Reprojection (PROJ) of projected <-> lon/lat round-trips to
well below a micrometre. Box edges are not densified before reprojection: over
a few metres the curvature of a straight edge between two CRSs is far below a
micrometre.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import shapely
from affine import Affine
from pyproj import CRS, Transformer

from geosim.errors import CRSError


def normalised_to_pixel_bounds(boxes: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """YOLO ``cx, cy, w, h`` (normalised) -> pixel ``x0, y0, x1, y1`` (px, corner grid)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    cx, cy, w, h = b.T
    return np.column_stack([(cx - w / 2) * width_px, (cy - h / 2) * height_px,
                            (cx + w / 2) * width_px, (cy + h / 2) * height_px])


def pixel_bounds_to_normalised(bounds_px: np.ndarray, width_px: int, height_px: int,
                               ) -> np.ndarray:
    """Pixel ``x0, y0, x1, y1`` (px) -> YOLO ``cx, cy, w, h`` normalised to the image."""
    b = np.asarray(bounds_px, dtype=np.float64).reshape(-1, 4)
    x0, y0, x1, y1 = b.T
    return np.column_stack([(x0 + x1) / 2 / width_px, (y0 + y1) / 2 / height_px,
                            (x1 - x0) / width_px, (y1 - y0) / height_px])


def box_corners_px(boxes: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Corners of YOLO boxes in pixel coordinates.

    Returns
    -------
    numpy.ndarray
        ``(n, 4, 2)`` ``(col, row)`` in px: top-left, top-right, bottom-right, bottom-left.
    """
    x0, y0, x1, y1 = normalised_to_pixel_bounds(boxes, width_px, height_px).T
    return np.stack([np.column_stack([x0, y0]), np.column_stack([x1, y0]),
                     np.column_stack([x1, y1]), np.column_stack([x0, y1])], axis=1)


def apply_affine(transform: Affine, xy: np.ndarray) -> np.ndarray:
    """Apply an affine to points ``(..., 2)`` (vectorised ``transform * (x, y)``)."""
    a, b, c, d, e, f = transform[:6]
    x, y = xy[..., 0], xy[..., 1]
    return np.stack([a * x + b * y + c, d * x + e * y + f], axis=-1)


def transform_geometries(geoms: np.ndarray, transform: Affine) -> np.ndarray:
    """Apply an affine to every coordinate of an array of shapely geometries."""
    return shapely.transform(np.asarray(geoms, dtype=object),
                             lambda xy: apply_affine(transform, xy))


def boxes_to_polygons(boxes: np.ndarray, transform: Affine, width_px: int, height_px: int,
                      ) -> np.ndarray:
    """YOLO boxes of an image -> polygons in that image's map coordinates.

    Parameters
    ----------
    boxes
        ``(n, 4)`` ``cx, cy, w, h`` normalised to the image.
    transform
        The image's pixel-corner -> map affine (CRS units per pixel).
    width_px, height_px
        Image size in pixels.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` shapely Polygons, corners TL, TR, BR, BL of the image, ring closed.
    """
    corners = apply_affine(transform, box_corners_px(boxes, width_px, height_px))
    if corners.shape[0] == 0:
        return np.empty(0, dtype=object)
    return shapely.polygons(corners)


def polygons_to_boxes(polygons: Sequence | np.ndarray, transform: Affine, width_px: int,
                      height_px: int) -> np.ndarray:
    """Polygons in map coordinates -> YOLO boxes of an image (not clipped).

    Each polygon becomes the axis-aligned bounding box of its vertices in the
    image's pixel grid, normalised to the image size. Values may fall outside
    [0, 1] for a polygon that is not inside the image: clip with
    :func:`geosim.labels.tiles.tile_boxes`.

    Returns
    -------
    numpy.ndarray
        ``(n, 4)`` ``cx, cy, w, h`` normalised (dimensionless).
    """
    geoms = np.asarray(polygons, dtype=object).reshape(-1)
    if geoms.size == 0:
        return np.zeros((0, 4))
    px = transform_geometries(geoms, ~transform)
    return pixel_bounds_to_normalised(shapely.bounds(px), width_px, height_px)


def box_centres(boxes: np.ndarray, transform: Affine, width_px: int, height_px: int,
                ) -> np.ndarray:
    """Map coordinates ``(n, 2)`` of box centres (an affine maps centre to centre)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    centres_px = np.column_stack([b[:, 0] * width_px, b[:, 1] * height_px])
    return apply_affine(transform, centres_px)


def box_sides(boxes: np.ndarray, transform: Affine, width_px: int, height_px: int,
              ) -> np.ndarray:
    """Side lengths of boxes in CRS units: ``(n, 2)`` width (along image columns), height.

    ``width = w * width_px * |(a, d)|`` and ``height = h * height_px * |(b, e)|``
    where ``(a, d)`` and ``(b, e)`` are the map vectors of one pixel step along a
    row and down a column. Multiply by :func:`linear_unit_m` for metres.
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    step_col = float(np.hypot(transform.a, transform.d))
    step_row = float(np.hypot(transform.b, transform.e))
    return np.column_stack([b[:, 2] * width_px * step_col, b[:, 3] * height_px * step_row])


def polygon_sides(polygons: Sequence | np.ndarray) -> np.ndarray:
    """Side lengths ``(n, 2)`` (CRS units) of polygons' minimum-area enclosing rectangles.

    The "width" is the side whose direction is closer to the map x axis (east),
    matching :func:`box_sides` for boxes of a north-up image. Used for label
    polygons that did not come from a YOLO box (e.g. digitised in QGIS).

    Computed by rotating calipers on the convex hull in coordinates relative to
    the hull's first vertex (GEOS's ``oriented_envelope`` loses about 1e-4 m on
    a 2 m box at UTM magnitudes).
    """
    geoms = np.asarray(polygons, dtype=object).reshape(-1)
    out = np.zeros((geoms.size, 2))
    for i, hull in enumerate(shapely.convex_hull(geoms)):
        if hull is None or hull.geom_type != "Polygon":
            continue  # degenerate (line/point): zero size
        xy = np.asarray(hull.exterior.coords)
        xy = xy - xy[0]
        edges = np.diff(xy, axis=0)
        lengths = np.hypot(edges[:, 0], edges[:, 1])
        edges, lengths = edges[lengths > 0], lengths[lengths > 0]
        u = edges / lengths[:, None]                     # unit edge directions
        along = xy @ u.T                                 # (points, edges)
        across = xy @ np.column_stack([-u[:, 1], u[:, 0]]).T
        ext_along = along.max(axis=0) - along.min(axis=0)
        ext_across = across.max(axis=0) - across.min(axis=0)
        k = int(np.argmin(ext_along * ext_across))
        # Side along edge k has direction u[k]; the other is perpendicular to it.
        east_along = abs(u[k, 0])
        east_across = abs(u[k, 1])
        out[i] = ((ext_along[k], ext_across[k]) if east_along >= east_across
                  else (ext_across[k], ext_along[k]))
    return out


def affine_linear_scale(transform: Affine) -> float:
    """Areal scale of an affine's linear part as a length factor, ``sqrt(|det|)``."""
    return float(np.sqrt(abs(transform.determinant)))


def linear_unit_m(crs: CRS | str) -> float:
    """Metres per unit of a projected CRS's x axis.

    Raises
    ------
    CRSError
        If the CRS is geographic (degrees are not a length).
    """
    c = CRS.from_user_input(crs)
    if not c.is_projected:
        raise CRSError(f"CRS {c.to_string()} is not projected, so box sizes in metres cannot "
                       "be read from it; work in a projected CRS (the site CRS)")
    return float(c.axis_info[0].unit_conversion_factor)


@functools.lru_cache(maxsize=64)
def _transformer(src: CRS, dst: CRS) -> Transformer:
    """A cached always-xy transformer (choosing the operation can take ~10 ms)."""
    return Transformer.from_crs(src, dst, always_xy=True)


def reproject_geometries(geoms: Sequence | np.ndarray, src_crs: CRS | str, dst_crs: CRS | str,
                         ) -> np.ndarray:
    """Reproject shapely geometries between CRSs (x, y = east, north / lon, lat).

    Raises
    ------
    CRSError
        If a coordinate cannot be transformed (outside the target CRS's domain).
    """
    src, dst = CRS.from_user_input(src_crs), CRS.from_user_input(dst_crs)
    arr = np.asarray(geoms, dtype=object).reshape(-1)
    if src == dst or arr.size == 0:
        return arr.copy()
    tr = _transformer(src, dst)

    def fn(xy: np.ndarray) -> np.ndarray:
        x, y = tr.transform(xy[:, 0], xy[:, 1])
        return np.column_stack([x, y])

    out = shapely.transform(arr, fn)
    coords = shapely.get_coordinates(out)
    if coords.size and not np.all(np.isfinite(coords)):
        raise CRSError(f"some coordinates cannot be transformed from {src.to_string()} to "
                       f"{dst.to_string()} (outside its area of use); check the inputs' CRS")
    return out
