"""Boxes <-> map polygons: known answers and the YOLO -> geographic -> YOLO round trip.

Round trip path (the one the labels step takes, plus the RFC 7946 leg):
pixel -> map in the *image* CRS through its affine, map -> lon/lat (EPSG:4326)
-> map with PROJ, map -> pixel through the inverse affine, pixel bounding box ->
normalised box. Where precision is lost:

- the affine and its inverse in float64: about 1e-16 of the coordinate
  magnitude (1e-9 m at a UTM northing of 7e6 m = 1e-8 of a 0.05 m pixel);
- PROJ's projected -> lon/lat -> projected round trip (transverse Mercator in the
  Poder/Engsager form, Mercator in closed form): far below a micrometre;
- NOT in this path: the GeoJSON text, which stores lon/lat with 9 decimals
  (1e-9 deg = 0.11 mm north-south); that file leg is tested in
  test_labels_steps.py with its own tolerance. The GeoPackage keeps float64.

The assertion is 1e-6 in normalised units for every box, transform and CRS drawn.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
import shapely
from affine import Affine
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyproj import CRS, Transformer

from geosim.errors import CRSError
from geosim.labels.georef import (
    affine_linear_scale,
    box_centres,
    box_sides,
    boxes_to_polygons,
    linear_unit_m,
    polygon_sides,
    polygons_to_boxes,
    reproject_geometries,
)

# CRS -> (lon range, lat range) inside its area of use, for drawing an image origin.
CRS_AREAS = {
    "EPSG:32756": ((150.5, 155.5), (-40.0, -10.0)),   # WGS 84 / UTM 56S
    "EPSG:32611": ((-119.5, -114.5), (30.0, 45.0)),   # WGS 84 / UTM 11N
    "EPSG:32633": ((12.5, 17.5), (40.0, 65.0)),       # WGS 84 / UTM 33N
    "EPSG:28356": ((150.5, 155.5), (-38.0, -12.0)),   # GDA94 / MGA 56
    "EPSG:3857": ((-179.0, 179.0), (-80.0, 80.0)),    # Web Mercator
    "EPSG:4326": ((-179.0, 179.0), (-85.0, 85.0)),    # lon/lat
}


@functools.lru_cache
def from_lonlat(crs: str) -> Transformer:
    return Transformer.from_crs("EPSG:4326", crs, always_xy=True)


@st.composite
def image_georef(draw):
    """An image CRS, a (possibly rotated/sheared) transform and an image size."""
    crs = draw(st.sampled_from(sorted(CRS_AREAS)))
    (lo0, lo1), (la0, la1) = CRS_AREAS[crs]
    lon = draw(st.floats(lo0, lo1))
    lat = draw(st.floats(la0, la1))
    x0, y0 = from_lonlat(crs).transform(lon, lat)
    if crs == "EPSG:4326":
        px = draw(st.floats(1e-7, 1e-5))       # degrees: ~1 cm to ~1 m
    else:
        px = draw(st.floats(0.01, 2.0))        # metres
    py = px * draw(st.floats(0.5, 2.0))        # non-square pixels
    rot = draw(st.sampled_from([0.0, 90.0, 180.0, -90.0]) | st.floats(-180.0, 180.0))
    shear = draw(st.sampled_from([0.0]) | st.floats(-20.0, 20.0))
    transform = (Affine.translation(x0, y0) @ Affine.rotation(rot)
                 @ Affine.shear(shear, 0.0) @ Affine.scale(px, -py))
    width = draw(st.integers(16, 20000))
    height = draw(st.integers(16, 20000))
    return crs, transform, width, height


@st.composite
def yolo_boxes(draw):
    n = draw(st.integers(1, 8))
    out = []
    for _ in range(n):
        x0 = draw(st.floats(0.0, 0.99))
        y0 = draw(st.floats(0.0, 0.99))
        w = draw(st.floats(1e-4, 1.0 - x0))
        h = draw(st.floats(1e-4, 1.0 - y0))
        out.append([x0 + w / 2, y0 + h / 2, w, h])
    return np.array(out)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(georef=image_georef(), boxes=yolo_boxes())
def test_yolo_geographic_yolo_round_trip(georef, boxes):
    crs, transform, width, height = georef
    polys = boxes_to_polygons(boxes, transform, width, height)          # image CRS
    lonlat = reproject_geometries(polys, crs, "EPSG:4326")              # RFC 7946 frame
    coords = shapely.get_coordinates(lonlat)
    assert np.all(np.abs(coords[:, 0]) <= 180) and np.all(np.abs(coords[:, 1]) <= 90)
    back = reproject_geometries(lonlat, "EPSG:4326", crs)               # image CRS
    again = polygons_to_boxes(back, transform, width, height)
    np.testing.assert_allclose(again, boxes, rtol=0, atol=1e-6)


def test_north_up_known_answer():
    t = Affine(0.05, 0.0, 1000.0, 0.0, -0.05, 2000.0)   # 5 cm, origin (1000, 2000)
    boxes = np.array([[0.5, 0.5, 0.2, 0.1]])               # on a 100 x 100 px image
    poly = boxes_to_polygons(boxes, t, 100, 100)[0]
    # Pixel x 40..60, y 45..55 -> map x 1002..1003, y 1997.25..1997.75.
    assert poly.bounds == pytest.approx((1002.0, 1997.25, 1003.0, 1997.75), abs=1e-9)
    assert poly.area == pytest.approx(0.5, abs=1e-9)
    np.testing.assert_allclose(box_centres(boxes, t, 100, 100), [[1002.5, 1997.5]], atol=1e-9)
    np.testing.assert_allclose(box_sides(boxes, t, 100, 100), [[1.0, 0.5]], atol=1e-12)
    # Corner order TL, TR, BR, BL of the image.
    xy = np.asarray(poly.exterior.coords)
    np.testing.assert_allclose(xy[:4], [[1002, 1997.75], [1003, 1997.75], [1003, 1997.25],
                                        [1002, 1997.25]], atol=1e-9)


def test_rotated_transform_known_answer():
    # Image rotated 90 degrees: columns run south, rows run west.
    t = Affine(0.0, -0.1, 500.0, -0.1, 0.0, 800.0)
    boxes = np.array([[0.25, 0.5, 0.5, 0.2]])   # 200 x 100 px image: cols 0..100, rows 40..60
    poly = boxes_to_polygons(boxes, t, 200, 100)[0]
    # x = 500 - 0.1*row in [494, 496]; y = 800 - 0.1*col in [790, 800].
    assert poly.bounds == pytest.approx((494.0, 790.0, 496.0, 800.0), abs=1e-9)
    np.testing.assert_allclose(box_sides(boxes, t, 200, 100), [[10.0, 2.0]], atol=1e-12)
    np.testing.assert_allclose(box_centres(boxes, t, 200, 100), [[495.0, 795.0]], atol=1e-9)


def test_polygon_to_box_of_another_image_is_enclosing_box():
    # A 45-degree square seen by a north-up image: its box is the enclosing square.
    t = Affine(1.0, 0, 0, 0, -1.0, 100.0)
    diamond = shapely.Polygon([(50, 60), (60, 50), (50, 40), (40, 50)])
    box = polygons_to_boxes([diamond], t, 100, 100)[0]
    np.testing.assert_allclose(box, [0.5, 0.5, 0.2, 0.2], atol=1e-12)


def test_polygon_sides_width_is_the_east_west_side():
    rect = shapely.box(0, 0, 3.0, 1.0)
    np.testing.assert_allclose(polygon_sides([rect]), [[3.0, 1.0]])
    tall = shapely.box(0, 0, 1.0, 3.0)
    np.testing.assert_allclose(polygon_sides([tall]), [[1.0, 3.0]])


def test_linear_unit_and_scale():
    assert linear_unit_m("EPSG:32756") == 1.0
    assert linear_unit_m("EPSG:2229") == pytest.approx(0.3048006096)   # US survey feet
    with pytest.raises(CRSError):
        linear_unit_m("EPSG:4326")
    a = Affine.rotation(30) @ Affine.scale(1.005)
    assert affine_linear_scale(a) == pytest.approx(1.005)


def test_reprojection_matches_pyproj_for_points():
    t = Transformer.from_crs(CRS.from_epsg(28356), CRS.from_epsg(4326), always_xy=True)
    p = shapely.Point(250000.0, 6180000.0)
    out = reproject_geometries([p], "EPSG:28356", "EPSG:4326")[0]
    lon, lat = t.transform(p.x, p.y)
    assert (out.x, out.y) == pytest.approx((lon, lat), abs=1e-12)
    assert math.isclose(lat, -34.5, abs_tol=1.0)


def test_reprojection_out_of_domain_is_a_crs_error():
    with pytest.raises(CRSError):
        reproject_geometries([shapely.Point(0.0, 91.0)], "EPSG:4326", "EPSG:3857")


def test_polygon_sides_of_rotated_box_at_utm_magnitudes():
    # 2 m x 0.8 m box rotated 1e-7 to 35 degrees at a UTM northing of 6.17e6 m.
    for angle in (1e-7, 0.3, 35.0):
        box = shapely.box(260004.0, 6169994.6, 260006.0, 6169995.4)
        rot = shapely.affinity.rotate(box, angle, origin="centroid")
        np.testing.assert_allclose(polygon_sides([rot]), [[2.0, 0.8]], atol=1e-8)
    steep = shapely.affinity.rotate(shapely.box(0, 0, 2.0, 0.8), 80.0)
    np.testing.assert_allclose(polygon_sides([steep]), [[0.8, 2.0]], atol=1e-9)
