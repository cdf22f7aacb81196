"""Writing vector outputs: RFC 7946 GeoJSON (lon/lat, CCW exteriors) and GeoPackage."""

from __future__ import annotations

import os
from pathlib import Path

import geopandas as gpd
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


def write_gpkg(gdf: gpd.GeoDataFrame, path: str | os.PathLike[str], *, layer: str) -> Path:
    """Write ``gdf`` in its own CRS as a one-layer GeoPackage, atomically.

    GeoPackage 1.2 is asked for explicitly: newer GDAL writes 1.4 by default, which
    QGIS 3.22 / GDAL 3.6 (still common on desktops) open only with a warning.
    """
    with atomic_path(path) as tmp:
        gdf.to_file(tmp, driver="GPKG", layer=layer, engine="pyogrio", VERSION="1.2")
    return Path(path)
