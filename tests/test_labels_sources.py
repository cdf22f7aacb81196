"""Reading a site's label sources: YOLO folders (whole image and patches), GeoJSON/GPKG."""

from __future__ import annotations

import datetime as dt

import geopandas as gpd
import numpy as np
import pytest
import shapely
from affine import Affine
from pyproj import Transformer

from geosim.config import FlightConfig
from geosim.errors import LabelError
from geosim.io.raster import write_geotiff
from geosim.labels.dedupe import dedupe_labels
from geosim.labels.georef import apply_affine
from geosim.labels.sources import LABEL_COLUMNS, read_flight_labels

GSD = 0.05
X0, Y0 = 260000.0, 6170000.0            # MGA 56, near Moss Vale NSW
IMG_T = Affine(GSD, 0.0, X0, 0.0, -GSD, Y0)
W, H = 400, 300                          # 20 m x 15 m
WHEN = dt.datetime(2021, 7, 15, 13, 10, tzinfo=dt.timezone(dt.timedelta(hours=10)))


def tif(path, transform, width, height, crs="EPSG:28356"):
    write_geotiff(path, np.zeros((height, width), np.uint8), transform=transform, crs=crs)
    return path


@pytest.fixture()
def flight(tmp_path):
    image = tif(tmp_path / "PA1.tif", IMG_T, W, H)
    labels = tmp_path / "labels"
    labels.mkdir()
    (labels / "classes.txt").write_text("cattle\n")
    return FlightConfig(id="PA1", image=image, acquired=WHEN, labels=labels)


def test_yolo_folder_whole_image_known_answer(flight):
    # Box pixels x 100..140, y 60..76 -> map x 5..7 m, y -3..-3.8 m from the corner.
    (flight.labels / "PA1.txt").write_text("0 0.300000 0.226667 0.100000 0.053333\n")
    gdf = read_flight_labels(flight, "EPSG:28356", base_dir=flight.image.parent)
    assert list(gdf.columns) == [*LABEL_COLUMNS, "geometry"]
    row = gdf.iloc[0]
    assert row.geometry.bounds == pytest.approx((X0 + 5.0, Y0 - 3.8, X0 + 7.0, Y0 - 3.0),
                                                abs=2e-4)   # six printed decimals
    assert (row.width_m, row.height_m) == pytest.approx((2.0, 0.8), abs=2e-4)
    assert row.flight == "PA1" and row.acquired == "2021-07-15T13:10:00+10:00"
    assert row.source_file == "labels/PA1.txt" and row.source_line == 1
    assert row.class_name == "cattle" and row.source_kind == "yolo"
    assert gdf.crs.to_epsg() == 28356


def test_yolo_into_another_site_crs_matches_pyproj(flight):
    (flight.labels / "PA1.txt").write_text("0 0.5 0.5 0.1 0.1\n")
    gdf = read_flight_labels(flight, "EPSG:32756")
    # Image centre in MGA 56, taken to WGS 84 / UTM 56S by PROJ independently.
    x, y = Transformer.from_crs("EPSG:28356", "EPSG:32756", always_xy=True).transform(
        X0 + 10.0, Y0 - 7.5)
    c = gdf.geometry.iloc[0].centroid
    assert (c.x, c.y) == pytest.approx((x, y), abs=1e-6)
    assert gdf.crs.to_epsg() == 32756


def test_yolo_on_lonlat_image_gives_sizes_in_metres(tmp_path):
    # A lon/lat image with ~5 cm pixels; boxes come out in metres in the site CRS.
    lon0, lat0 = 150.4, -34.55
    dlat = GSD / 110_950.0                       # metres per degree of latitude at 34.55 S
    dlon = GSD / (111_320.0 * np.cos(np.radians(lat0)) * 1.0009)  # ditto longitude (approx.)
    t = Affine(dlon, 0.0, lon0, 0.0, -dlat, lat0)
    image = tif(tmp_path / "F.tif", t, 400, 400, crs="EPSG:4326")
    labels = tmp_path / "lab"
    labels.mkdir()
    (labels / "classes.txt").write_text("cattle\n")
    (labels / "F.txt").write_text("0 0.5 0.5 0.1 0.05\n")   # 40 x 20 px = ~2.0 m x 1.0 m
    gdf = read_flight_labels(FlightConfig("F", image, WHEN, labels), "EPSG:32756")
    assert gdf.width_m.iloc[0] == pytest.approx(2.0, rel=3e-3)
    assert gdf.height_m.iloc[0] == pytest.approx(1.0, rel=3e-3)


