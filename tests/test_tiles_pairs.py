"""Tiles: exact transforms, same ground per id, partial-tile rule; pairs.csv contents."""

from __future__ import annotations

import csv
import datetime as dt
import json
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.crs import CRS

from geosim.config import FlightConfig, Parameters, SiteConfig
from geosim.io.atomic import write_json
from geosim.io.raster import write_geotiff
from geosim.pipeline import run_pipeline
from geosim.prepare.grid import snap_grid
from geosim.prepare.pairs import COLUMNS, pair_rows
from geosim.prepare.steps import run_pairs, run_tiles
from geosim.prepare.tiles import iter_tiles, tile_id, tile_transform

FLIGHTS = ("PA1", "PA2", "PA3")
TILE_PX = 120
AWIN = (30, 20, 380, 270)       # aligned window on the site grid: col, row, width, height


def make_run(tmp_path: Path, *, keep_partial: bool) -> tuple[SiteConfig, Path, dict]:
    """A run folder with grid.json, alignment.json and aligned rasters (no kernels needed)."""
    crs = CRS.from_epsg(32756)
    grid = snap_grid((300000.3, 6199970.2, 300025.0, 6199990.0), crs, uav_gsd_m=0.05,
                     sat_gsd_m=0.5)
    out = tmp_path / "run"
    (out / "grid").mkdir(parents=True)
    write_json(out / "grid" / "grid.json", grid.to_dict())
    c0, r0, w, h = AWIN
    at = grid.uav_transform @ Affine.translation(c0, r0)
    write_json(out / "alignment.json", {"reference": "PA1", "aligned_grid": {
        "transform": list(at)[:6], "shape": [h, w],
        "window_px": {"col_off": c0, "row_off": r0, "width": w, "height": h}}, "flights": {}})
    rng = np.random.default_rng(1)
    images = {}
    for fid in FLIGHTS:
        img = rng.integers(0, 255, size=(3, h, w), dtype=np.uint8)
        mask = np.ones((h, w), bool)
        if fid == "PA2":
            mask[:10, 250:] = False            # PA2 misses the top of tile r000_c002
        if fid == "PA3":
            mask[:, :5] = False                # PA3 misses the left edge column of tiles
            mask[:, 5:] = True
        images[fid] = (img, mask)
        write_geotiff(out / "aligned" / f"{fid}.tif", img, transform=at, crs=crs, mask=mask)
    flights = tuple(FlightConfig(id=f, image=out / "aligned" / f"{f}.tif",
                                 acquired=dt.datetime(2021, 7, 15 + i, 11, 0,
                                                      tzinfo=dt.timezone(dt.timedelta(hours=10))))
                    for i, f in enumerate(FLIGHTS))
    site = SiteConfig(path=None, name="t", crs="auto", reference_flight="PA1", flights=flights,
                      parameters=Parameters(tile_px=TILE_PX, keep_partial_tiles=keep_partial))
    return site, out, {"grid": grid, "aligned_transform": at, "images": images}


def test_tile_ids_and_transforms_are_whole_tile_offsets():
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    tiles = list(iter_tiles((250, 370), t, 120))
    assert [x.id for x in tiles[:4]] == ["r000_c000", "r000_c001", "r000_c002", "r000_c003"]
    assert len(tiles) == 3 * 4 and tile_id(12, 3) == "r012_c003"
    for x in tiles:
        assert x.transform == t @ Affine.translation(x.col * 120, x.row * 120)
        assert tile_transform(t, x.row, x.col, 120) == x.transform


def test_tiles_full_coverage_only(tmp_path):
    site, out, info = make_run(tmp_path, keep_partial=False)
    summary = run_tiles(site, out).record
    at = info["aligned_transform"]
    # 270×380 px aligned grid, 120 px tiles: full rows 0-1, full cols 0-2; PA3 misses col 0's
    # left edge, PA2 misses the top of c002 in row 0 → kept: r000_c001, r001_c001, r001_c002
    expect = {"r000_c001", "r001_c001", "r001_c002"}
    assert summary["tiles"] == len(expect)
    for fid in FLIGHTS:
        assert {p.stem for p in (out / "tiles" / fid).glob("*.tif")} == expect
    bounds = {}
    for fid in FLIGHTS:
        img, _mask = info["images"][fid]
        for tid in sorted(expect):
            row, col = int(tid[1:4]), int(tid[6:9])
            with rasterio.open(out / "tiles" / fid / f"{tid}.tif") as ds:
                # exact: the aligned grid transform offset by whole tiles
                assert ds.transform == at @ Affine.translation(col * TILE_PX, row * TILE_PX)
                # and the site grid transform offset by whole pixels (to float precision)
                g = info["grid"].uav_transform @ Affine.translation(
                    AWIN[0] + col * TILE_PX, AWIN[1] + row * TILE_PX)
                assert ds.transform.almost_equals(g, precision=1e-9)
                assert ds.crs.to_epsg() == 32756
                assert (ds.width, ds.height) == (TILE_PX, TILE_PX)
                assert ds.profile["compress"] == "deflate"   # (tiled from 256 px up)
                assert (ds.dataset_mask() > 0).all()
                np.testing.assert_array_equal(
                    ds.read(), img[:, row * TILE_PX:(row + 1) * TILE_PX,
                                   col * TILE_PX:(col + 1) * TILE_PX])
                bounds.setdefault(tid, set()).add(tuple(ds.bounds))
    assert all(len(b) == 1 for b in bounds.values())     # same id → identical bounds
    idx = gpd.read_file(out / "tiles" / "index.geojson")
    assert idx.crs.to_epsg() == 4326 and set(idx["tile_id"]) == expect
    idx_site = gpd.read_file(out / "tiles" / "index.gpkg")
    assert idx_site.crs.to_epsg() == 32756
    for _, r in idx_site.iterrows():
        assert r.geometry.bounds == pytest.approx(next(iter(bounds[r["tile_id"]])), abs=1e-6)


