"""Writing vector outputs: RFC 7946 GeoJSON (lon/lat, CCW exteriors) and GeoPackage."""

from __future__ import annotations

import os
from pathlib import Path

import geopandas as gpd
import pandas as pd
import shapely
from shapely.geometry.base import BaseGeometry

from geosim.io.atomic import atomic_path


def _orient_rfc7946(geom: BaseGeometry | None) -> BaseGeometry | None:
    """Exterior rings counter-clockwise, holes clockwise (RFC 7946 §3.1.6)."""
    if geom is None or geom.is_empty:
        return geom
    if geom.geom_type in ("Polygon", "MultiPolygon"):
        return shapely.orient_polygons(geom, exterior_cw=False)
    return geom


def write_geojson(gdf: gpd.GeoDataFrame, path: str | os.PathLike[str]) -> Path:
    """Write ``gdf`` as RFC 7946 GeoJSON: reprojected to EPSG:4326, rings oriented, atomic."""
    out = gdf.to_crs("EPSG:4326") if gdf.crs is not None else gdf.set_crs("EPSG:4326")
    out = out.set_geometry(out.geometry.map(_orient_rfc7946))
    with atomic_path(path) as tmp:
        # name the collection after the final file, not the temporary one
        out.to_file(tmp, driver="GeoJSON", engine="pyogrio", layer=Path(path).stem, RFC7946="YES",
                    WRITE_BBOX="YES", COORDINATE_PRECISION=9)
    return Path(path)


#: Columns holding times: written as GeoPackage DateTime fields (UTC, as the spec asks).
TIME_COLUMNS = ("acquired",)


def typed_times(gdf: gpd.GeoDataFrame) -> gpd.GeoDataFrame:
    """A copy with the ISO 8601 text of :data:`TIME_COLUMNS` as UTC datetimes.

    GeoPackage stores DateTime as UTC (``...Z``); QGIS's temporal controller and
    ``WHERE acquired > ...`` then work on the field. Empty values stay empty.
    """
    cols = [c for c in TIME_COLUMNS if c in gdf.columns
            and not pd.api.types.is_datetime64_any_dtype(gdf[c])]
    if not cols:
        return gdf
    out = gdf.copy()
    for c in cols:
        out[c] = pd.to_datetime(out[c], utc=True, format="ISO8601")
    return out


def write_gpkg(gdf: gpd.GeoDataFrame, path: str | os.PathLike[str], *, layer: str,
               append: bool = False) -> Path:
    """Write ``gdf`` in its own CRS as a GeoPackage layer, atomically.

    GeoPackage 1.2 is asked for explicitly: newer GDAL writes 1.4 by default, which
    QGIS 3.22 / GDAL 3.6 (still common on desktops) open only with a warning. Times
    (:data:`TIME_COLUMNS`) become DateTime fields (:func:`typed_times`). ``append``
    adds a layer to an existing file in place (not atomic; for files being staged).
    """
    if append:
        typed_times(gdf).to_file(path, driver="GPKG", layer=layer, engine="pyogrio")
        return Path(path)
    with atomic_path(path) as tmp:
        typed_times(gdf).to_file(tmp, driver="GPKG", layer=layer, engine="pyogrio",
                                 VERSION="1.2")
    return Path(path)
