"""End-to-end diagnosis on small synthetic grids: control, scene change, outputs."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import diagnose_arrays
from geosim.diagnose.grids import FlightPixels, diagnose_grids
from geosim.diagnose.simulate import QSimulator
from tests.test_diagnose_effects import textured_uav

PHI = 2


@pytest.fixture(scope="module")
def uav():
    return textured_uav(384, seed=11)


def test_control_no_effect_and_no_better_fit(uav):
    sim = QSimulator(uav, phi=PHI, q_min=0.7)
    real = np.round(sim(1.4))
    d = diagnose_arrays(real, sim, q_base=1.4, rng=np.random.default_rng(0))
    s = d.summary
    assert s["effects"] == []
    assert s["refined"]["q"] == pytest.approx(1.4, rel=0.03)
    # refined no better than the baseline by more than the quantisation noise (1/12 DN²)
    assert s["baseline"]["rmse"] - s["refined"]["rmse"] < 0.05
    assert s["refined"]["q_in_physical_range"]


def test_scene_change_and_outputs(uav, tmp_path):
    sim = QSimulator(uav, phi=PHI, q_min=0.7)
    real = sim(1.4).copy()
    blobs = [(40, 50), (120, 140), (150, 30)]
    for r, c in blobs:  # cattle-sized (5 × 2 px = 2.5 m × 1 m) dark objects
        real[:, r:r + 2, c:c + 5] = 30.0
    real = np.round(real)
    transform = Affine(0.5, 0, 500000.0, 0, -0.5, 6200000.0)
    crs = CRS.from_epsg(32756)
    uav_valid = np.ones(uav.shape[-2:], bool)
    sat_valid = np.ones(real.shape[-2:], bool)
    pixels = FlightPixels.of_arrays(uav, real, sat_transform=transform, crs=crs, phi=PHI,
                                    uav_valid=uav_valid, sat_valid=sat_valid, q_base=1.4)
    doc = diagnose_grids(pixels, tmp_path, phi=PHI)
    names = [e["name"] for e in doc["effects"]]
    assert "scene_change" in names
    assert not set(names) & {"motion_smear", "atmospheric_blur", "detector_integration",
                             "off_nadir_anisotropy", "resampling", "sensor_noise"}
    # schema
    data = json.loads((tmp_path / "diagnosis.json").read_text())
    assert set(data["grid"]) == {"crs", "transform", "width", "height"}
    assert len(data["grid"]["transform"]) == 6
    for k in ("q", "lv_satellite", "lv_simulated", "rmse", "spectral_error"):
        assert isinstance(data["baseline"][k], float)
    for k in ("q", "rmse", "spectral_error"):
        assert isinstance(data["refined"][k], float)
    for e in data["effects"]:
        assert {"name", "params", "explanation", "delta_bic", "rmse_after",
                "spectral_error_after"} <= set(e)
        for k in ("delta_bic", "rmse_after", "spectral_error_after"):
            assert isinstance(e[k], float), (e["name"], k, e[k])
    assert data["regions"] == "regions.geojson"
    assert data["files"] == {"satellite": "satellite_on_grid.tif",
                             "baseline": "sim_baseline.tif", "refined": "sim_refined.tif"}
    # the three GeoTIFFs share CRS, transform and shape
    metas = []
    for f in data["files"].values():
        with rasterio.open(tmp_path / f) as ds:
            metas.append((ds.crs, ds.transform, ds.width, ds.height, ds.count))
    assert metas[0] == metas[1] == metas[2]
    assert metas[0][0] == crs and metas[0][1] == transform
    # regions: scene changes at the blobs, in lon/lat (RFC 7946)
    regions = gpd.read_file(tmp_path / "regions.geojson")
    assert regions.crs.to_epsg() == 4326
    sc = regions[regions["kind"] == "scene_change"].to_crs(crs)
    for r, c in blobs:
        x, y = transform.c + (c + 2.5) * 0.5, transform.f - (r + 1.0) * 0.5
        assert sc.distance(gpd.points_from_xy([x], [y], crs=crs)[0]).min() < 1.5
    assert (tmp_path / "report.md").read_text().startswith("# Diagnosis")
    for png in data["plots"]:
        assert (tmp_path / png).stat().st_size > 1000


def test_run_diagnose_on_run_folder(uav, tmp_path):
    """The pipeline step reads grid/satellite.tif, aligned/<flight>.tif, calibration.json."""
    from types import SimpleNamespace

    from geosim.diagnose.effects import get_effect
    from geosim.diagnose.steps import run_diagnose
    from geosim.io.atomic import write_json
    from geosim.io.raster import write_geotiff

    crs = CRS.from_epsg(32756)
    sat_t = Affine(0.5, 0, 500000.0, 0, -0.5, 6200000.0)
    uav_t = Affine(0.25, 0, 500000.0, 0, -0.25, 6200000.0)  # phi = 2 for speed
    sim = QSimulator(uav, phi=PHI, q_min=0.7)
    real = np.round(get_effect("motion_smear").apply(sim(1.4), length_px=2.5,
                                                     direction_deg=45.0))
    (tmp_path / "grid").mkdir()
    (tmp_path / "aligned").mkdir()
    write_geotiff(tmp_path / "grid" / "satellite.tif", np.clip(real, 0, 255).astype(np.uint8),
                  transform=sat_t, crs=crs)
    write_geotiff(tmp_path / "aligned" / "F1.tif", np.clip(uav, 0, 255).astype(np.uint8),
                  transform=uav_t, crs=crs)
    write_json(tmp_path / "calibration.json", {"q": 1.9})
    site = SimpleNamespace(reference_flight="F1", flights=[SimpleNamespace(id="F1")],
                           parameters=SimpleNamespace(phi=PHI, q_min=0.5, q_max=8.0))
    summary = run_diagnose(site, tmp_path).record
    assert summary["q_base"] == pytest.approx(1.9)
    assert "motion_smear" in summary["effects"]
    got = summary["effects"]["motion_smear"]
    assert abs((got["direction_deg"] - 45.0 + 90) % 180 - 90) < 10
    doc = json.loads((tmp_path / "diagnosis" / "diagnosis.json").read_text())
    assert doc["grid"]["transform"] == list(sat_t)[:6]

    # resumable: a rerun with nothing changed reuses the flight's diagnosis (files
    # untouched, same combined verdict) and says so; a changed input diagnoses it again
    flight_dir = tmp_path / "diagnosis" / "F1"
    stamps = {p: p.stat().st_mtime_ns for p in flight_dir.rglob("*") if p.is_file()}
    assert len(stamps) > 5
    again = run_diagnose(site, tmp_path)
    assert again.record["skipped_current"] == 1
    assert "1 of 1 flight diagnoses already current, skipped" in again.summary
    assert {p: p.stat().st_mtime_ns for p in flight_dir.rglob("*") if p.is_file()} == stamps
    assert set(again.outputs) >= {str(p.relative_to(tmp_path)) for p in stamps}
    assert json.loads((tmp_path / "diagnosis" / "diagnosis.json").read_text()) == doc
    write_json(tmp_path / "calibration.json", {"q": 2.1})
    changed = run_diagnose(site, tmp_path).record
    assert changed["skipped_current"] == 0 and changed["q_base"] == pytest.approx(2.1)


def test_cli_standalone_and_errors(uav, tmp_path):
    """`geosim diagnose --uav --satellite` on GeoTIFFs in two different CRSs."""
    from click.testing import CliRunner

    from geosim.cli.main import cli
    from geosim.io.raster import write_geotiff

    sim = QSimulator(uav, phi=PHI, q_min=0.7)
    real = np.clip(np.round(sim(1.4)), 0, 255).astype(np.uint8)
    # UAV in GDA94 / MGA 56, satellite in WGS 84 / UTM 56S (same projection, other datum)
    write_geotiff(tmp_path / "uav.tif", np.clip(uav, 0, 255).astype(np.uint8),
                  transform=Affine(0.25, 0, 500000.0, 0, -0.25, 6200000.0), crs="EPSG:28356")
    write_geotiff(tmp_path / "sat.tif", real,
                  transform=Affine(0.5, 0, 500000.0, 0, -0.5, 6200000.0), crs="EPSG:32756")
    runner = CliRunner()
    res = runner.invoke(cli, ["diagnose", "--uav", str(tmp_path / "uav.tif"), "--satellite",
                              str(tmp_path / "sat.tif"), "--uav-gsd", "0.25", "--out",
                              str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    doc = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert doc["grid"]["crs"] == "EPSG:32756"
    assert [e["name"] for e in doc["effects"]] == []  # a control through the whole I/O path
    with rasterio.open(tmp_path / "out" / "sim_refined.tif") as ds:
        assert ds.crs.to_epsg() == 32756
    record = json.loads((tmp_path / "out" / "run.json").read_text())  # recorded like a run
    step = record["steps"]["diagnose_images"]
    assert record["status"] == "ok" and step["status"] == "ok"
    assert "diagnosis.json" in step["outputs"] and "run.json" not in step["outputs"]
    assert record["inputs"]["satellite.image"]["path"] == str(tmp_path / "sat.tif")
    res = runner.invoke(cli, ["diagnose", "--uav", str(tmp_path / "uav.tif"), "--out",
                              str(tmp_path / "o2")])
    assert res.exit_code == 2
    assert "--satellite" in res.output


def test_compare_with_truth_rows():
    from geosim.diagnose.truth_compare import compare_with_truth, format_truth_comparison

    doc = {"baseline": {"q": 4.3}, "refined": {"q": 1.6},
           "effects": [{"name": "off_nadir_anisotropy", "params": {"sigma_px": 0.3},
                        "indistinguishable_from": ["motion_smear"]}]}
    truth = {"satellite": {"effects": {"optics": {"q": 1.5},
                                       "motion_smear": {"length_px": 1.0}}}}
    rows = {r["effect"]: r for r in compare_with_truth(doc, truth)}
    assert rows["optics"]["fitted"] == {"q": 1.6, "q_baseline": 4.3}
    assert rows["motion_smear"]["fitted"] is None and "indistinguishable" in rows[
        "motion_smear"]["note"]
    assert rows["off_nadir_anisotropy"]["truth"] is None
    assert "not present" in format_truth_comparison(list(rows.values()))
    # a missed isotropic blur is set against the detection limit the diagnosis stated
    doc["detection_limits"] = {
        "detector_integration": {"param": "pitch_px", "limit": 1.3, "absorbed_side": "below",
                                 "q": 1.6},
        "atmospheric_blur": {"param": "f0_cyc_per_px", "limit": 1.1, "absorbed_side": "above",
                             "q": 1.6}}
    truth["satellite"]["effects"].update(detector_integration={"pitch_px": 1.0},
                                         atmospheric_blur={"f0_cyc_per_px": 0.4})
    rows = {r["effect"]: r for r in compare_with_truth(doc, truth)}
    assert rows["detector_integration"]["note"] == (
        "below the stated detection limit pitch_px 1.30 at Q 1.60: absorbed into Q")
    assert rows["atmospheric_blur"]["note"].startswith("missed, though beyond")
    # an anisotropic blur's limit reads alike, but not beside a claimed member of its
    # family (that is a swap, the data showed the anisotropy)
    doc["detection_limits"]["motion_smear"] = {"param": "length_px", "limit": 1.8,
                                               "absorbed_side": "below", "q": 1.6}
    doc["effects"][0]["indistinguishable_from"] = []
    rows = {r["effect"]: r for r in compare_with_truth(doc, truth)}
    assert rows["motion_smear"]["fitted"] is None and "note" not in rows["motion_smear"]
    doc["effects"] = []
    rows = {r["effect"]: r for r in compare_with_truth(doc, truth)}
    assert rows["motion_smear"]["note"] == (
        "below the stated detection limit length_px 1.80 at Q 1.60: absorbed into Q")