def test_yolo_on_rotated_image(tmp_path):
    # Image rotated 30 degrees: a 40 x 20 px box is 2 m x 1 m on the ground whatever the angle.
    t = Affine.translation(X0, Y0) @ Affine.rotation(30.0) @ Affine.scale(GSD, -GSD)
    image = tif(tmp_path / "R.tif", t, 400, 400)
    labels = tmp_path / "lab"
    labels.mkdir()
    (labels / "classes.txt").write_text("cattle\n")
    (labels / "R.txt").write_text("0 0.25 0.5 0.1 0.05\n")
    gdf = read_flight_labels(FlightConfig("R", image, WHEN, labels), "EPSG:28356")
    assert (gdf.width_m.iloc[0], gdf.height_m.iloc[0]) == pytest.approx((2.0, 1.0))
    c = gdf.geometry.iloc[0].centroid
    assert (c.x, c.y) == pytest.approx(tuple(apply_affine(t, np.array([100.0, 200.0]))), abs=1e-9)
    assert gdf.geometry.iloc[0].area == pytest.approx(2.0)


def test_same_cow_labelled_in_two_overlapping_patches_is_one_feature(flight):
    # Two 200 x 200 px patches of PA1 overlapping by 100 px; the cow (pixels x 150..190,
    # y 80..96 of the flight image) lies in the overlap and is labelled in both.
    p0 = tif(flight.labels / "PA1_p0.tif", IMG_T, 200, 200)
    p1 = tif(flight.labels / "PA1_p1.tif", IMG_T @ Affine.translation(100, 0), 200, 200)
    assert p0.exists() and p1.exists()
    (flight.labels / "PA1_p0.txt").write_text("0 0.850000 0.440000 0.200000 0.080000\n"
                                              "0 0.200000 0.200000 0.100000 0.100000\n")
    # The second labeller drew it 2 px wider.
    (flight.labels / "PA1_p1.txt").write_text("0 0.350000 0.440000 0.210000 0.080000\n")
    gdf = read_flight_labels(flight, "EPSG:28356")
    assert len(gdf) == 3
    assert set(gdf["source_file"].str.rsplit("/", n=1).str[-1]) == {"PA1_p0.txt", "PA1_p1.txt"}
    out = dedupe_labels(gdf)
    assert len(out) == 2
    merged = out[out["n_merged"] == 2].iloc[0]
    c = merged.geometry.centroid
    assert (c.x, c.y) == pytest.approx((X0 + 170 * GSD, Y0 - 88 * GSD), abs=0.06)


def test_label_file_without_image_is_an_error(flight):
    (flight.labels / "stray.txt").write_text("0 0.5 0.5 0.1 0.1\n")
    with pytest.raises(LabelError, match="stray.txt: no image"):
        read_flight_labels(flight, "EPSG:28356")


def test_missing_classes_file_is_an_error(flight):
    (flight.labels / "classes.txt").unlink()
    (flight.labels / "PA1.txt").write_text("0 0.5 0.5 0.1 0.1\n")
    with pytest.raises(LabelError, match="classes.txt"):
        read_flight_labels(flight, "EPSG:28356")


def test_empty_folder_is_an_error(flight):
    with pytest.raises(LabelError, match="PA1.txt"):
        read_flight_labels(flight, "EPSG:28356")


