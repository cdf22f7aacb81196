"""Several flights against one satellite scene: per-flight diagnoses and a combined verdict."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.combine import combine_flights, combine_values
from geosim.diagnose.effects import get_effect
from geosim.diagnose.flights import diagnose_flights
from geosim.diagnose.grids import FlightPixels
from geosim.diagnose.simulate import QSimulator
from tests.test_diagnose_effects import textured_uav

PHI = 2
CRS_ = CRS.from_epsg(32756)
SAT_T = Affine(0.5, 0, 500000.0, 0, -0.5, 6200000.0)
SMEAR = {"length_px": 2.5, "direction_deg": 45.0}


def _eff(name, params, dbic=50.0, alts=()):
    e = {"name": name, "params": params, "delta_bic": dbic, "rmse_after": 1.0,
         "spectral_error_after": 0.1, "uncertainty": {}}
    if alts:
        e["indistinguishable_from"] = list(alts)
    return e


def _doc(effects, q=1.5):
    return {"effects": effects, "baseline": {"q": 2.0, "lv_satellite": 5.0, "lv_simulated": 5.0,
                                             "rmse": 2.0, "spectral_error": 0.3},
            "refined": {"q": q, "q_sigma": 0.01, "rmse": 1.0, "spectral_error": 0.05,
                        "physical_q_range": [0.5, 2.0]}, "candidates_delta_bic": {}}


def test_majority_rule_groups_and_circular_median():
    docs = {
        "A": _doc([_eff("misregistration", {"shift_px": [1.0, 0.0]}),
                   _eff("motion_smear", {"length_px": 2.0, "direction_deg": 176.0},
                        alts=["off_nadir_anisotropy"]),
                   _eff("compression", {"quality": 60})]),
        "B": _doc([_eff("off_nadir_anisotropy", {"sigma_px": 0.5, "azimuth_deg": 2.0}),
                   _eff("haze", {"transmission": [0.9, 0.8, 0.7],
                                 "path_radiance_dn": [5.0, 6.0, 9.0]})]),
        "C": _doc([_eff("motion_smear", {"length_px": 2.4, "direction_deg": 4.0}),
                   _eff("haze", {"transmission": [0.92, 0.82, 0.74],
                                 "path_radiance_dn": [5.0, 7.0, 11.0]}),
                   _eff("scene_change", {"n_regions": 3, "area_m2": 10.0})], q=1.7),
    }
    out = combine_flights(docs, reference="A")
    sat = {e["name"]: e for e in out["effects"] if e["scope"] == "satellite"}
    # motion (A, C) and off-nadir (B) vote together: 3/3; the name claimed most often wins
    assert set(sat) == {"motion_smear", "haze"}
    m = sat["motion_smear"]
    assert m["votes"] == "3/3" and m["indistinguishable_from"] == ["off_nadir_anisotropy"]
    # directions 176° and 4° are 8° apart across the wrap: median at 0°, spread ≈ 5.7°
    assert abs((m["params"]["direction_deg"] + 90) % 180 - 90) < 1e-6
    assert m["uncertainty"]["direction_deg"] == pytest.approx(np.std([-4, 4], ddof=1), abs=1e-6)
    assert m["params"]["length_px"] == pytest.approx(2.2)
    assert sat["haze"]["params"]["path_radiance_dn"] == pytest.approx([5.0, 6.5, 10.0])
    assert sat["haze"]["flights_claimed"] == ["B", "C"]
    # one flight of three is not a majority: compression is not claimed for the satellite
    assert "compression" in out["not_carried"] and "compression" not in sat
    # per-flight effects: the reference's misregistration heads the list; scene change of C
    # is reported per flight, not as satellite physics
    assert out["effects"][0]["name"] == "misregistration"
    assert out["effects"][0]["scope"] == "per_flight"
    assert out["per_flight_effects"]["scene_change"] == {"C": {"n_regions": 3, "area_m2": 10.0}}
    assert out["refined"]["q"] == pytest.approx(1.5)
    assert out["refined"]["q_sigma"] == pytest.approx(np.std([1.5, 1.5, 1.7], ddof=1))
    assert combine_values("x", "quality", [60, 70, 80])[0] == 70


@pytest.fixture(scope="module")
def ground():
    return textured_uav(384, seed=21)


def _loader(uav, real, q_base=None):
    def load():
        return FlightPixels.of_arrays(uav, real, sat_transform=SAT_T, crs=CRS_, phi=PHI,
                                      q_base=q_base)
    return load


def test_three_flights_one_with_local_change(ground, tmp_path):
    """Satellite with a known smear; flights A, B see the ground as it was, flight C also
    shows objects the satellite does not (a local scene change). The combined physics
    verdict is the smear with the right parameters; the change stays C's."""
    real = np.round(get_effect("motion_smear").apply(
        QSimulator(ground, phi=PHI, q_min=0.7)(1.4), **SMEAR))
    rng = np.random.default_rng(4)
    flight_b = np.clip(ground * 1.04 + rng.normal(0, 1.0, ground.shape), 0, 255)  # other camera
    flight_c = ground.copy()
    for r, c in [(60, 80), (200, 260), (300, 100), (150, 330)]:  # cattle-sized, UAV pixels
        flight_c[:, r:r + 5, c:c + 12] = 235.0
    loaders = [("A", _loader(ground, real, 1.9)), ("B", _loader(flight_b, real, 1.9)),
               ("C", _loader(flight_c, real, 1.9))]
    doc = diagnose_flights(loaders, tmp_path, reference="A", phi=PHI)
    sat = {e["name"]: e for e in doc["effects"] if e["scope"] == "satellite"}
    assert set(sat) == {"motion_smear"}, sat.keys()
    got = sat["motion_smear"]["params"]
    assert abs((got["direction_deg"] - SMEAR["direction_deg"] + 90) % 180 - 90) < 10
    assert got["length_px"] == pytest.approx(SMEAR["length_px"], abs=0.3)
    assert sat["motion_smear"]["votes"] == "3/3"
    assert set(doc["per_flight_effects"].get("scene_change", {})) == {"C"}
    # files: per flight in its folder, the reference's GeoTIFFs at the top level
    data = json.loads((tmp_path / "diagnosis.json").read_text())
    assert set(data["flights"]) == {"A", "B", "C"} and data["reference_flight"] == "A"
    for f in ("A", "B", "C"):
        assert (tmp_path / f / "diagnosis.json").is_file()
        assert data["flights"][f]["dir"] == f
    with rasterio.open(tmp_path / data["files"]["refined"]) as top, \
            rasterio.open(tmp_path / "A" / "sim_refined.tif") as ref:
        assert top.transform == ref.transform and top.crs == ref.crs
        np.testing.assert_array_equal(top.read(), ref.read())
    assert "### Flight C" in (tmp_path / "report.md").read_text()


