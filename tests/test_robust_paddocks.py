"""Geometry hygiene in cattle-per-paddock (issue 12, item 5): invalid polygons repaired with
a warning that names the paddock and the area change; null or duplicate names and a
missing --name-column refused."""

from __future__ import annotations

from pathlib import Path

import geopandas as gpd
import pytest
import shapely
from click.testing import CliRunner

from geosim.cli.main import cli
from geosim.errors import GeosimWarning, LabelError
from geosim.labels.paddocks import cattle_per_paddock, check_paddocks

CRS = "EPSG:32756"
X0, Y0 = 255100.0, 6184850.0
# A bow-tie drawn with crossing edges: (0,0)-(300,100) and (300,0)-(0,60) cross at
# (112.5, 37.5); its lobes are triangles of 3375 m² and 9375 m² (12 750 m² = 1.275 ha),
# while the shoelace area of the ring as drawn is |3375 - 9375| = 6000 m².
BOWTIE = shapely.Polygon([(X0, Y0), (X0 + 300, Y0 + 100), (X0 + 300, Y0), (X0, Y0 + 60)])
SQUARE = shapely.box(X0 - 200, Y0, X0 - 100, Y0 + 100)  # 1 ha, valid


def _paddocks(names: list[object], geoms: list[shapely.Geometry] | None = None,
              column: str = "name") -> gpd.GeoDataFrame:
    geoms = geoms or [BOWTIE, SQUARE][: len(names)]
    return gpd.GeoDataFrame({column: names}, geometry=geoms, crs=CRS)


def _cattle() -> gpd.GeoDataFrame:
    left = [(X0 + 20, Y0 + 30), (X0 + 40, Y0 + 30), (X0 + 10, Y0 + 45)]  # in the 3375 m² lobe
    right = [(X0 + 250, Y0 + 20), (X0 + 280, Y0 + 50), (X0 + 290, Y0 + 80),
             (X0 + 200, Y0 + 40), (X0 + 260, Y0 + 60)]                   # in the 9375 m² lobe
    square = [(X0 - 150, Y0 + 50)]
    pts = [shapely.Point(p) for p in left + right + square]
    return gpd.GeoDataFrame({"flight": ["PA1"] * len(pts)}, geometry=pts, crs=CRS)


def test_invalid_paddock_is_repaired_with_warning_and_true_area() -> None:
    with pytest.warns(GeosimWarning, match="'Bowtie'.*repaired") as rec:
        table = cattle_per_paddock(_cattle(), _paddocks(["Bowtie", "Square"]))
    msg = str(rec[0].message)
    row = table[table.paddock == "Bowtie"].iloc[0]
    assert row["count"] == 8  # all cattle in both lobes
    # geodesic vs UTM grid area differ by the squared scale factor (< 0.1 % here)
    assert row["area_ha"] == pytest.approx(1.275, rel=2e-3)
    assert row["cattle_per_ha"] == pytest.approx(8 / 1.275, rel=2e-3)
    assert "0.600 ha as drawn -> 1.27" in msg or "0.600 ha as drawn -> 1.28" in msg
    sq = table[table.paddock == "Square"].iloc[0]
    assert sq["count"] == 1 and sq["area_ha"] == pytest.approx(1.0, rel=2e-3)


def test_check_paddocks_reports_each_repair() -> None:
    fixed, repairs = check_paddocks(_paddocks(["Bowtie", "Square"]))
    assert [r.name for r in repairs] == ["Bowtie"]
    assert "Self-intersection" in repairs[0].reason
    assert fixed.geometry.is_valid.all()
    assert fixed.geometry.iloc[0].area == pytest.approx(12750.0, rel=1e-9)  # planar, exact


@pytest.mark.parametrize("bad", [None, "", "  "])
def test_null_or_empty_name_is_refused(bad: object) -> None:
    with pytest.raises(LabelError, match="no name"):
        cattle_per_paddock(_cattle(), _paddocks(["Bowtie", bad], [SQUARE, BOWTIE]))


def test_duplicate_names_are_refused() -> None:
    with pytest.raises(LabelError, match="'North' is used by 2 features"):
        cattle_per_paddock(_cattle(), _paddocks(["North", "North"], [SQUARE, BOWTIE]))


def test_cli_missing_name_column_lists_the_columns(tmp_path: Path) -> None:
    # On the old main a mistyped --name-column silently named the paddocks paddock_1, ...
    _cattle().to_file(tmp_path / "cattle.gpkg", layer="cattle", driver="GPKG")
    _paddocks(["Bowtie", "Square"], column="paddock_name").to_file(
        tmp_path / "paddocks.gpkg", driver="GPKG")
    r = CliRunner().invoke(cli, ["cattle-per-paddock", "--labels", str(tmp_path / "cattle.gpkg"),
                                 "--paddocks", str(tmp_path / "paddocks.gpkg"),
                                 "--name-column", "paddock_nmae"])
    assert r.exit_code == 2
    assert "'paddock_nmae'" in r.output and "columns there are: paddock_name" in r.output
    assert "Traceback" not in r.output


def test_cli_warns_on_stderr_and_counts_repaired_paddock(tmp_path: Path) -> None:
    _cattle().to_file(tmp_path / "cattle.gpkg", layer="cattle", driver="GPKG")
    _paddocks(["Bowtie", "Square"]).to_file(tmp_path / "paddocks.gpkg", driver="GPKG")
    r = CliRunner().invoke(cli, ["cattle-per-paddock", "--labels", str(tmp_path / "cattle.gpkg"),
                                 "--paddocks", str(tmp_path / "paddocks.gpkg"),
                                 "--out", str(tmp_path / "counts.csv")])
    assert r.exit_code == 0, r.output
    assert "geosim: warning:" in r.output and "'Bowtie'" in r.output
    import pandas as pd

    csv = pd.read_csv(tmp_path / "counts.csv")
    assert int(csv[csv.paddock == "Bowtie"]["count"].iloc[0]) == 8
