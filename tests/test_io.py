"""Output conventions, checked with independent readers (GDAL via rasterio, shapely)."""

from __future__ import annotations

import json
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from shapely.geometry import Polygon

from geosim.io.atomic import atomic_path, write_json
from geosim.io.raster import provenance_tags, read_valid_mask, write_geotiff
from geosim.io.vector import write_geojson


def test_geotiff_has_georef_mask_tiles_and_provenance(tmp_path: Path) -> None:
    arr = np.arange(3 * 300 * 260, dtype=np.uint16).reshape(3, 300, 260) % 4000
    mask = np.ones((300, 260), bool)
    mask[:40, :] = False
    t = Affine(0.05, 0, 500000.0, 0, -0.05, 6200000.0)
    out = write_geotiff(tmp_path / "x.tif", arr, transform=t, crs="EPSG:32756", mask=mask,
                        band_descriptions=["red", "green", "blue"],
                        tags=provenance_tags("test", {"q": 1.5}, ["in.tif"]))
    with rasterio.open(out) as ds:
        assert ds.transform == t and ds.crs.to_epsg() == 32756
        assert ds.descriptions == ("red", "green", "blue")
        assert ds.block_shapes[0] == (256, 256)
        assert ds.compression is not None
        assert json.loads(ds.tags()["GEOSIM_PARAMS"]) == {"q": 1.5}
        np.testing.assert_array_equal(ds.read(), arr)
        np.testing.assert_array_equal(read_valid_mask(ds), mask)
    assert not list(tmp_path.glob(".*part*"))


def test_atomic_path_leaves_nothing_on_failure(tmp_path: Path) -> None:
    target = tmp_path / "out.json"
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed")
    assert list(tmp_path.iterdir()) == []
    write_json(target, {"a": np.float32(1.5)})
    assert json.loads(target.read_text()) == {"a": 1.5}


def test_geojson_is_rfc7946(tmp_path: Path) -> None:
    # clockwise square in UTM 56S: must come out counter-clockwise in lon/lat
    cw = Polygon([(500000, 6200000), (500000, 6200010), (500010, 6200010), (500010, 6200000)])
    assert not cw.exterior.is_ccw
    gdf = gpd.GeoDataFrame({"name": ["a"]}, geometry=[cw], crs="EPSG:32756")
    path = write_geojson(gdf, tmp_path / "a.geojson")
    doc = json.loads(path.read_text())
    ring = doc["features"][0]["geometry"]["coordinates"][0]
    assert ring[0] == ring[-1]
    assert shapely.LinearRing(ring).is_ccw
    lon, lat = ring[0]
    assert 150 < lon < 154 and -35 < lat < -33
    back = gpd.read_file(path).to_crs("EPSG:32756")
    # 9 decimals of a degree is ~0.1 mm: the round trip lands within a millimetre
    assert back.geometry.iloc[0].hausdorff_distance(cw) < 1e-3


def test_geojson_collection_is_named_after_the_final_file(tmp_path: Path) -> None:
    gdf = gpd.GeoDataFrame({"a": [1]}, geometry=[shapely.Point(151, -34)], crs="EPSG:4326")
    doc = json.loads(write_geojson(gdf, tmp_path / "cattle.geojson").read_text())
    assert doc["name"] == "cattle"


def test_gpkg_is_version_1_2_in_its_crs(tmp_path: Path) -> None:
    import sqlite3

    from geosim.io.vector import write_gpkg

    gdf = gpd.GeoDataFrame({"a": [1]}, geometry=[shapely.Point(500000, 6200000)],
                           crs="EPSG:32756")
    path = write_gpkg(gdf, tmp_path / "x.gpkg", layer="x")
    with sqlite3.connect(path) as con:  # the GeoPackage spec's version lives in user_version
        assert con.execute("PRAGMA user_version").fetchone()[0] == 10200
    assert gpd.read_file(path, layer="x").crs.to_epsg() == 32756


def test_provenance_sources_relative_to_the_run_folder(tmp_path: Path) -> None:
    inside = tmp_path / "run" / "aligned" / "PA1.tif"
    outside = tmp_path / "inputs" / "PA1.tif"
    tags = provenance_tags("tiles", {}, [inside, outside], base_dir=tmp_path / "run")
    assert json.loads(tags["GEOSIM_SOURCES"]) == ["aligned/PA1.tif", str(outside)]


def test_read_raster_window_round_trip(tmp_path: Path) -> None:
    """read_raster gives the window's pixels, mask and transform (written with plain rasterio)."""
    from affine import Affine
    from rasterio.windows import Window

    from geosim.io.raster import read_raster
    from tests.helpers import textured_rgb, write_raster

    img = textured_rgb(40, 60, seed=3)
    img[:, :5, :] = 0  # nodata rows
    t = Affine(0.05, 0, 250000.0, 0, -0.05, 6190000.0)
    path = write_raster(tmp_path / "r.tif", img, transform=t, nodata=0)
    data = read_raster(path, window=Window(10, 2, 30, 20))
    np.testing.assert_array_equal(data.array, img[:, 2:22, 10:40])
    assert data.valid.shape == (20, 30) and not data.valid[:3].any() and data.valid[3:].all()
    assert data.transform == Affine(0.05, 0, 250000.0 + 10 * 0.05, 0, -0.05,
                                    6190000.0 - 2 * 0.05)
    assert data.crs.to_epsg() == 28356 and data.nodata == 0 and data.shape == (20, 30)
    assert data.band_names == (None, None, None)