def test_cli_two_uav_inputs(ground, tmp_path):
    """`geosim diagnose --uav A.tif --uav B.tif --satellite S.tif`: both diagnosed, combined."""
    from click.testing import CliRunner

    from geosim.cli.main import cli
    from geosim.io.raster import write_geotiff

    uav = ground[:, :256, :256]
    real = np.clip(np.round(get_effect("motion_smear").apply(
        QSimulator(uav, phi=PHI, q_min=0.7)(1.4), **SMEAR)), 0, 255).astype(np.uint8)
    write_geotiff(tmp_path / "a.tif", np.clip(uav, 0, 255).astype(np.uint8),
                  transform=Affine(0.25, 0, 500000.0, 0, -0.25, 6200000.0), crs="EPSG:32756")
    # the second flight in another CRS (GDA94 / MGA 56) and 4 % brighter
    write_geotiff(tmp_path / "b.tif", np.clip(uav * 1.04, 0, 255).astype(np.uint8),
                  transform=Affine(0.25, 0, 500000.0, 0, -0.25, 6200000.0), crs="EPSG:28356")
    write_geotiff(tmp_path / "sat.tif", real, transform=SAT_T, crs="EPSG:32756")
    res = CliRunner().invoke(cli, ["diagnose", "--uav", str(tmp_path / "a.tif"), "--uav",
                                   str(tmp_path / "b.tif"), "--satellite",
                                   str(tmp_path / "sat.tif"), "--uav-gsd", "0.25", "--out",
                                   str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    assert "flight a:" in res.output and "flight b:" in res.output
    doc = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert set(doc["flights"]) == {"a", "b"} and doc["reference_flight"] == "a"
    assert doc["combination"]["votes_needed"] == 2
    names = [e["name"] for e in doc["effects"] if e["scope"] == "satellite"]
    assert names == ["motion_smear"]
    for f in doc["files"].values():
        assert (tmp_path / "out" / f).is_file()
    assert (tmp_path / "out" / "b" / "sim_refined.tif").is_file()


def test_combined_alternative_carries_the_median_delta_bic():
    """Each flight's exact duel states by how much its claim beat the alternative on all
    blocks (ΔBIC); the combined verdict carries their median."""
    def smear(dbic_alt):
        e = _eff("motion_smear", SMEAR, alts=["off_nadir_anisotropy"])
        e["alternatives"] = [{"name": "off_nadir_anisotropy", "heldout_gain": 0.2,
                              "params": {"sigma_px": 0.8, "azimuth_deg": 45.0},
                              "delta_bic": dbic_alt}]
        return e

    docs = {"A": _doc([smear(1.0)]), "B": _doc([smear(3.0)]), "C": _doc([smear(8.0)])}
    out = combine_flights(docs, reference="A")
    (m,) = [e for e in out["effects"] if e["name"] == "motion_smear"]
    (alt,) = m["alternatives"]
    assert alt["name"] == "off_nadir_anisotropy" and alt["delta_bic"] == pytest.approx(3.0)
    assert alt["heldout_gain"] == pytest.approx(0.2)
    (amb,) = out["ambiguities"]
    assert "median ΔBIC 3.0, evidence positive" in amb["note"]
