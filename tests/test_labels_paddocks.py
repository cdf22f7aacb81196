"""Cattle per paddock: paddocks in lon/lat, cattle in UTM; areas against a closed formula."""

from __future__ import annotations

import math

import geopandas as gpd
import numpy as np
import pytest
import shapely
from click.testing import CliRunner
from pyproj import Transformer

from geosim.cli.main import cli
from geosim.errors import LabelError
from geosim.labels.paddocks import OUTSIDE, cattle_per_paddock

# WGS 84 ellipsoid.
A_M = 6378137.0
F = 1 / 298.257223563
B_M = A_M * (1 - F)
E = math.sqrt(F * (2 - F))


def quadrangle_area_m2(lon0, lat0, lon1, lat1):
    """Area of a lon/lat quadrangle on the WGS 84 ellipsoid (closed form):
    A = b^2 dlambda / 2 [g(phi1) - g(phi0)],
    g(phi) = sin(phi) / (1 - e^2 sin^2(phi)) + ln((1 + e sin(phi)) / (1 - e sin(phi))) / (2e)."""
    def g(lat):
        s = math.sin(math.radians(lat))
        return s / (1 - E**2 * s**2) + math.log((1 + E * s) / (1 - E * s)) / (2 * E)
    return abs(B_M**2 * math.radians(lon1 - lon0) / 2 * (g(lat1) - g(lat0)))


# Two paddocks side by side near Moss Vale NSW, in lon/lat, plus a third with no cattle.
NORTH = (150.3700, -34.5500, 150.3740, -34.5480)
SOUTH = (150.3700, -34.5530, 150.3740, -34.5500)
EMPTY = (150.3800, -34.5530, 150.3820, -34.5510)
TO_UTM = Transformer.from_crs("EPSG:4326", "EPSG:32756", always_xy=True)


def paddocks_4326():
    return gpd.GeoDataFrame({"name": ["North", "South", "Empty"]},
                            geometry=[shapely.box(*NORTH), shapely.box(*SOUTH),
                                      shapely.box(*EMPTY)], crs="EPSG:4326")


def cattle_utm():
    """Cattle boxes in UTM 56S whose centres are placed in known paddocks.

    Centres are placed at lon/lat positions chosen inside/outside the paddocks (some
    a few decimetres from a boundary) and projected with pyproj; boxes are 2 m x 0.8 m.
    """
    d = 4e-6   # ~0.4 m in longitude, ~0.44 m in latitude
    spots = {
        "PA1": [(150.3710, -34.5490, "North"), (150.3720, -34.5485, "North"),
                (150.3740 - d, -34.5490, "North"), (150.3720, -34.5500 + d, "North"),
                (150.3720, -34.5500 - d, "South"), (150.3705, -34.5520, "South"),
                (150.3740 + d, -34.5490, OUTSIDE)],
        "PA2": [(150.3710, -34.5510, "South"), (150.3711, -34.5511, "South"),
                (150.3712, -34.5512, "South")],
    }
    rows, geoms, expected = [], [], {}
    for flight, pts in spots.items():
        for lon, lat, where in pts:
            x, y = TO_UTM.transform(lon, lat)
            geoms.append(shapely.box(x - 1.0, y - 0.4, x + 1.0, y + 0.4))
            rows.append({"flight": flight, "acquired": f"2021-07-15T1{len(rows) % 3}:00"})
            expected[(flight, where)] = expected.get((flight, where), 0) + 1
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs="EPSG:32756")
    gdf["acquired"] = gdf["flight"].map({"PA1": "2021-07-15T10:00:00+10:00",
                                         "PA2": "2021-07-15T13:00:00+10:00"})
    return gdf, expected


def test_counts_and_density_with_paddocks_in_lonlat_and_cattle_in_utm():
    cattle, expected = cattle_utm()
    table = cattle_per_paddock(cattle, paddocks_4326())
    got = {(r.flight, r.paddock): r.count for r in table.itertuples()}
    for key, n in expected.items():
        assert got[key] == n, key
    assert got[("PA1", "Empty")] == 0 and got[("PA2", "North")] == 0
    assert ("PA2", OUTSIDE) not in got   # no outside row when nobody is outside
    for name, box in (("North", NORTH), ("South", SOUTH), ("Empty", EMPTY)):
        area_ha = quadrangle_area_m2(*box) / 1e4
        rows = table[table["paddock"] == name]
        np.testing.assert_allclose(rows["area_ha"], area_ha, rtol=1e-5)
        np.testing.assert_allclose(rows["cattle_per_ha"], rows["count"] / area_ha, rtol=1e-5)
    # About 367 m x 222 m = 8.14 ha for North: a sanity check on the formula itself.
    assert quadrangle_area_m2(*NORTH) / 1e4 == pytest.approx(8.14, abs=0.05)
    # Flights in acquisition order, paddocks in file order.
    assert table["flight"].tolist()[:3] == ["PA1"] * 3
    assert table["paddock"].tolist()[:3] == ["North", "South", "Empty"]


def test_same_counts_when_both_in_lonlat_or_both_in_utm():
    cattle, _ = cattle_utm()
    pads = paddocks_4326()
    ref = cattle_per_paddock(cattle, pads)
    a = cattle_per_paddock(cattle.to_crs("EPSG:4326"), pads)
    b = cattle_per_paddock(cattle, pads.to_crs("EPSG:32756"))
    assert a["count"].tolist() == ref["count"].tolist() == b["count"].tolist()
    # Geodesic areas do not depend on the CRS the paddocks came in.
    np.testing.assert_allclose(b["area_ha"].dropna(), ref["area_ha"].dropna(), rtol=1e-9)


def test_missing_name_column_is_an_error():
    cattle, _ = cattle_utm()
    with pytest.raises(LabelError, match="'name'"):
        cattle_per_paddock(cattle, paddocks_4326().rename(columns={"name": "x"}))


def test_cli_prints_table_and_writes_csv(tmp_path):
    cattle, expected = cattle_utm()
    cattle.to_file(tmp_path / "cattle.gpkg", layer="cattle", driver="GPKG")
    paddocks_4326().to_file(tmp_path / "paddocks.geojson", driver="GeoJSON")
    out = tmp_path / "counts.csv"
    result = CliRunner().invoke(cli, ["cattle-per-paddock", "--labels",
                                      str(tmp_path / "cattle.gpkg"), "--paddocks",
                                      str(tmp_path / "paddocks.geojson"), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "North" in result.output and "cattle_per_ha" in result.output
    import pandas as pd

    csv = pd.read_csv(out)
    assert int(csv[(csv.flight == "PA1") & (csv.paddock == "North")]["count"].iloc[0]) == \
        expected[("PA1", "North")]


def test_cli_missing_file_is_one_line_error(tmp_path):
    result = CliRunner().invoke(cli, ["cattle-per-paddock", "--labels",
                                      str(tmp_path / "nope.gpkg"), "--paddocks",
                                      str(tmp_path / "p.geojson")])
    assert result.exit_code == 2
    assert "nope.gpkg" in result.output and "Traceback" not in result.output
