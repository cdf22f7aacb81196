"""Map polygons -> YOLO boxes for one tile (pure).

A label polygon (map coordinates, the tile's CRS) is taken into the tile's
pixel grid, clipped to the tile rectangle, and replaced by the axis-aligned
bounding box of the clipped part. The *visible fraction* is the clipped area
over the whole polygon's area (an affine scales all areas alike, so this is the
same measured in pixels or in square metres). Boxes with a visible fraction
below ``min_visible_fraction`` are dropped: a cow cut mostly off a tile is not
a useful positive there.

The 0.5 m tile of a UAV tile has the same origin and ``phi`` times the pixel
size (docs/alignment.md, "the shared grid"), so :func:`sat_tile_geometry` gives its
georeference without the degraded file existing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from affine import Affine

from geosim.errors import ConfigError
from geosim.labels.georef import pixel_bounds_to_normalised, transform_geometries

#: Relative slack when comparing a visible fraction with the threshold (float rounding).
_FRACTION_SLACK = 1e-9


@dataclass(frozen=True)
class TileBoxes:
    """Boxes of label polygons on one tile.

    Attributes
    ----------
    index
        ``(k,)`` positions of the kept polygons in the input sequence.
    boxes
        ``(k, 4)`` ``cx, cy, w, h`` normalised to the tile, clipped to it.
    visible_fraction
        ``(k,)`` area of the polygon inside the tile over its whole area, in (0, 1].
    clipped
        ``(k,)`` True where the tile edge cut the polygon.
    dropped
        Positions of polygons that touch the tile but were dropped (visible
        fraction below the threshold).
    """

    index: np.ndarray
    boxes: np.ndarray
    visible_fraction: np.ndarray
    clipped: np.ndarray
    dropped: np.ndarray

    def __len__(self) -> int:
        return int(self.index.size)


def tile_boxes(polygons: Sequence | np.ndarray, transform: Affine, width_px: int,
               height_px: int, *, min_visible_fraction: float) -> TileBoxes:
    """YOLO boxes on a tile for label polygons given in map coordinates.

    Parameters
    ----------
    polygons
        Label polygons in the tile's CRS (map units).
    transform
        The tile's pixel-corner -> map affine.
    width_px, height_px
        Tile size in pixels.
    min_visible_fraction
        Keep a box only if at least this fraction of its area lies on the tile
        (0 <= f <= 1, the site parameter ``min_visible_fraction``; with 0 any
        visible part is kept).

    Returns
    -------
    TileBoxes
        Kept boxes in input order; polygons not touching the tile are absent.
    """
    if not 0.0 <= min_visible_fraction <= 1.0:
        raise ConfigError(f"min_visible_fraction = {min_visible_fraction} must be in [0, 1]")
    geoms = np.asarray(polygons, dtype=object).reshape(-1)
    empty = TileBoxes(np.zeros(0, dtype=np.int64), np.zeros((0, 4)), np.zeros(0),
                      np.zeros(0, dtype=bool), np.zeros(0, dtype=np.int64))
    if geoms.size == 0:
        return empty
    px = transform_geometries(geoms, ~transform)
    b = shapely.bounds(px)
    touching = np.flatnonzero((b[:, 2] > 0) & (b[:, 0] < width_px)
                              & (b[:, 3] > 0) & (b[:, 1] < height_px))
    if touching.size == 0:
        return empty
    tile = shapely.box(0.0, 0.0, float(width_px), float(height_px))
    sub = px[touching]
    area = shapely.area(sub)
    inside = shapely.intersection(sub, tile)
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(area > 0, shapely.area(inside) / area, 0.0)
    keep = (fraction > 0) & (fraction >= min_visible_fraction * (1 - _FRACTION_SLACK))
    inside_bounds = shapely.bounds(inside[keep])
    # Clip the bounds to the tile: the intersection is inside it up to rounding.
    inside_bounds[:, [0, 2]] = np.clip(inside_bounds[:, [0, 2]], 0.0, float(width_px))
    inside_bounds[:, [1, 3]] = np.clip(inside_bounds[:, [1, 3]], 0.0, float(height_px))
    boxes = pixel_bounds_to_normalised(inside_bounds, width_px, height_px)
    full = b[touching][keep]
    clipped = ((full[:, 0] < 0) | (full[:, 1] < 0) | (full[:, 2] > width_px)
               | (full[:, 3] > height_px))
    nonzero = (boxes[:, 2] > 0) & (boxes[:, 3] > 0)
    return TileBoxes(
        index=touching[keep][nonzero],
        boxes=boxes[nonzero],
        visible_fraction=np.minimum(fraction[keep][nonzero], 1.0),
        clipped=clipped[nonzero],
        dropped=touching[~keep & (fraction > 0)],
    )


def sat_tile_geometry(transform: Affine, width_px: int, height_px: int, phi: int,
                      ) -> tuple[Affine, int, int]:
    """Georeference of the 0.5 m (degraded) tile of a UAV tile.

    Parameters
    ----------
    transform
        UAV tile transform (pixel corner -> map, e.g. 0.05 m pixels).
    width_px, height_px
        UAV tile size in UAV pixels; must be whole multiples of ``phi``.
    phi
        Satellite GSD / UAV GSD (whole number, 10 by default).

    Returns
    -------
    tuple
        ``(transform @ Affine.scale(phi), width_px // phi, height_px // phi)``: the same
        origin, ``phi`` times the pixel size, covering exactly the same ground.
    """
    if width_px % phi or height_px % phi:
        raise ConfigError(f"tile of {width_px} x {height_px} px is not a whole number of "
                          f"{phi} x {phi} UAV pixels, so its 0.5 m tile does not cover the same "
                          "ground; choose tile_px as a multiple of sat_gsd_m / uav_gsd_m")
    return transform @ Affine.scale(phi), width_px // phi, height_px // phi