def test_to_jsonable_nan_to_null_gives_strict_json() -> None:
    """The one JSON converter: numpy values become plain JSON; with ``nan_to_null`` the
    non-finite floats become null, so a strict reader (no NaN literal) accepts the text."""
    from geosim.io.atomic import to_jsonable

    doc = {"a": np.float64("nan"), "b": [np.inf, 1.5, np.int64(2)], 3: (np.bool_(True),),
           "c": np.array([[1.0, -np.inf]], dtype=np.float32)}
    plain = to_jsonable(doc)
    assert np.isnan(plain["a"]) and plain["b"][0] == float("inf")
    strict = to_jsonable(doc, nan_to_null=True)
    assert strict == {"a": None, "b": [None, 1.5, 2], "3": [True], "c": [[1.0, None]]}

    def refuse(token: str) -> float:
        raise ValueError(token)

    assert json.loads(json.dumps(strict), parse_constant=refuse) == strict


def test_read_window_boundless_and_max_bands(tmp_path: Path) -> None:
    """The typed read edge: a window reaching outside the raster reads as 0 and invalid
    there, the window transform places it, ``max_bands`` keeps the first bands."""
    from rasterio.windows import Window

    from geosim.io.raster import read_raster

    data = np.arange(1, 4 * 20 * 30 + 1, dtype=np.uint16).reshape(4, 20, 30)  # no alpha
    t = Affine(0.5, 0, 500_000.0, 0, -0.5, 6_200_000.0)
    path = tmp_path / "r.tif"
    with rasterio.open(path, "w", driver="GTiff", width=30, height=20, count=4, dtype="uint16",
                       crs="EPSG:32756", transform=t, nodata=None) as ds:
        ds.write(data)
        ds.descriptions = ("r", "g", "b", "nir")
    got = read_raster(path, window=Window(-5, 10, 20, 15), max_bands=3, boundless=True)
    assert got.array.shape == (3, 15, 20) and got.band_names == ("r", "g", "b")
    assert got.transform == t * Affine.translation(-5, 10)
    assert np.array_equal(got.array[:, :10, 5:], data[:3, 10:20, 0:15])
    assert not got.array[:, :, :5].any() and not got.array[:, 10:, :].any()
    assert got.valid[:10, 5:].all() and not got.valid[:, :5].any() and not got.valid[10:].any()
    inside = read_raster(path, window=Window(2, 3, 10, 5))
    assert inside.array.shape == (4, 5, 10) and inside.valid.all()
    assert np.array_equal(inside.array, data[:, 3:8, 2:12])


def test_cog_is_fast_deflate_yet_decodes_exactly_with_gdal(tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch
                                                           ) -> None:
    """Level-1 deflate COG, raw or zstd scratch: same decoded pixels/mask; GDAL 3.6 reads it."""
    import shutil
    import subprocess

    import geosim.io.cog as cog

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (3, 700, 600), dtype=np.uint8)
    mask = np.ones((700, 600), bool)
    mask[:40] = False
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    assert cog.scratch_options({"width": 600, "height": 700, "count": 3,
                                "dtype": "uint8"})["compress"] == "none"
    raw = write_geotiff(tmp_path / "raw.tif", img, transform=t, crs="EPSG:32756", mask=mask)
    monkeypatch.setattr(cog, "SCRATCH_RAW_MAX_BYTES", 0)  # force the zstd scratch path
    assert cog.scratch_options({"width": 600, "height": 700, "count": 3,
                                "dtype": "uint8"})["compress"] == "zstd"
    zst = write_geotiff(tmp_path / "zst.tif", img, transform=t, crs="EPSG:32756", mask=mask)
    for path in (raw, zst):
        with rasterio.open(path) as ds:
            assert ds.compression.name.lower() == "deflate"
            assert ds.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert ds.overviews(1) == [2, 4]  # down to one 256 px block
            np.testing.assert_array_equal(ds.read(), img)
            np.testing.assert_array_equal(ds.read_masks(1) > 0, mask)
            assert ds.transform == t
    assert not list(tmp_path.glob("*scratch*"))
    gdalinfo = shutil.which("gdalinfo", path="/usr/bin")
    if gdalinfo is None:
        pytest.skip("Debian's gdalinfo not installed")
    info = json.loads(subprocess.run([gdalinfo, "-json", "-checksum", str(raw)], check=True,
                                     capture_output=True, text=True).stdout)
    assert info["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"] == "DEFLATE"
    assert info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
    assert info["bands"][0]["mask"]["flags"] == ["PER_DATASET"]
    assert len(info["bands"][0]["overviews"]) == 2
