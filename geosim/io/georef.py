"""Where an image sits on the map: the one georeference type of geosim."""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from affine import Affine
from pyproj import CRS


@dataclass(frozen=True)
class Georef:
    """An image's georeference: pixel-edge transform, CRS and size (and where it came from).

    Attributes
    ----------
    transform
        Pixel-corner -> map affine (CRS units per pixel; rasterio's convention).
    crs
        The image's CRS (pyproj; :meth:`rasterio_crs` for writing).
    width_px, height_px
        Image size, pixels.
    path
        The image file, when read from one.
    name
        A label such as a tile id (``r000_c001``), or empty.
    """

    transform: Affine
    crs: CRS
    width_px: int
    height_px: int
    path: Path | None = None
    name: str = ""

    @classmethod
    def of_dataset(cls, ds: Any, *, path: str | os.PathLike[str] | None = None,
                   name: str = "") -> Georef:
        """The georeference of an opened rasterio dataset (which must have a CRS)."""
        return cls(ds.transform, CRS.from_user_input(ds.crs.to_wkt()), ds.width, ds.height,
                   Path(path) if path is not None else None, name)

    @property
    def gsd_m(self) -> float:
        """Pixel size along x, map units (metres in a projected site CRS)."""
        return float(math.hypot(self.transform.a, self.transform.d))

    @property
    def outline(self) -> shapely.Polygon:
        """The image's outline in its own CRS (a parallelogram for rotated transforms)."""
        cols = np.array([0, self.width_px, self.width_px, 0], dtype=float)
        rows = np.array([0, 0, self.height_px, self.height_px], dtype=float)
        t = self.transform
        return shapely.Polygon(np.column_stack([t.a * cols + t.b * rows + t.c,
                                                t.d * cols + t.e * rows + t.f]))

    def rasterio_crs(self) -> Any:
        """The CRS as a :class:`rasterio.crs.CRS` (for writing GeoTIFFs)."""
        from rasterio.crs import CRS as RioCRS

        return RioCRS.from_wkt(self.crs.to_wkt())
