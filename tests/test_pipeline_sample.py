"""End to end on the bundled sample site: the whole `geosim run`, then the invariants
that tie the steps together, checked with independent readers (rasterio/GDAL,
geopandas, csv) against the sample generator's truth."""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
from fractions import Fraction
from pathlib import Path

import geopandas as gpd
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner

from geosim.cli.main import cli

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run_dir(samples_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("run")
    result = CliRunner().invoke(cli, ["run", str(samples_dir / "site.toml"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


@pytest.fixture(scope="module")
def truth(samples_dir: Path) -> dict:
    return json.loads((samples_dir / "truth.json").read_text())


def test_run_json_records_every_step_and_the_inputs(run_dir: Path, samples_dir: Path) -> None:
    record = json.loads((run_dir / "run.json").read_text())
    assert record["status"] == "ok"
    assert [k for k, v in record["steps"].items() if v["status"] == "ok"] == [
        "grid", "footprints", "align", "tiles", "pairs", "labels", "calibrate", "degrade",
        "diagnose", "deliver"]
    image = samples_dir / "flights" / "PA1.tif"
    assert record["inputs"]["flights.PA1.image"]["sha256"] == \
        hashlib.sha256(image.read_bytes()).hexdigest()


def test_grids_are_nested_and_every_raster_sits_on_them(run_dir: Path) -> None:
    grid = json.loads((run_dir / "grid" / "grid.json").read_text())
    uav, sat = Affine(*grid["uav"]["transform"]), Affine(*grid["sat"]["transform"])
    phi = grid["phi"]
    assert (uav.c, uav.f) == (sat.c, sat.f)
    assert sat.a == uav.a * phi and sat.e == uav.e * phi
    for tif in sorted((run_dir / "degraded").rglob("*.tif")):
        flight, tile = tif.parent.name, tif.name
        with rasterio.open(tif) as deg, rasterio.open(run_dir / "tiles" / flight / tile) as src:
            t, s = deg.transform, src.transform
            # the degraded tile: same origin, pixel size ×φ, exactly
            assert t == Affine(s.a * phi, s.b, s.c, s.d, s.e * phi, s.f)
            assert deg.crs == src.crs and (deg.width * phi, deg.height * phi) == \
                (src.width, src.height)
            # …and its pixels are whole pixels of the satellite grid (exact rational arithmetic)
            col = (Fraction(t.c) - Fraction(sat.c)) / Fraction(sat.a)
            row = (Fraction(t.f) - Fraction(sat.f)) / Fraction(sat.e)
            assert col.denominator == 1 and row.denominator == 1, (tif, col, row)


def test_tiles_pairs_and_labels_are_consistent(run_dir: Path, truth: dict) -> None:
    index = gpd.read_file(run_dir / "tiles" / "index.geojson")
    tile_ids = sorted(index["tile_id"])
    flights = sorted(truth["flights"])
    assert tile_ids
    bounds = {}
    for flight, tile in itertools.product(flights, tile_ids):
        with rasterio.open(run_dir / "tiles" / flight / f"{tile}.tif") as ds:
            bounds.setdefault(tile, set()).add(tuple(ds.bounds))
        for res in ("yolo", "yolo_0.5m"):
            assert (run_dir / "labels" / res / flight / f"{tile}.txt").is_file()
    assert all(len(b) == 1 for b in bounds.values())  # a tile id is the same ground
    with open(run_dir / "pairs.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(tile_ids) * len(list(itertools.combinations(flights, 2)))
    for row in rows:
        assert (run_dir / row["path_a"]).is_file() and (run_dir / row["path_b"]).is_file()

    cattle = gpd.read_file(run_dir / "labels" / "cattle.gpkg", layer="cattle")
    counts = cattle.groupby("flight").size().to_dict()
    true_counts = {f: len(truth["flights"][f]["cattle"]) for f in flights}
    assert counts == true_counts


def test_calibration_and_diagnosis_outputs(run_dir: Path) -> None:
    cal = json.loads((run_dir / "calibration.json").read_text())
    qs = [v["q"] for v in cal["flights"] if v.get("q") is not None]
    assert len(qs) == 3 and abs(cal["mean_q"] - sum(qs) / 3) < 1e-9
    diag = json.loads((run_dir / "diagnosis" / "diagnosis.json").read_text())
    for key in ("grid", "baseline", "effects", "refined", "regions", "files"):
        assert key in diag
    shapes = set()
    for name in ("satellite", "baseline", "refined"):
        with rasterio.open(run_dir / "diagnosis" / diag["files"][name]) as ds:
            shapes.add((ds.crs.to_string(), tuple(ds.transform), ds.shape))
    assert len(shapes) == 1


def test_diagnosis_of_the_sample_scene_agrees_with_truth(run_dir: Path) -> None:
    """The concealed physics of the sample satellite scene, found blind by `geosim run`."""
    record = json.loads((run_dir / "run.json").read_text())
    summary = record["steps"]["diagnose"]["summary"]
    rows = {r["effect"]: r for r in summary["truth_comparison"]}
    # misregistration: satellite minus the reference flight's stated frame
    mis = rows["misregistration"]
    assert mis["fitted"] is not None
    for fitted, true in zip(mis["fitted"]["shift_m"], mis["truth"]["shift_m"], strict=True):
        assert abs(fitted - true) < 0.10
    assert abs(mis["fitted"]["rotation_deg"] - mis["truth"]["rotation_deg"]) < 0.05
    # haze: path radiance per band (the transmission is relative to PA1's own exposure)
    haze = rows["haze"]
    fitted_l, true_l = haze["fitted"]["path_radiance_dn"], haze["truth"]["path_radiance_dn"]
    for fitted, true in zip(fitted_l, true_l, strict=True):
        assert abs(fitted - true) < 0.15 * true
    assert fitted_l[2] == max(fitted_l)  # blue strongest
    # the smear is anisotropic blur along ~84°: whichever name is claimed, the direction holds
    # (with the held-out selection the weak 0.9 px smear is carried by 1-2 of 3 flights:
    # after the one-warp alignment only PA3 claims it, so the majority verdict may omit it;
    # when it is claimed its direction must hold)
    aniso = rows["motion_smear"]["fitted"] or rows.get("off_nadir_anisotropy", {}).get("fitted")
    if aniso is not None:
        direction = aniso.get("direction_deg", aniso.get("azimuth_deg"))
        true_dir = rows["motion_smear"]["truth"]["direction_deg"]
        assert abs((direction - true_dir + 90) % 180 - 90) < 15
    assert rows["sensor_noise"]["fitted"] is not None
    # the fit improves where it counts
    base, ref = summary["spectral_error"]
    assert ref <= base / 2


def test_whole_tiles_are_degraded_from_their_first_overview(run_dir: Path) -> None:
    """`geosim tile` gives whole tiles the binomial first overview and `geosim degrade`
    reads it (partial tiles: full resolution); either way the degraded tile is within 1 DN
    of the paper's operation done the straightforward way on the full tile."""
    import numpy as np

    from geosim.degrade.core import degrade_array, to_dtype
    from geosim.degrade.steps import DEGRADE_READ_TAG, READ_FULL, READ_LEVEL1
    from geosim.io.overviews import LEVEL1_TAG

    record = json.loads((run_dir / "run.json").read_text())["steps"]["degrade"]["summary"]
    q = record["q"]
    whole = 0
    for tif in sorted((run_dir / "degraded").rglob("*.tif")):
        with rasterio.open(run_dir / "tiles" / tif.parent.name / tif.name) as src:
            img, valid, tags = src.read(), src.dataset_mask() > 0, src.tags()
        with rasterio.open(tif) as deg:
            out, read_from = deg.read(), deg.tags()[DEGRADE_READ_TAG]
        assert (LEVEL1_TAG in tags) == bool(valid.all())
        assert read_from == (READ_LEVEL1 if valid.all() else READ_FULL)
        whole += bool(valid.all())
        ref, valid_out = degrade_array(img, q=q, phi=10, valid=valid, method="reference")
        diff = np.abs(out.astype(int) - to_dtype(ref, np.uint8))[:, valid_out]
        assert diff.max(initial=0) <= 1
    assert whole > 0 and record["read_from_first_overview"] == whole
