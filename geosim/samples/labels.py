"""Label files as people make them: YOLO text (LabelImg layout) in a flight's pixel
grid, or GeoJSON boxes in the flight's stated georeference; paddock polygons.

A label box is the axis-aligned box of the animal's outline *as it appears in
the image*: the true outline mapped through the flight's georeferencing error
into the stated frame, then into pixels.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import geopandas as gpd
import numpy as np
from affine import Affine
from shapely.geometry import Polygon, box

from geosim.io.atomic import write_text
from geosim.io.vector import write_geojson

CLASS_NAMES = ("cattle",)


def box_in_image(outline_true_xy: np.ndarray, true_to_stated: Affine, stated_transform: Affine
                 ) -> tuple[float, float, float, float]:
    """Pixel box (col_min, row_min, col_max, row_max) of an outline in a flight image.

    Parameters
    ----------
    outline_true_xy
        (N, 2) outline points in true map coordinates, metres.
    true_to_stated
        Inverse of the flight's georeferencing error.
    stated_transform
        The flight file's transform.
    """
    a = (~stated_transform) @ true_to_stated
    x, y = outline_true_xy[:, 0], outline_true_xy[:, 1]
    col = a.a * x + a.b * y + a.c
    row = a.d * x + a.e * y + a.f
    return float(col.min()), float(row.min()), float(col.max()), float(row.max())


def yolo_text(boxes_px: Sequence[tuple[float, float, float, float]], width: int, height: int
              ) -> str:
    """YOLO lines ``0 cx cy w h`` (normalised to the image, 6 decimals, as LabelImg writes)."""
    lines = []
    for c0, r0, c1, r1 in boxes_px:
        lines.append(f"0 {(c0 + c1) / 2 / width:.6f} {(r0 + r1) / 2 / height:.6f} "
                     f"{(c1 - c0) / width:.6f} {(r1 - r0) / height:.6f}")
    return "\n".join(lines) + ("\n" if lines else "")


def write_yolo_folder(folder: str | os.PathLike[str], image_stem: str,
                      boxes_px: Sequence[tuple[float, float, float, float]], width: int,
                      height: int) -> list[Path]:
    """Write ``<folder>/<image_stem>.txt`` and ``<folder>/classes.txt`` (LabelImg layout)."""
    folder = Path(folder)
    return [write_text(folder / f"{image_stem}.txt", yolo_text(boxes_px, width, height)),
            write_text(folder / "classes.txt", "\n".join(CLASS_NAMES) + "\n")]


def stated_boxes(boxes_px: Sequence[tuple[float, float, float, float]],
                 stated_transform: Affine) -> list[Polygon]:
    """Pixel boxes as polygons in the stated map frame (north-up transform assumed)."""
    out = []
    for c0, r0, c1, r1 in boxes_px:
        x0, y0 = stated_transform @ (c0, r1)
        x1, y1 = stated_transform @ (c1, r0)
        out.append(box(min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)))
    return out


def _write_geojson(gdf: gpd.GeoDataFrame, path: str | os.PathLike[str]) -> Path:
    """:func:`~geosim.io.vector.write_geojson`, then make the collection's ``name``
    the file's stem.

    GDAL names a GeoJSON collection after its layer, which ``write_geojson`` takes
    from its temporary file name (random); this keeps the output deterministic and
    is a no-op once ``write_geojson`` names the layer itself.
    """
    p = write_geojson(gdf, path)
    text = p.read_text()
    fixed = re.sub(r'^"name": ".*",$', f'"name": {json.dumps(p.stem)},', text, count=1,
                   flags=re.MULTILINE)
    if fixed != text:
        write_text(p, fixed)
    return p


def write_box_geojson(path: str | os.PathLike[str], polygons: Sequence[Polygon], crs: str
                      ) -> Path:
    """Boxes as RFC 7946 GeoJSON (lon/lat) with ``class = "cattle"``."""
    gdf = gpd.GeoDataFrame({"class": [CLASS_NAMES[0]] * len(polygons)},
                           geometry=list(polygons), crs=crs)
    return _write_geojson(gdf, path)


def write_paddocks(path: str | os.PathLike[str], paddocks: dict[str, Polygon], crs: str
                   ) -> Path:
    """Paddock polygons as RFC 7946 GeoJSON with a ``name`` attribute."""
    names = list(paddocks)
    gdf = gpd.GeoDataFrame({"name": names}, geometry=[paddocks[n] for n in names], crs=crs)
    return _write_geojson(gdf, path)
