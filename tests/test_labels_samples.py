"""The bundled sample site's labels against its ground truth (``truth.json``).

Conventions used from truth.json (``conventions`` there): ``centre_stated_xy``
is each animal's label-box centre in the flight's *stated* frame, EPSG:28356;
``paddock_counts`` are per flight; paddock ``area_m2`` are planar areas in
EPSG:28356 (grid areas, which exceed ground areas by the projection's areal
scale factor). PA1 and PA2 are labelled with YOLO files, PA3 with GeoJSON.
"""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pandas as pd
import pytest
from pyproj import Proj
from scipy.spatial import cKDTree

from geosim.config import load_site
from geosim.labels.paddocks import cattle_per_paddock
from geosim.labels.sources import read_flight_labels, read_paddocks

UAV_PX_M = 0.05


@pytest.fixture(scope="module")
def sample(samples_dir):
    truth_path = samples_dir / "truth.json"
    if not truth_path.is_file():
        pytest.skip(f"{truth_path} not generated yet")
    site = load_site(samples_dir / "site.toml", check_rasters=False)
    labels = {f.id: read_flight_labels(f, "EPSG:28356", base_dir=samples_dir)
              for f in site.flights if f.labels is not None}
    return site, json.loads(truth_path.read_text()), labels


@pytest.mark.parametrize("flight,kind", [("PA1", "yolo"), ("PA2", "yolo"),
                                         ("PA3", "geojson")])
def test_label_centres_match_truth(sample, flight, kind):
    _, truth, labels = sample
    gdf = labels[flight]
    assert (gdf["source_kind"] == kind).all()
    truth_xy = np.array([c["centre_stated_xy"] for c in truth["flights"][flight]["cattle"]])
    got_xy = np.column_stack([gdf.geometry.centroid.x, gdf.geometry.centroid.y])
    assert len(got_xy) == len(truth_xy) == truth["flights"][flight]["n_cattle"]
    dist, nearest = cKDTree(truth_xy).query(got_xy)
    assert len(set(nearest.tolist())) == len(nearest), "two labels matched one animal"
    assert dist.max() <= 2 * UAV_PX_M, f"{flight}: worst label centre {dist.max():.3f} m off"


def test_cattle_per_paddock_equals_truth(sample, samples_dir):
    site, truth, labels = sample
    cattle = gpd.GeoDataFrame(pd.concat(list(labels.values()), ignore_index=True),
                              crs="EPSG:28356")
    paddocks = read_paddocks(samples_dir / "paddocks.geojson")
    table = cattle_per_paddock(cattle, paddocks)
    for flight in labels:
        got = {r.paddock: r.count for r in table[table["flight"] == flight].itertuples()}
        assert got == truth["flights"][flight]["paddock_counts"], flight
    # Geodesic areas = planar MGA areas / the areal scale factor at the site.
    lon, lat = truth["site"]["centre_lonlat"]
    k2 = Proj("EPSG:28356").get_factors(lon, lat).areal_scale
    for name, info in truth["world"]["paddocks"].items():
        area_ha = table.loc[table["paddock"] == name, "area_ha"].iloc[0]
        assert area_ha == pytest.approx(info["area_m2"] / k2 / 1e4, rel=2e-5), name


def test_stationary_cattle_found_between_flights(sample):
    """Labels moved into PA1's frame with truth's relative transforms: every animal that
    truly stood still between PA1 and PA2 is classified 'stayed', paired with itself.
    (A moved animal may by chance end up within 1 m of where another stood, so a few
    extra 'stayed' pairs are tolerated.)"""
    from affine import Affine

    from geosim.labels.movement import cattle_movement
    from geosim.labels.steps import apply_corrections

    _, truth, labels = sample
    corrections = {f: Affine(*np.ravel(truth["flights"][f]["relative_to_reference"][
        "stated_to_reference_stated"])) for f in ("PA1", "PA2")}
    both = gpd.GeoDataFrame(pd.concat([labels["PA1"], labels["PA2"]], ignore_index=True),
                            crs="EPSG:28356")
    animal = {}   # row index -> truth animal id, by label centre in the stated frame
    for f in ("PA1", "PA2"):
        cattle = truth["flights"][f]["cattle"]
        rows = np.flatnonzero(both["flight"] == f)
        xy = np.column_stack([both.geometry.centroid.x, both.geometry.centroid.y])[rows]
        _, k = cKDTree([c["centre_stated_xy"] for c in cattle]).query(xy)
        animal.update({str(r): cattle[i]["id"] for r, i in zip(rows, k, strict=True)})
    mv = cattle_movement(apply_corrections(both, corrections), "PA1", "PA2", radius_m=30.0,
                         stayed_within_m=1.0)
    true_xy = {f: {c["id"]: np.array(c["centre_xy"]) for c in truth["flights"][f]["cattle"]}
               for f in ("PA1", "PA2")}
    still = {i for i in true_xy["PA1"].keys() & true_xy["PA2"].keys()
             if np.hypot(*(true_xy["PA1"][i] - true_xy["PA2"][i])) < 1.0}
    stayed = mv[mv["category"] == "stayed"]
    pairs = {(animal[a], animal[b]) for a, b in zip(stayed["id_a"], stayed["id_b"],
                                                    strict=True)}
    assert len(still) >= 5
    assert {(i, i) for i in still} <= pairs
    assert len(pairs) - len(still) <= max(1, len(still) // 10)
