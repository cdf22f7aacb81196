"""The labels step end to end on a synthetic run folder with known cattle.

Truth: cattle boxes in the *aligned* frame (site CRS EPSG:32756). Flight PA1 has
YOLO labels on a UAV image in the site CRS with the identity correction; flight
PA2 has GeoJSON labels in EPSG:4326 digitised over its *stated* frame, which
differs from the aligned frame by a known similarity transform C (rotation
0.3 deg, scale 1.002, shift 0.8 m, -0.4 m). The labels step must put every cow
back on its truth box, and write YOLO files for every tile at both resolutions.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import shutil
import subprocess

import geopandas as gpd
import numpy as np
import pyogrio
import pytest
import shapely
from affine import Affine
from click.testing import CliRunner
from pyproj import Transformer
from rasterio.crs import CRS as RioCRS

from geosim.cli.main import cli
from geosim.config import FlightConfig, Parameters, SiteConfig
from geosim.errors import InputFileError, LabelError
from geosim.io.raster import write_geotiff
from geosim.labels.steps import run_labels
from geosim.labels.yolo import parse_yolo
from geosim.prepare.grid import snap_grid

SITE_CRS = "EPSG:32756"
X0, Y0 = 280000.0, 6175000.0        # north-west corner of the aligned tiles
GSD, PHI, TILE = 0.05, 10, 200      # 200 px tiles = 10 m
TILE_IDS = ["r000_c000", "r000_c001", "r001_c000", "r001_c001"]
WHEN1 = dt.datetime(2021, 7, 15, 10, 0, tzinfo=dt.timezone(dt.timedelta(hours=10)))
WHEN2 = dt.datetime(2021, 7, 15, 13, 0, tzinfo=dt.timezone(dt.timedelta(hours=10)))

# name: (cx, cy, w, h) in metres, aligned frame.
TRUTH = {
    "PA1": {
        "a": (X0 + 4.0, Y0 - 5.0, 2.0, 0.8),     # inside r000_c000
        "b": (X0 + 9.8, Y0 - 6.0, 2.0, 0.8),     # 60 % in r000_c000, 40 % in r000_c001
        "calf": (X0 + 15.0, Y0 - 15.0, 0.4, 0.3),  # r001_c001, below one 0.5 m pixel
    },
    "PA2": {
        "e": (X0 + 5.0, Y0 - 15.0, 2.2, 0.9),    # r001_c000
        "f": (X0 + 14.0, Y0 - 10.35, 1.0, 1.0),  # 35 % in r000_c001, 65 % in r001_c001
    },
}
# Where each cow must be written (min_visible_fraction 0.5).
EXPECTED_TILES = {"a": ["r000_c000"], "b": ["r000_c000"], "calf": ["r001_c001"],
                  "e": ["r001_c000"], "f": ["r001_c001"]}
CENTRE = (X0 + 10.0, Y0 - 10.0)
CORRECTION_ENTRY = {"center_m": list(CENTRE), "shift_m": [0.8, -0.4], "rotation_deg": 0.3,
                    "scale": 1.002, "confidence": 0.9}


def correction() -> Affine:
    """C(p) = centre + shift + s R(theta) (p - centre), theta counter-clockwise."""
    th, s = math.radians(0.3), 1.002
    lin = Affine(s * math.cos(th), -s * math.sin(th), 0, s * math.sin(th), s * math.cos(th), 0)
    return (Affine.translation(CENTRE[0] + 0.8, CENTRE[1] - 0.4) @ lin
            @ Affine.translation(-CENTRE[0], -CENTRE[1]))


def truth_box(cx, cy, w, h):
    return shapely.box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2)


def tile_transform(tid: str) -> Affine:
    r, c = int(tid[1:4]), int(tid[6:9])
    return Affine(GSD, 0, X0 + c * TILE * GSD, 0, -GSD, Y0 - r * TILE * GSD)


def build_run(tmp_path, *, bad_line: str | None = None):
    """A run folder (grid.json, tiles) and a site whose PA1/PA2 labels encode TRUTH."""
    out = tmp_path / "run"
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    grid = snap_grid((X0 - 5, Y0 - 25, X0 + 25, Y0 + 5), RioCRS.from_string(SITE_CRS),
                     uav_gsd_m=GSD, sat_gsd_m=GSD * PHI)
    (out / "grid").mkdir(parents=True)
    (out / "grid" / "grid.json").write_text(json.dumps(grid.to_dict()))
    for fid in ("PA1", "PA2"):
        for tid in TILE_IDS:
            (out / "tiles" / fid).mkdir(parents=True, exist_ok=True)
            write_geotiff(out / "tiles" / fid / f"{tid}.tif", np.zeros((TILE, TILE), np.uint8),
                          transform=tile_transform(tid), crs=SITE_CRS)
    # PA1: a 600 x 600 px image in the site CRS, stated frame = aligned frame; YOLO labels.
    t1 = Affine(GSD, 0, X0 - 5.0, 0, -GSD, Y0 + 5.0)
    write_geotiff(inputs / "PA1.tif", np.zeros((600, 600), np.uint8), transform=t1,
                  crs=SITE_CRS)
    (inputs / "PA1").mkdir()
    (inputs / "PA1" / "classes.txt").write_text("cattle\n")
    lines = []
    for cx, cy, w, h in TRUTH["PA1"].values():
        (c0, r0), (c1, r1) = ~t1 @ (cx - w / 2, cy + h / 2), ~t1 @ (cx + w / 2, cy - h / 2)
        lines.append(f"0 {(c0 + c1) / 1200:.6f} {(r0 + r1) / 1200:.6f} "
                     f"{(c1 - c0) / 600:.6f} {(r1 - r0) / 600:.6f}")
    if bad_line is not None:
        lines.append(bad_line)
    (inputs / "PA1" / "PA1.txt").write_text("\n".join(lines) + "\n")
    # PA2: an image in GDA94 / MGA 56 around the same ground; GeoJSON labels in lon/lat
    # digitised in the stated frame, i.e. at C^-1(truth).
    ox, oy = Transformer.from_crs(SITE_CRS, "EPSG:28356", always_xy=True).transform(
        X0 - 5.0, Y0 + 5.0)
    write_geotiff(inputs / "PA2.tif", np.zeros((600, 600), np.uint8),
                  transform=Affine(GSD, 0, ox, 0, -GSD, oy), crs="EPSG:28356")
    inv = ~correction()
    stated = [shapely.transform(truth_box(*b), lambda xy: np.column_stack(
        inv @ (xy[:, 0], xy[:, 1]))) for b in TRUTH["PA2"].values()]
    gpd.GeoDataFrame({"class_name": ["cattle"] * len(stated)}, geometry=stated,
                     crs=SITE_CRS).to_crs("EPSG:4326").to_file(inputs / "PA2.geojson",
                                                                driver="GeoJSON")
    site = SiteConfig(
        path=None, name="synthetic", crs=SITE_CRS, reference_flight="PA1",
        flights=(FlightConfig("PA1", inputs / "PA1.tif", WHEN1, inputs / "PA1"),
                 FlightConfig("PA2", inputs / "PA2.tif", WHEN2, inputs / "PA2.geojson"),
                 FlightConfig("PA3", inputs / "PA1.tif", WHEN2, None)),
        parameters=Parameters(tile_px=TILE))
    return site, out


CORRECTIONS = {"PA1": Affine.identity(), "PA2": correction()}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("labels_step")
    site, out = build_run(tmp)
    summary = run_labels(site, out, corrections=CORRECTIONS).record
    return site, out, summary


def cattle_by_name(out):
    """GPKG features keyed by truth name (matched by source order)."""
    gdf = gpd.read_file(out / "labels" / "cattle.gpkg", layer="cattle")
    names = {("PA1", 1): "a", ("PA1", 2): "b", ("PA1", 3): "calf",
             ("PA2", 1): "e", ("PA2", 2): "f"}
    return {names[(r.flight, r.source_line)]: r for r in gdf.itertuples()}, gdf


def test_cattle_land_on_their_truth_boxes(run):
    _, out, summary = run
    cattle, gdf = cattle_by_name(out)
    assert gdf.crs.equals(SITE_CRS) or gdf.crs.to_epsg() == 32756
    assert len(gdf) == 5 and summary["cattle"] == 5
    for flight, cows in TRUTH.items():
        for name, (cx, cy, w, h) in cows.items():
            r = cattle[name]
            # YOLO text has six decimals on a 600 px image: 1.5e-5 m.
            assert r.geometry.bounds == pytest.approx(truth_box(cx, cy, w, h).bounds,
                                                      abs=1e-4), name
            assert (r.centre_x, r.centre_y) == pytest.approx((cx, cy), abs=1e-4), name
            assert (r.width_m, r.height_m) == pytest.approx((w, h), abs=1e-4), name
            assert r.flight == flight
    assert bool(cattle["calf"].below_sat_pixel) and not bool(cattle["a"].below_sat_pixel)
    # a DateTime field in the GeoPackage (UTC, as the spec asks): the same instant
    assert cattle["a"].acquired.to_pydatetime() == WHEN1
    assert cattle["e"].source_kind == "geojson" and cattle["a"].source_kind == "yolo"
    for name, tiles in EXPECTED_TILES.items():
        assert cattle[name].tile_ids.split(";") == tiles, name


def test_centres_layer_and_lonlat_attributes(run):
    _, out, _ = run
    centres = gpd.read_file(out / "labels" / "cattle.gpkg", layer="cattle_centres")
    assert (centres.geom_type == "Point").all() and centres.crs.to_epsg() == 32756
    to_ll = Transformer.from_crs(SITE_CRS, "EPSG:4326", always_xy=True)
    lon, lat = to_ll.transform(centres.geometry.x.to_numpy(), centres.geometry.y.to_numpy())
    np.testing.assert_allclose(centres["centre_lon"], lon, atol=1e-9)
    np.testing.assert_allclose(centres["centre_lat"], lat, atol=1e-9)
    assert set(pyogrio.list_layers(out / "labels" / "cattle.gpkg")[:, 0]) == {
        "cattle", "cattle_centres"}


def yolo_ground(text, transform, size_px):
    """Map bounds of the boxes of a YOLO text, through the tile transform."""
    labels = parse_yolo(text, source="t", class_list=("cattle",))
    out = []
    for cx, cy, w, h in labels.boxes:
        (x0, y0) = transform @ ((cx - w / 2) * size_px, (cy - h / 2) * size_px)
        (x1, y1) = transform @ ((cx + w / 2) * size_px, (cy + h / 2) * size_px)
        out.append((min(x0, x1), min(y0, y1), max(x0, x1), max(y0, y1)))
    return out


@pytest.mark.parametrize("flight", ["PA1", "PA2"])
def test_yolo_files_for_every_tile_at_both_resolutions(run, flight):
    _, out, _ = run
    labels = out / "labels"
    assert (labels / "classes.txt").read_text() == "cattle\n"
    for tid in TILE_IDS:
        t = tile_transform(tid)
        ground = shapely.box(*(t @ (0, TILE)), *(t @ (TILE, 0)))
        expected = sorted(
            shapely.intersection(truth_box(*b), ground).bounds
            for name, b in TRUTH[flight].items() if tid in EXPECTED_TILES[name])
        uav = (labels / "yolo" / flight / f"{tid}.txt").read_text()
        sat = (labels / "yolo_0.5m" / flight / f"{tid}.txt").read_text()
        if not expected:
            assert uav == "" and sat == "", f"{flight} {tid} should be an empty file"
            continue
        got_uav = sorted(yolo_ground(uav, t, TILE))
        got_sat = sorted(yolo_ground(sat, t @ Affine.scale(PHI), TILE // PHI))
        np.testing.assert_allclose(got_uav, expected, atol=1e-4)
        # The 0.5 m box covers the same ground as the 0.05 m one (half a 0.5 m pixel).
        np.testing.assert_allclose(got_sat, got_uav, atol=0.25)
        np.testing.assert_allclose(got_sat, expected, atol=1e-3)
    assert not (labels / "yolo" / "PA3").exists()   # unlabelled flight: no negatives claimed


def test_summary(run):
    _, _, summary = run
    json.dumps(summary)
    pa1, pa2 = summary["flights"]["PA1"], summary["flights"]["PA2"]
    assert pa1["tiles"] == 4 and pa1["empty_tiles"] == 2 and pa1["boxes_uav"] == 3
    assert pa1["clipped"] == 1 and pa1["dropped_below_visible_fraction"] == 1
    assert pa2["boxes_uav"] == 2 and pa2["clipped"] == 1
    assert pa2["dropped_below_visible_fraction"] == 1
    assert pa1["below_sat_pixel"] == 1 and summary["yolo_files_per_resolution"] == 8


# ------------------------------------------------------------------ RFC 7946 GeoJSON


def test_geojson_is_rfc7946(run):
    _, out, _ = run
    doc = json.loads((out / "labels" / "cattle.geojson").read_text())
    assert doc["type"] == "FeatureCollection" and "crs" not in doc
    assert len(doc["features"]) == 5
    for feat in doc["features"]:
        assert feat["geometry"]["type"] == "Polygon"
        rings = feat["geometry"]["coordinates"]
        assert len(rings) == 1
        ring = np.array(rings[0])
        assert np.all((-180 <= ring[:, 0]) & (ring[:, 0] <= 180))
        assert np.all((-90 <= ring[:, 1]) & (ring[:, 1] <= 90))
        assert 150 < ring[0, 0] < 152 and -35 < ring[0, 1] < -34   # near Moss Vale
        assert ring[0].tolist() == ring[-1].tolist()               # closed
        assert shapely.LinearRing(ring).is_ccw                     # right-hand rule
        props = feat["properties"]
        for key in ("cattle_id", "flight", "acquired", "class_name", "source_file",
                    "source_line", "width_m", "height_m", "centre_lon", "centre_lat",
                    "below_sat_pixel", "tile_ids"):
            assert key in props, key


def test_geojson_reads_back_onto_the_gpkg(run):
    _, out, _ = run
    gj = gpd.read_file(out / "labels" / "cattle.geojson")
    gp = gpd.read_file(out / "labels" / "cattle.gpkg", layer="cattle")
    assert gj.crs.to_epsg() == 4326
    back = gj.to_crs(gp.crs)
    # GeoJSON stores 9 decimals of a degree: 0.11 mm.
    for a, b in zip(back.geometry, gp.geometry, strict=True):
        np.testing.assert_allclose(a.bounds, b.bounds, atol=2e-4)
    assert gj["cattle_id"].tolist() == gp["cattle_id"].tolist()


@pytest.mark.parametrize("reader", ["ogrinfo", "pyogrio.read_info"])
def test_geojson_opens_with_gdal(run, reader):
    _, out, _ = run
    path = out / "labels" / "cattle.geojson"
    if reader == "ogrinfo":
        exe = shutil.which("ogrinfo")
        if exe is None:
            pytest.skip("GDAL's ogrinfo is not on PATH; the same GDAL check runs through "
                        f"pyogrio.read_info (GDAL {pyogrio.__gdal_version_string__})")
        res = subprocess.run([exe, "-ro", "-al", "-so", str(path)], capture_output=True,
                             text=True, check=True)
        assert "Feature Count: 5" in res.stdout and "Polygon" in res.stdout
    else:
        info = pyogrio.read_info(path)
        assert info["features"] == 5 and info["geometry_type"] == "Polygon"
        assert info["crs"] == "EPSG:4326" and info["driver"] == "GeoJSON"


# ------------------------------------------------------------- atomicity and errors


def test_malformed_label_writes_nothing(tmp_path):
    site, out = build_run(tmp_path, bad_line="0 0.5 0.5 0.1")
    with pytest.raises(LabelError, match=r"PA1\.txt: line 4: expected 5 fields"):
        run_labels(site, out, corrections=CORRECTIONS)
    assert not (out / "labels").exists()
    assert not any(p.name.startswith(".labels") for p in out.iterdir())


def test_failed_rerun_keeps_previous_outputs(tmp_path):
    site, out = build_run(tmp_path)
    run_labels(site, out, corrections=CORRECTIONS)
    before = {p.relative_to(out): p.read_bytes() for p in (out / "labels").rglob("*")
              if p.is_file()}
    txt = site.flights[0].labels / "PA1.txt"
    txt.write_text(txt.read_text() + "0 0.99 0.5 0.1 0.1\n")      # box outside its image
    with pytest.raises(LabelError, match="outside its image"):
        run_labels(site, out, corrections=CORRECTIONS)
    after = {p.relative_to(out): p.read_bytes() for p in (out / "labels").rglob("*")
             if p.is_file()}
    assert after == before


def test_missing_tiles_is_a_clear_error(tmp_path):
    site, out = build_run(tmp_path)
    shutil.rmtree(out / "tiles")
    with pytest.raises(InputFileError, match="geosim tile"):
        run_labels(site, out, corrections=CORRECTIONS)


def test_site_without_labels_is_a_no_op(tmp_path):
    site, out = build_run(tmp_path)
    bare = SiteConfig(path=None, name="bare", crs=SITE_CRS, reference_flight="PA3",
                      flights=(site.flights[2],), parameters=site.parameters)
    result = run_labels(bare, out)
    assert result.record["cattle"] == 0 and "no flight has labels" in result.summary
    assert not (out / "labels").exists()


# ------------------------------------------------------ alignment.json and the CLI


def write_site_toml(site, path):
    f1, f2 = site.flights[0], site.flights[1]
    path.write_text(f"""
