"""The shared site grid: one projected CRS, two nested north-up grids.

The UAV grid (pixel ``uav_gsd_m``, default 0.05 m) and the satellite grid (pixel
``sat_gsd_m``, default 0.5 m) share one origin, snapped to whole multiples of
``sat_gsd_m``, so every satellite pixel is exactly ``phi × phi`` UAV pixels
(``phi = sat_gsd_m / uav_gsd_m``, a whole number).

The grid's extent is the **union** of the flights' extents (their bounding boxes
in the site CRS), snapped outward to whole satellite pixels: every flight keeps
all of its data on the grid, and pixel ``(row, col)`` is the same ground in
every flight's ``grid/<flight>.tif``. The satellite scene is cut to that same
extent (a scene usually covers far more than the flights). The *common* extent
(intersection of the flights' valid-data footprints) is found later by the
footprints step and used by alignment and tiling.

Everything here is pure (no files): CRS choice, snapping, and the
:class:`SiteGrid` container with its JSON form.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from affine import Affine
from pyproj import CRS as ProjCRS
from rasterio.crs import CRS
from rasterio.windows import Window
from rasterio.windows import bounds as window_bounds

from geosim.errors import ConfigError, CRSError, RasterError

Bounds = tuple[float, float, float, float]  # (minx, miny, maxx, maxy)

_SNAP_TOL = 1e-6  # a coordinate within this many grid steps of a multiple counts as on it


def gsd_ratio(uav_gsd_m: float, sat_gsd_m: float) -> int:
    """Whole-number ratio ``phi = sat_gsd_m / uav_gsd_m``.

    Raises
    ------
    ConfigError
        When the ratio is not a whole number ≥ 1.
    """
    if uav_gsd_m <= 0 or sat_gsd_m <= 0:
        raise ConfigError(f"uav_gsd_m={uav_gsd_m}, sat_gsd_m={sat_gsd_m}: ground sample "
                          "distances must be positive; fix [parameters] in the site file")
    ratio = sat_gsd_m / uav_gsd_m
    phi = round(ratio)
    if phi < 1 or abs(ratio - phi) > 1e-9 * max(1.0, ratio):
        raise ConfigError(f"sat_gsd_m / uav_gsd_m = {sat_gsd_m} / {uav_gsd_m} = {ratio:g} is "
                          "not a whole number; choose GSDs whose ratio is an integer (e.g. 0.5 "
                          "and 0.05)")
    return phi


def utm_crs_for_lonlat(lon: float, lat: float) -> CRS:
    """The WGS 84 / UTM zone CRS (EPSG:326zz north, 327zz south) containing a point.

    Parameters
    ----------
    lon, lat
        Longitude and latitude in degrees (WGS 84).
    """
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    zone = min(60, max(1, int(math.floor((lon + 180.0) / 6.0)) + 1))
    expected = (32600 if lat >= 0 else 32700) + zone
    infos = query_utm_crs_info(datum_name="WGS 84",
                               area_of_interest=AreaOfInterest(lon, lat, lon, lat))
    codes = sorted(int(i.code) for i in infos if i.auth_name == "EPSG")
    code = expected if (expected in codes or not codes) else codes[0]
    return CRS.from_epsg(code)


def resolve_site_crs(setting: str, lonlat_bounds: Sequence[Bounds]) -> CRS:
    """Choose the site CRS.

    Parameters
    ----------
    setting
        ``"auto"`` (the WGS 84 / UTM zone of the centroid of the union of
        ``lonlat_bounds``) or any CRS string pyproj understands (``"EPSG:28356"``,
        WKT, PROJ string). A named CRS must be projected with metre units.
    lonlat_bounds
        Extents of the flights in lon/lat degrees (EPSG:4326, x = lon), used for ``auto``.

    Raises
    ------
    CRSError
        Unknown CRS, a geographic CRS, or a CRS whose unit is not the metre.
    """
    if setting.strip().lower() == "auto":
        if not lonlat_bounds:
            raise CRSError("site crs = 'auto' needs at least one flight to find its UTM zone; "
                           "add [[flights]] or name the CRS in [site] crs")
        import shapely
        from shapely.geometry import box

        union = shapely.union_all([box(*b) for b in lonlat_bounds])
        c = union.centroid
        return utm_crs_for_lonlat(c.x, c.y)
    try:
        crs = CRS.from_user_input(setting)
    except Exception as exc:  # rasterio raises CRSError of its own
        raise CRSError(f"site crs = {setting!r} is not a CRS GDAL/PROJ knows ({exc}); use "
                       "'auto' or a code such as 'EPSG:28356'") from exc
    pcrs = ProjCRS.from_wkt(crs.to_wkt())
    if not pcrs.is_projected:
        raise CRSError(f"site crs = {setting!r} is not a projected CRS; the shared grid needs "
                       "metres: use 'auto' (UTM) or a projected CRS such as 'EPSG:28356'")
    units = {ax.unit_name.lower() for ax in pcrs.axis_info}
    if not units <= {"metre", "meter", "m"}:
        raise CRSError(f"site crs = {setting!r} has axis units {sorted(units)}, not metres; "
                       "name a projected CRS in metres")
    return crs


def _snap_down(value: float, step: float) -> float:
    k = value / step
    kr = round(k)
    return (kr if abs(k - kr) < _SNAP_TOL else math.floor(k)) * step


def _snap_up(value: float, step: float) -> float:
    k = value / step
    kr = round(k)
    return (kr if abs(k - kr) < _SNAP_TOL else math.ceil(k)) * step


@dataclass(frozen=True)
class SiteGrid:
    """Two nested north-up grids in the site CRS with one origin.

    Attributes
    ----------
    crs
        The site's projected CRS (metres).
    uav_transform
        Affine of the UAV grid: pixel ``(col, row)`` outer corner → map ``(x, y)`` in m;
        ``Affine(uav_gsd_m, 0, x0, 0, -uav_gsd_m, y0)``.
    uav_shape
        ``(rows, cols)`` of the UAV grid; both are multiples of ``phi``.
    sat_transform
        Affine of the satellite grid, same origin ``(x0, y0)``, pixel ``sat_gsd_m``.
    sat_shape
        ``(rows, cols)`` of the satellite grid = ``uav_shape / phi``.
    """

    crs: CRS
    uav_transform: Affine
    uav_shape: tuple[int, int]
    sat_transform: Affine
    sat_shape: tuple[int, int]

    @property
    def uav_gsd_m(self) -> float:
        """UAV pixel size in metres."""
        return float(self.uav_transform.a)

    @property
    def sat_gsd_m(self) -> float:
        """Satellite pixel size in metres."""
        return float(self.sat_transform.a)

    @property
    def phi(self) -> int:
        """UAV pixels per satellite pixel along each axis."""
        return gsd_ratio(self.uav_gsd_m, self.sat_gsd_m)

    @property
    def bounds(self) -> Bounds:
        """``(minx, miny, maxx, maxy)`` of the grid in the site CRS, metres."""
        rows, cols = self.sat_shape
        return window_bounds(Window(0, 0, cols, rows), self.sat_transform)

    def uav_window_transform(self, window: Window) -> Affine:
        """Transform of a UAV-grid window: the grid transform offset by whole pixels."""
        return self.uav_transform @ Affine.translation(int(window.col_off), int(window.row_off))

    def to_dict(self) -> dict[str, Any]:
        """JSON form (``grid/grid.json``): CRS as WKT and EPSG, transforms as 6 numbers."""
        epsg = self.crs.to_epsg()
        return {
            "crs_wkt": self.crs.to_wkt(),
            "crs_epsg": epsg,
            "crs": f"EPSG:{epsg}" if epsg else self.crs.to_wkt(),
            "phi": self.phi,
            "uav": {"gsd_m": self.uav_gsd_m, "transform": list(self.uav_transform)[:6],
                    "shape": list(self.uav_shape)},
            "sat": {"gsd_m": self.sat_gsd_m, "transform": list(self.sat_transform)[:6],
                    "shape": list(self.sat_shape)},
            "bounds": list(self.bounds),
            "transform_order": "a, b, c, d, e, f as in affine.Affine: x = a*col + b*row + c, "
                               "y = d*col + e*row + f (pixel corners)",
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SiteGrid:
        """Inverse of :meth:`to_dict`."""
        return cls(crs=CRS.from_wkt(d["crs_wkt"]),
                   uav_transform=Affine(*d["uav"]["transform"]),
                   uav_shape=(int(d["uav"]["shape"][0]), int(d["uav"]["shape"][1])),
                   sat_transform=Affine(*d["sat"]["transform"]),
                   sat_shape=(int(d["sat"]["shape"][0]), int(d["sat"]["shape"][1])))


def snap_grid(bounds: Bounds, crs: CRS, *, uav_gsd_m: float, sat_gsd_m: float) -> SiteGrid:
    """Nested grids covering ``bounds``, snapped outward to whole satellite pixels.

    Parameters
    ----------
    bounds
        ``(minx, miny, maxx, maxy)`` to cover, in ``crs`` units (metres).
    crs
        The site CRS.
    uav_gsd_m, sat_gsd_m
        Pixel sizes in metres; their ratio must be a whole number.

    Returns
    -------
    SiteGrid
        Origin ``(x0, y0)`` = (west, north) edge, each a whole multiple of ``sat_gsd_m``.
    """
    phi = gsd_ratio(uav_gsd_m, sat_gsd_m)
    minx, miny, maxx, maxy = (float(v) for v in bounds)
    if not (maxx > minx and maxy > miny) or not all(map(math.isfinite, bounds)):
        raise ConfigError(f"grid bounds {bounds} are empty or not finite; check the inputs' "
                          "georeference")
    x0, x1 = _snap_down(minx, sat_gsd_m), _snap_up(maxx, sat_gsd_m)
    y0, y1 = _snap_down(miny, sat_gsd_m), _snap_up(maxy, sat_gsd_m)
    sat_cols = max(1, round((x1 - x0) / sat_gsd_m))
    sat_rows = max(1, round((y1 - y0) / sat_gsd_m))
    return SiteGrid(
        crs=crs,
        uav_transform=Affine(uav_gsd_m, 0.0, x0, 0.0, -uav_gsd_m, y1),
        uav_shape=(sat_rows * phi, sat_cols * phi),
        sat_transform=Affine(sat_gsd_m, 0.0, x0, 0.0, -sat_gsd_m, y1),
        sat_shape=(sat_rows, sat_cols),
    )


def union_bounds(all_bounds: Iterable[Bounds]) -> Bounds:
    """Smallest ``(minx, miny, maxx, maxy)`` containing every box."""
    boxes = list(all_bounds)
    if not boxes:
        raise ConfigError("no extents to combine: the site has no flights")
    return (min(b[0] for b in boxes), min(b[1] for b in boxes),
            max(b[2] for b in boxes), max(b[3] for b in boxes))


def snap_window_to_sat(window: Window, phi: int, uav_shape: tuple[int, int]) -> Window:
    """Grow a UAV-grid window outward to whole satellite pixels, clipped to the grid.

    The result's offsets and sizes are multiples of ``phi`` (the grid shape is too),
    so its transform stays nested in the satellite grid.
    """
    rows, cols = uav_shape
    c0 = max(0, math.floor(window.col_off / phi) * phi)
    r0 = max(0, math.floor(window.row_off / phi) * phi)
    c1 = min(cols, math.ceil((window.col_off + window.width) / phi) * phi)
    r1 = min(rows, math.ceil((window.row_off + window.height) / phi) * phi)
    return Window(c0, r0, max(0, c1 - c0), max(0, r1 - r0))


def sat_grid_offset(uav_tf: Affine, sat_tf: Affine, phi: int, what: str) -> tuple[int, int]:
    """(row, col) of a UAV-grid raster's north-west corner on the satellite grid, whole pixels.

    Raises
    ------
    RasterError
        ``what`` is rotated, its pixel size × ``phi`` is not the satellite grid's, or its
        origin is not on a satellite pixel corner: it is not on the shared nested grid.
    """
    if uav_tf.b != 0 or uav_tf.d != 0 or sat_tf.b != 0 or sat_tf.d != 0:
        raise RasterError(f"{what}: rotated georeference; the shared grid is north-up — "
                          "re-run 'geosim grid' and 'geosim align'")
    for name, u, s in (("x", uav_tf.a, sat_tf.a), ("y", uav_tf.e, sat_tf.e)):
        if not math.isclose(u * phi, s, rel_tol=1e-9):
            raise RasterError(f"{what}: {name} pixel size {u} m × φ = {phi} is not the "
                              f"satellite grid's {s} m; both must come from the same "
                              "'geosim grid' run (re-run grid and align)")
    col = (uav_tf.c - sat_tf.c) / sat_tf.a
    row = (uav_tf.f - sat_tf.f) / sat_tf.e
    if abs(col - round(col)) > 1e-6 or abs(row - round(row)) > 1e-6:
        raise RasterError(f"{what}: its origin is {col:.6f}, {row:.6f} satellite pixels from "
                          "the satellite grid's, not a whole number: it is not on the shared "
                          "nested grid; re-run 'geosim grid' and 'geosim align'")
    return round(row), round(col)
