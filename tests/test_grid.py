"""Shared grid: CRS choice, snapping to whole satellite pixels, nested transforms."""

from __future__ import annotations

import json

import pytest
from affine import Affine
from rasterio.crs import CRS
from rasterio.windows import Window

from geosim.errors import ConfigError, CRSError
from geosim.prepare.grid import (
    SiteGrid,
    gsd_ratio,
    resolve_site_crs,
    snap_grid,
    snap_window_to_sat,
    union_bounds,
    utm_crs_for_lonlat,
)


def test_gsd_ratio_whole_number_only():
    assert gsd_ratio(0.05, 0.5) == 10
    assert gsd_ratio(0.1, 0.5) == 5
    with pytest.raises(ConfigError, match="not a whole number"):
        gsd_ratio(0.03, 0.5)
    with pytest.raises(ConfigError):
        gsd_ratio(0.0, 0.5)


@pytest.mark.parametrize(("lon", "lat", "epsg"), [
    (150.4, -34.5, 32756),     # Southern Highlands NSW: UTM 56S
    (-119.73, 37.1, 32611),    # SJER California: UTM 11N
    (115.2, -8.6, 32750),      # Bali: UTM 50S
    (3.0, 0.5, 32631),         # just north of the equator
])
def test_utm_zone_of_a_point(lon, lat, epsg):
    assert utm_crs_for_lonlat(lon, lat).to_epsg() == epsg


def test_auto_crs_uses_centroid_of_union():
    # two boxes straddling the 150°E zone boundary, most of the area east of it
    crs = resolve_site_crs("auto", [(149.99, -34.6, 150.3, -34.5), (150.2, -34.6, 150.4, -34.5)])
    assert crs.to_epsg() == 32756
    crs = resolve_site_crs("AUTO", [(149.0, -34.6, 149.2, -34.5)])
    assert crs.to_epsg() == 32755


def test_named_crs_must_be_projected_metres():
    assert resolve_site_crs("EPSG:28356", []).to_epsg() == 28356
    with pytest.raises(CRSError, match="not a projected CRS"):
        resolve_site_crs("EPSG:4326", [])
    with pytest.raises(CRSError, match="not metres"):
        resolve_site_crs("EPSG:2227", [])  # California zone 3, US survey feet
    with pytest.raises(CRSError, match="not a CRS"):
        resolve_site_crs("EPSG:99999999", [])
    with pytest.raises(CRSError, match="at least one flight"):
        resolve_site_crs("auto", [])


def test_snap_grid_origin_on_sat_multiples_and_nested():
    bounds = (300000.23, 6199990.07, 300107.61, 6200041.99)
    g = snap_grid(bounds, CRS.from_epsg(32756), uav_gsd_m=0.05, sat_gsd_m=0.5)
    x0, y0 = g.uav_transform.c, g.uav_transform.f
    assert (x0, y0) == (300000.0, 6200042.0)           # snapped outward (west, north)
    assert g.sat_transform == Affine(0.5, 0.0, 300000.0, 0.0, -0.5, 6200042.0)
    assert g.uav_transform @ Affine.scale(10) == g.sat_transform   # exactly nested
    assert g.uav_shape == (g.sat_shape[0] * 10, g.sat_shape[1] * 10)
    minx, miny, maxx, maxy = g.bounds
    assert minx <= bounds[0] and miny <= bounds[1] and maxx >= bounds[2] and maxy >= bounds[3]
    # no more than one satellite pixel of padding on any side
    assert bounds[0] - minx < 0.5 and maxx - bounds[2] < 0.5
    assert bounds[1] - miny < 0.5 and maxy - bounds[3] < 0.5
    assert g.sat_shape == (round((maxy - miny) / 0.5), round((maxx - minx) / 0.5))
    assert g.phi == 10 and g.uav_gsd_m == 0.05 and g.sat_gsd_m == 0.5


def test_snap_grid_keeps_bounds_already_on_the_grid():
    g = snap_grid((100.0, 200.0, 150.0, 260.0), CRS.from_epsg(32756), uav_gsd_m=0.05,
                  sat_gsd_m=0.5)
    assert g.bounds == (100.0, 200.0, 150.0, 260.0)
    assert g.sat_shape == (120, 100) and g.uav_shape == (1200, 1000)


def test_grid_json_round_trip_and_window_transform():
    g = snap_grid((300000.2, 6199990.1, 300100.6, 6200040.0), CRS.from_epsg(32756),
                  uav_gsd_m=0.05, sat_gsd_m=0.5)
    d = json.loads(json.dumps(g.to_dict()))
    assert d["crs_epsg"] == 32756 and d["crs"] == "EPSG:32756"
    assert len(d["uav"]["transform"]) == 6
    back = SiteGrid.from_dict(d)
    assert back == g
    assert g.uav_window_transform(Window(30, 20, 5, 5)) == g.uav_transform @ Affine.translation(
        30, 20)


def test_snap_window_and_union():
    w = snap_window_to_sat(Window(13, 27, 40, 11), 10, (100, 100))
    assert (w.col_off, w.row_off, w.width, w.height) == (10, 20, 50, 20)
    w = snap_window_to_sat(Window(95, 95, 40, 40), 10, (100, 100))
    assert (w.col_off, w.row_off, w.width, w.height) == (90, 90, 10, 10)
    assert union_bounds([(0, 1, 2, 3), (-1, 2, 1, 5)]) == (-1, 1, 2, 5)