[site]
name = "synthetic"
crs = "{SITE_CRS}"
reference_flight = "PA1"

[parameters]
tile_px = {TILE}

[[flights]]
id = "PA1"
image = "{f1.image}"
acquired = "{f1.acquired.isoformat()}"
labels = "{f1.labels}"

[[flights]]
id = "PA2"
image = "{f2.image}"
acquired = "{f2.acquired.isoformat()}"
labels = "{f2.labels}"
""")
    return path


def test_cli_with_alignment_json_matches_direct_run(run, tmp_path):
    site, out, _ = run
    run2 = tmp_path / "run2"
    shutil.copytree(out / "grid", run2 / "grid")
    shutil.copytree(out / "tiles", run2 / "tiles")
    identity = {"center_m": list(CENTRE), "shift_m": [0.0, 0.0], "rotation_deg": 0.0,
                "scale": 1.0, "confidence": 1.0}
    (run2 / "alignment.json").write_text(json.dumps(
        {"reference": "PA1", "flights": {"PA1": identity, "PA2": CORRECTION_ENTRY}}))
    toml = write_site_toml(site, tmp_path / "site.toml")
    result = CliRunner().invoke(cli, ["labels", str(toml), "--out", str(run2)])
    assert result.exit_code == 0, result.output
    assert "5 cattle" in result.output
    a = gpd.read_file(out / "labels" / "cattle.gpkg", layer="cattle")
    b = gpd.read_file(run2 / "labels" / "cattle.gpkg", layer="cattle")
    for ga, gb in zip(a.geometry, b.geometry, strict=True):
        np.testing.assert_allclose(ga.bounds, gb.bounds, atol=1e-9)
    for tid in TILE_IDS:
        assert (run2 / "labels" / "yolo" / "PA2" / f"{tid}.txt").read_text() == \
            (out / "labels" / "yolo" / "PA2" / f"{tid}.txt").read_text()


def test_cli_missing_alignment_is_one_line_error(run, tmp_path):
    site, out, _ = run
    run3 = tmp_path / "run3"
    shutil.copytree(out / "grid", run3 / "grid")
    shutil.copytree(out / "tiles", run3 / "tiles")
    toml = write_site_toml(site, tmp_path / "site.toml")
    result = CliRunner().invoke(cli, ["labels", str(toml), "--out", str(run3)])
    assert result.exit_code == 2
    assert "alignment.json" in result.output and "geosim align" in result.output
    assert not (run3 / "labels").exists()


# ------------------------------------------------------------------------ resume


def test_rerun_with_nothing_changed_skips_and_a_change_rebuilds(tmp_path):
    """labels/ has a manifest entry: a rerun with the same inputs skips the step (says so,
    same outputs, files untouched); a changed label file or correction rebuilds it."""
    site, out = build_run(tmp_path)
    first = run_labels(site, out, corrections=CORRECTIONS)
    assert first.record["skipped_current"] == 0 and "skipped" not in first.summary
    files = sorted(p for p in (out / "labels").rglob("*") if p.is_file())
    stamps = {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in files}

    again = run_labels(site, out, corrections=CORRECTIONS)
    assert again.record["skipped_current"] == 1
    assert again.summary == first.summary + "; already current, skipped"
    assert again.outputs == first.outputs
    assert {k: v for k, v in again.record.items() if k != "skipped_current"} == \
        json.loads(json.dumps({k: v for k, v in first.record.items()
                               if k != "skipped_current"}))
    assert {p: (p.stat().st_mtime_ns, p.read_bytes()) for p in files} == stamps

    moved = {k: Affine.translation(0.5, 0.0) * v for k, v in CORRECTIONS.items()}
    assert run_labels(site, out, corrections=moved).record["skipped_current"] == 0
    assert run_labels(site, out, corrections=moved).record["skipped_current"] == 1

    txt = site.flights[0].labels / "PA1.txt"
    txt.write_text(txt.read_text().splitlines(keepends=True)[0] * 2)  # a duplicate box
    rebuilt = run_labels(site, out, corrections=moved)
    assert rebuilt.record["skipped_current"] == 0

    (out / "labels" / "cattle.geojson").unlink()  # an output gone: made again
    assert run_labels(site, out, corrections=moved).record["skipped_current"] == 0
    assert (out / "labels" / "cattle.geojson").is_file()
