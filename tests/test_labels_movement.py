"""Movement between flights: one-to-one matching within a radius, four categories."""

from __future__ import annotations

import json

import geopandas as gpd
import numpy as np
import pytest
import shapely
from click.testing import CliRunner

from geosim.cli.main import cli
from geosim.errors import LabelError
from geosim.labels.movement import cattle_movement, match_points, movement_summary

X0, Y0 = 280000.0, 6175000.0


def herd():
    """PA1 -> PA2 with known fates.

    c1 stays (0.3 m), c2 moves 6 m east, c3 goes, n4 appears far away, and c5/c6 form a
    trap for greedy nearest-neighbour matching: c5 is 1.0 m from both n5 and n6, c6 is
    1.5 m from n6 and 3.5 m from n5. Greedy may pair c5-n6 and c6-n5 (4.5 m in all);
    the optimal assignment pairs c5-n5 and c6-n6 (2.5 m).
    """
    a = {"c1": (0.0, 0.0), "c2": (20.0, 0.0), "c3": (40.0, 40.0),
         "c5": (60.0, 0.0), "c6": (62.5, 0.0)}
    b = {"n1": (0.3, 0.0), "n2": (26.0, 0.0), "n4": (90.0, 90.0),
         "n5": (59.0, 0.0), "n6": (61.0, 0.0)}
    rows, geoms = [], []
    for flight, pts in (("PA1", a), ("PA2", b)):
        for cid, (x, y) in pts.items():
            rows.append({"cattle_id": cid, "flight": flight})
            geoms.append(shapely.box(X0 + x - 1.0, Y0 + y - 0.4, X0 + x + 1.0, Y0 + y + 0.4))
    return gpd.GeoDataFrame(rows, geometry=geoms, crs="EPSG:32756")


def test_categories_recovered():
    mv = cattle_movement(herd(), "PA1", "PA2", radius_m=10.0, stayed_within_m=1.0)
    fate = {(r.id_a, r.id_b): r.category for r in mv.itertuples()}
    assert fate[("c1", "n1")] == "stayed"
    assert fate[("c2", "n2")] == "moved"
    assert fate[("c3", "")] == "gone"
    assert fate[("", "n4")] == "appeared"
    assert fate[("c5", "n5")] == "stayed"        # 1.0 m, at the stay threshold
    assert fate[("c6", "n6")] == "moved"         # 1.5 m
    assert movement_summary(mv) == {"stayed": 2, "moved": 2, "gone": 1, "appeared": 1}
    d = dict(zip(mv["id_a"], mv["distance_m"], strict=True))
    assert d["c2"] == pytest.approx(6.0) and d["c1"] == pytest.approx(0.3)
    assert mv.geometry[mv["category"] == "moved"].geom_type.eq("LineString").all()
    assert mv.geometry[mv["category"] == "gone"].geom_type.eq("Point").all()


def test_radius_gates_matches():
    mv = cattle_movement(herd(), "PA1", "PA2", radius_m=5.0)
    s = movement_summary(mv)
    # c2 moved 6 m: beyond a 5 m radius it is gone and n2 appeared.
    assert s == {"stayed": 2, "moved": 1, "gone": 2, "appeared": 2}


def test_assignment_maximises_matches_before_distance():
    # Greedy nearest neighbour would pair a1-b0 (0.5 m) and leave a0 unmatched.
    a = np.array([[0.0, 0.0], [1.5, 0.0]])
    b = np.array([[1.0, 0.0], [3.0, 0.0]])
    pairs, dist = match_points(a, b, radius_m=1.6)
    assert pairs.tolist() == [[0, 0], [1, 1]]
    np.testing.assert_allclose(dist, [1.0, 1.5])


def test_matching_is_one_to_one_on_a_random_herd():
    rng = np.random.default_rng(3)
    a = rng.uniform(0, 200, (400, 2))
    perm = rng.permutation(400)
    b = a[perm] + rng.normal(0, 0.2, (400, 2))      # everyone stayed, shuffled
    pairs, dist = match_points(a, b, radius_m=2.0)
    assert len(np.unique(pairs[:, 0])) == len(pairs) == len(np.unique(pairs[:, 1]))
    # Each cow found itself (perm maps b index -> a index).
    assert (perm[pairs[:, 1]] == pairs[:, 0]).mean() > 0.99
    assert dist.max() <= 2.0


def test_unknown_flight_and_geographic_crs_are_errors():
    with pytest.raises(LabelError, match="PA9"):
        cattle_movement(herd(), "PA1", "PA9", radius_m=5.0)
    with pytest.raises(LabelError, match="projected"):
        cattle_movement(herd().to_crs("EPSG:4326"), "PA1", "PA2", radius_m=5.0)


def test_cli_writes_lines_and_table(tmp_path):
    herd().to_file(tmp_path / "cattle.gpkg", layer="cattle", driver="GPKG")
    result = CliRunner().invoke(cli, ["movement", "--labels", str(tmp_path / "cattle.gpkg"),
                                      "--from", "PA1", "--to", "PA2", "--radius-m", "10",
                                      "--out", str(tmp_path / "mv")])
    assert result.exit_code == 0, result.output
    assert "moved" in result.output
    doc = json.loads((tmp_path / "mv" / "movement_PA1_PA2.geojson").read_text())
    kinds = sorted({f["geometry"]["type"] for f in doc["features"]})
    assert kinds == ["LineString", "Point"]
    lon, lat = doc["features"][0]["geometry"]["coordinates"][0]
    assert 150 < lon < 152 and -35 < lat < -34     # RFC 7946 lon/lat
    csv = (tmp_path / "mv" / "movement_PA1_PA2.csv").read_text().splitlines()
    assert csv[0].startswith("category,flight_a,flight_b,id_a,id_b")
    assert len(csv) == 1 + 6
