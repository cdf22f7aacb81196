"""Cattle per paddock: a spatial join of cattle centres with paddock polygons.

A cow is counted in a paddock when its box *centre* lies within the paddock
polygon (so a cow on a fence line is counted once, where most of it is).
Paddocks may come in any CRS; they are reprojected to the cattle's CRS for the
join. Paddock areas are ellipsoidal (geodesic) areas on the WGS 84 ellipsoid
computed with :class:`pyproj.Geod` from the polygons in lon/lat, so they are
the ground areas whatever CRS either input is in (a UTM grid area differs from
the ground area by the squared scale factor, up to 0.08 % inside a zone).
Paddocks must have unique, non-empty names; invalid polygons are repaired with
:func:`shapely.make_valid` and reported (:func:`check_paddocks`).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely
from pyproj import Geod

from geosim.errors import GeosimWarning, LabelError
from geosim.io.atomic import write_text

#: Row name for cattle whose centre is in no paddock.
OUTSIDE = "(outside paddocks)"

COUNT_COLUMNS = ("flight", "acquired", "paddock", "count", "area_ha", "cattle_per_ha")

_GEOD = Geod(ellps="WGS84")
_M2_PER_HA = 10_000.0


def geodesic_area_m2(geom: shapely.Geometry) -> float:
    """Area of a lon/lat (EPSG:4326, x = lon) polygon on the WGS 84 ellipsoid, m²."""
    area, _ = _GEOD.geometry_area_perimeter(geom)
    return abs(float(area))


def cattle_centres(cattle: gpd.GeoDataFrame) -> gpd.GeoSeries:
    """Centre points of cattle features, in the cattle's CRS.

    Polygon centroids are taken in a projected CRS (the cattle's own, or the
    local UTM zone when the cattle are in lon/lat); points are used as they are.
    """
    if cattle.crs is None:
        raise LabelError("cattle features have no CRS; assign one")
    geoms = cattle.geometry
    if len(geoms) and (geoms.geom_type == "Point").all():
        return geoms
    if cattle.crs.is_projected:
        return geoms.centroid
    work = cattle.estimate_utm_crs()
    return geoms.to_crs(work).centroid.to_crs(cattle.crs)


def paddock_areas_ha(paddocks: gpd.GeoDataFrame) -> np.ndarray:
    """Geodesic area of each paddock polygon, hectares."""
    lonlat = paddocks.geometry.to_crs("EPSG:4326")
    return np.array([geodesic_area_m2(g) for g in lonlat]) / _M2_PER_HA


@dataclass(frozen=True)
class PaddockRepair:
    """An invalid paddock polygon repaired with :func:`shapely.make_valid`.

    Attributes
    ----------
    name
        The paddock's name.
    reason
        Why it was invalid (GEOS's explanation, e.g. ``Self-intersection[x y]``).
    area_before_ha, area_after_ha
        Geodesic area as drawn and after the repair, hectares.
    """

    name: str
    reason: str
    area_before_ha: float
    area_after_ha: float

    def message(self) -> str:
        """One line for the user."""
        return (f"paddock '{self.name}' is an invalid polygon ({self.reason}); repaired: "
                f"area {self.area_before_ha:.3f} ha as drawn -> {self.area_after_ha:.3f} ha; "
                "check it in QGIS")


def _polygonal(geom: shapely.Geometry) -> shapely.Geometry:
    """The polygons of a geometry (make_valid may add lines or points), as one geometry."""
    parts = [g for g in shapely.get_parts(geom) if g.geom_type in ("Polygon", "MultiPolygon")]
    return shapely.union_all(parts) if parts else shapely.Polygon()


def check_paddocks(paddocks: gpd.GeoDataFrame, name_column: str = "name"
                   ) -> tuple[gpd.GeoDataFrame, list[PaddockRepair]]:
    """Paddocks fit for counting: named, unique, polygonal, valid (repaired if needed).

    Parameters
    ----------
    paddocks
        Paddock features with a CRS and a name column.
    name_column
        The paddock name attribute.

    Returns
    -------
    (geopandas.GeoDataFrame, list of PaddockRepair)
        The paddocks (invalid polygons replaced by their :func:`shapely.make_valid`
        polygonal part) and one record per repaired paddock.

    Raises
    ------
    LabelError
        The name column is missing (the message lists the columns there are), a name is
        null/empty or used twice, a feature is not a polygon, or a polygon is empty or
        collapses to nothing when repaired.
    """
    if name_column not in paddocks.columns:
        columns = [c for c in paddocks.columns if c != paddocks.geometry.name]
        raise LabelError(f"paddocks have no '{name_column}' column; columns there are: "
                         f"{', '.join(map(str, columns)) or '(none)'}; give the one holding "
                         "paddock names with --name-column")
    raw = paddocks[name_column]
    null = raw.isna() | (raw.astype(str).str.strip() == "")
    if null.any():
        raise LabelError(f"paddock feature {int(np.flatnonzero(null.to_numpy())[0])} has no "
                         f"name in column '{name_column}' ({int(null.sum())} unnamed); name "
                         "every paddock, its cattle would otherwise count as outside")
    names = raw.astype(str)
    dup = names[names.duplicated()]
    if len(dup):
        raise LabelError(f"paddock name '{dup.iloc[0]}' is used by "
                         f"{int((names == dup.iloc[0]).sum())} features; give each paddock one "
                         "(multi)polygon and a unique name (dissolve parts in QGIS)")
    geoms = paddocks.geometry
    poly = geoms.geom_type.isin(["Polygon", "MultiPolygon"])
    if not poly.all():
        bad = int(np.flatnonzero(~poly.to_numpy())[0])
        raise LabelError(f"paddock '{names.iloc[bad]}' is a {geoms.iloc[bad].geom_type}; "
                         "paddocks must be polygons")
    repairs: list[PaddockRepair] = []
    fixed = list(geoms.values)
    lonlat = geoms.to_crs("EPSG:4326")
    for i in np.flatnonzero(~shapely.is_valid(geoms.values)):
        repaired = _polygonal(shapely.make_valid(fixed[i]))
        after = shapely.make_valid(lonlat.iloc[i])
        if repaired.is_empty:
            raise LabelError(f"paddock '{names.iloc[i]}' is an invalid polygon "
                             f"({shapely.is_valid_reason(fixed[i])}) with no area left when "
                             "repaired; redraw it")
        repairs.append(PaddockRepair(
            name=names.iloc[i], reason=shapely.is_valid_reason(fixed[i]),
            area_before_ha=geodesic_area_m2(lonlat.iloc[i]) / _M2_PER_HA,
            area_after_ha=geodesic_area_m2(_polygonal(after)) / _M2_PER_HA))
        fixed[i] = repaired
    empty = shapely.is_empty(np.asarray(fixed, dtype=object))
    if empty.any():
        raise LabelError(f"paddock '{names.iloc[int(np.flatnonzero(empty)[0])]}' has an empty "
                         "geometry; draw it or remove it")
    out = paddocks.copy()
    out[name_column] = names
    return out.set_geometry(gpd.GeoSeries(fixed, index=paddocks.index, crs=paddocks.crs)), repairs


def _dissolve(paddocks: gpd.GeoDataFrame, name_column: str) -> gpd.GeoDataFrame:
    checked, repairs = check_paddocks(paddocks, name_column)
    for r in repairs:
        warnings.warn(r.message(), GeosimWarning, stacklevel=3)
    return gpd.GeoDataFrame({"paddock": checked[name_column].tolist()},
                            geometry=checked.geometry.values, crs=paddocks.crs)


def cattle_per_paddock(cattle: gpd.GeoDataFrame, paddocks: gpd.GeoDataFrame, *,
                       name_column: str = "name") -> pd.DataFrame:
    """Count cattle in each paddock in each flight.

    Parameters
    ----------
    cattle
        Cattle features (box polygons or centre points) with a ``flight`` column
        and optionally ``acquired``; any CRS.
    paddocks
        Paddock polygons with a name column; any CRS.
    name_column
        The paddock name attribute.

    Returns
    -------
    pandas.DataFrame
        Columns :data:`COUNT_COLUMNS`: one row per flight and paddock (flights in
        order of acquisition time, then id; paddocks in file order), ``count``
        (cattle whose centre lies within the paddock), ``area_ha`` (geodesic
        area, hectares) and ``cattle_per_ha`` (count / area_ha). Cattle in no
        paddock get a row named :data:`OUTSIDE` (area and density NaN) when
        there are any.
    """
    if "flight" not in cattle.columns:
        raise LabelError("cattle features have no 'flight' column")
    if paddocks.crs is None:
        raise LabelError("paddocks have no CRS; assign the CRS they were drawn in")
    pads = _dissolve(paddocks, name_column)
    pads["area_ha"] = paddock_areas_ha(pads)
    points = gpd.GeoDataFrame({"flight": cattle["flight"].astype(str).to_numpy()},
                              geometry=cattle_centres(cattle).to_numpy(), crs=cattle.crs)
    joined = gpd.sjoin(points, pads.to_crs(cattle.crs)[["paddock", "geometry"]],
                       how="left", predicate="within")
    # A cow in two overlapping paddocks counts in both; one in none counts as outside.
    joined["paddock"] = joined["paddock"].fillna(OUTSIDE)
    counts = joined.groupby(["flight", "paddock"]).size()

    acquired: dict[str, str] = {}
    if "acquired" in cattle.columns:
        for f, a in zip(cattle["flight"].astype(str), cattle["acquired"], strict=True):
            acquired.setdefault(f, "" if a is None else str(a))
    flights = sorted(dict.fromkeys(points["flight"]), key=lambda f: (acquired.get(f, ""), f))
    rows = []
    for f in flights:
        for name, area in zip(pads["paddock"], pads["area_ha"], strict=True):
            n = int(counts.get((f, name), 0))
            density = n / float(area) if area > 0 else np.nan
            rows.append((f, acquired.get(f, ""), name, n, float(area), density))
        outside = int(counts.get((f, OUTSIDE), 0))
        if outside:
            rows.append((f, acquired.get(f, ""), OUTSIDE, outside, np.nan, np.nan))
    return pd.DataFrame(rows, columns=list(COUNT_COLUMNS))


def format_counts(table: pd.DataFrame) -> str:
    """A fixed-width text table of :func:`cattle_per_paddock` output."""
    if table.empty:
        return "(no cattle)"
    show = table.drop(columns=["acquired"]).copy()
    show["area_ha"] = show["area_ha"].map(lambda v: "" if pd.isna(v) else f"{v:.3f}")
    show["cattle_per_ha"] = show["cattle_per_ha"].map(
        lambda v: "" if pd.isna(v) else f"{v:.2f}")
    return show.to_string(index=False)


def write_counts_csv(table: pd.DataFrame, path: str | os.PathLike[str]) -> Path:
    """Write :func:`cattle_per_paddock` output as CSV, atomically."""
    return write_text(path, table.to_csv(index=False, float_format="%.6g"))