def test_bad_line_names_file_and_line(flight):
    (flight.labels / "PA1.txt").write_text("0 0.5 0.5 0.1 0.1\n0 0.98 0.5 0.1 0.1\n")
    with pytest.raises(LabelError) as info:
        read_flight_labels(flight, "EPSG:28356")
    assert str(flight.labels / "PA1.txt") in str(info.value)
    assert "line 2" in str(info.value) and "outside its image" in str(info.value)


# ------------------------------------------------------------------ vector sources


def boxes_mga(centres, w=2.0, h=0.8):
    return [shapely.box(x - w / 2, y - h / 2, x + w / 2, y + h / 2) for x, y in centres]


def geojson_flight(tmp_path, gdf, suffix=".geojson"):
    image = tif(tmp_path / "PA3.tif", IMG_T, W, H)
    path = tmp_path / f"PA3{suffix}"
    gdf.to_file(path, driver="GPKG" if suffix == ".gpkg" else "GeoJSON")
    return FlightConfig("PA3", image, WHEN, path)


def test_geojson_in_lonlat_read_into_site_crs(tmp_path):
    centres = [(X0 + 5.0, Y0 - 5.0), (X0 + 12.3, Y0 - 10.1)]
    gdf = gpd.GeoDataFrame({"class": ["cattle", "cattle"]},
                           geometry=boxes_mga(centres), crs="EPSG:28356").to_crs("EPSG:4326")
    flight = geojson_flight(tmp_path, gdf)
    got = read_flight_labels(flight, "EPSG:28356")
    xy = np.array([(g.centroid.x, g.centroid.y) for g in got.geometry])
    np.testing.assert_allclose(xy, centres, atol=1e-6)
    np.testing.assert_allclose(got[["width_m", "height_m"]], [[2.0, 0.8]] * 2, atol=1e-6)
    assert got["source_line"].tolist() == [1, 2] and (got["source_kind"] == "geojson").all()


def test_gpkg_in_another_utm_zone(tmp_path):
    centres = [(X0 + 3.0, Y0 - 4.0)]
    gdf = gpd.GeoDataFrame(geometry=boxes_mga(centres), crs="EPSG:28356").to_crs("EPSG:32755")
    flight = geojson_flight(tmp_path, gdf, suffix=".gpkg")
    got = read_flight_labels(flight, "EPSG:28356")
    c = got.geometry.iloc[0].centroid
    assert (c.x, c.y) == pytest.approx(centres[0], abs=1e-6)
    assert got["class_name"].tolist() == ["cattle"] and got["source_kind"].iloc[0] == "gpkg"


@pytest.mark.parametrize("case,match", [
    ("point", "feature 2 is a Point"),
    ("unknown_class", "feature 1: class_name = 'sheep'"),
    ("outside", "feature 2 lies outside the image"),
])
def test_bad_vector_labels(tmp_path, case, match):
    geoms = boxes_mga([(X0 + 5.0, Y0 - 5.0), (X0 + 9.0, Y0 - 5.0)])
    classes = ["cattle", "cattle"]
    if case == "point":
        geoms[1] = shapely.Point(X0 + 9.0, Y0 - 5.0)
    elif case == "unknown_class":
        classes[0] = "sheep"
    else:
        geoms[1] = boxes_mga([(X0 + 50.0, Y0 - 5.0)])[0]   # 30 m east of the image
    gdf = gpd.GeoDataFrame({"class_name": classes}, geometry=geoms, crs="EPSG:28356")
    with pytest.raises(LabelError, match=match):
        read_flight_labels(geojson_flight(tmp_path, gdf), "EPSG:28356")


def test_unknown_label_format_is_an_error(tmp_path):
    image = tif(tmp_path / "PA1.tif", IMG_T, W, H)
    (tmp_path / "labels.csv").write_text("x,y\n")
    with pytest.raises(LabelError, match="neither a YOLO folder"):
        read_flight_labels(FlightConfig("PA1", image, WHEN, tmp_path / "labels.csv"),
                           "EPSG:28356")