def test_keep_partial_tiles_with_mask_and_pairs(tmp_path):
    site, out, info = make_run(tmp_path, keep_partial=True)
    summary = run_tiles(site, out).record
    assert summary["tiles"] == 3 * 4                       # every tile touches data
    with rasterio.open(out / "tiles" / "PA2" / "r002_c003.tif") as ds:
        m = ds.dataset_mask() > 0
        assert ds.transform == info["aligned_transform"] @ Affine.translation(360, 240)
        # aligned grid is 270 × 380: only 30 rows × 20 cols of this tile hold data
        assert m[:30, :20].all() and not m[30:].any() and not m[:, 20:].any()
        assert not ds.read()[:, ~m].any()
    with rasterio.open(out / "tiles" / "PA2" / "r000_c002.tif") as ds:
        m = ds.dataset_mask() > 0
        assert not m[:10, 10:].any() and m[10:].all()
    # an earlier run's tiles that are no longer selected are removed (by the runner, which
    # knows from run.json which files the earlier run wrote)
    import dataclasses
    import shutil

    inputs = tmp_path / "inputs"  # the runner refuses a site whose inputs are in --out
    inputs.mkdir()
    flights = []
    for f in site.flights:
        shutil.copy(f.image, inputs / f.image.name)
        flights.append(dataclasses.replace(f, image=inputs / f.image.name))
    site = dataclasses.replace(site, flights=tuple(flights))
    run_pipeline(site, out, only=["tiles"], echo=lambda s: None)
    site2, _, _ = make_run(tmp_path / "again", keep_partial=False)
    site2 = SiteConfig(**{**site2.__dict__, "flights": site.flights})
    record = run_pipeline(site2, out, only=["tiles"], echo=lambda s: None)
    assert not (out / "tiles" / "PA2" / "r002_c003.tif").exists()
    assert "tiles/PA2/r002_c003.tif" in record["cleaned"]["stale_outputs"]

    run_tiles(site, out)
    pairs = run_pairs(site, out).record
    with open(out / "pairs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == COLUMNS
    assert len(rows) == pairs["pairs"] == 12 * 3           # 3 unordered pairs per tile
    order = {f: i for i, f in enumerate(FLIGHTS)}
    for r in rows:
        assert order[r["flight_a"]] < order[r["flight_b"]]
        assert r["pair_id"] == f"{r['tile_id']}_{r['flight_a']}_{r['flight_b']}"
        assert r["crs"] == "EPSG:32756"
        assert dt.datetime.fromisoformat(r["acquired_a"]).utcoffset() == dt.timedelta(hours=10)
        for key in ("path_a", "path_b"):
            with rasterio.open(out / r[key]) as ds:
                assert ds.bounds == pytest.approx(
                    tuple(float(r[k]) for k in ("minx", "miny", "maxx", "maxy")), abs=0)
    assert len({r["pair_id"] for r in rows}) == len(rows)
    index = json.loads((out / "tiles" / "index.json").read_text())
    assert len(index["tiles"]) == 12


def test_pair_rows_only_where_both_flights_have_the_tile():
    tiles = [{"tile_id": "r000_c000", "minx": 0.0, "miny": 0.0, "maxx": 1.0, "maxy": 1.0,
              "crs": "EPSG:32756", "flights": "A,C"}]
    rows = pair_rows(tiles, ["A", "B", "C"], {"A": None, "B": None, "C": "2021-01-01"})
    assert [(r["flight_a"], r["flight_b"]) for r in rows] == [("A", "C")]
    assert rows[0]["path_b"] == "tiles/C/r000_c000.tif" and rows[0]["acquired_a"] == ""
