"""`geosim run` on real imagery: two NEON SJER years (0.1 m, EPSG:32611) as flights,
no satellite scene, a fixed Q: the pipeline runs through, skips what needs a satellite,
and keeps the nested-grid invariants with φ = 5."""

from __future__ import annotations

import json
from pathlib import Path

import rasterio
from affine import Affine
from click.testing import CliRunner

from geosim.cli.main import cli


def test_run_on_sjer_years_without_satellite(realdata: Path, tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f"""
[site]
name = "SJER 021"
[parameters]
uav_gsd_m = 0.1
sat_gsd_m = 0.5
tile_px = 200
align_window_px = 384
keep_partial_tiles = true
q = 2.0
[[flights]]
id = "y2017"
image = "{realdata / 'sjer_2017' / 'SJER_021.tif'}"
acquired = 2017-05-01T10:00:00-07:00
[[flights]]
id = "y2018"
image = "{realdata / 'sjer_2018' / 'SJER_021.tif'}"
acquired = 2018-05-01T10:00:00-07:00
""")
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["run", str(site), "--out", str(out)])
    assert result.exit_code == 0, result.output
    record = json.loads((out / "run.json").read_text())
    status = {k: v["status"] for k, v in record["steps"].items()}
    assert status["calibrate"] == "skipped" and status["diagnose"] == "skipped"
    assert status["degrade"] == "ok"
    assert record["steps"]["degrade"]["summary"]["q"] == 2.0
    alignment = json.loads((out / "alignment.json").read_text())
    assert alignment["flights"]["y2018"]["confidence"] > 0.1
    degraded = sorted((out / "degraded").rglob("*.tif"))
    assert degraded
    for path in degraded:
        with rasterio.open(path) as deg, \
                rasterio.open(out / "tiles" / path.parent.name / path.name) as src:
            s = src.transform
            assert deg.transform == Affine(s.a * 5, s.b, s.c, s.d, s.e * 5, s.f)
            assert deg.crs == src.crs and deg.crs.to_epsg() == 32611


def test_site_without_satellite_or_q_says_what_to_do(realdata: Path, tmp_path: Path) -> None:
    site = tmp_path / "site.toml"
    site.write_text(f"""
[parameters]
uav_gsd_m = 0.1
tile_px = 200
align_window_px = 384
keep_partial_tiles = true
[[flights]]
id = "a"
image = "{realdata / 'sjer_2017' / 'SJER_021.tif'}"
acquired = 2017-05-01
""")
    result = CliRunner().invoke(cli, ["run", str(site), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "q = 4.34" in result.output and "[satellite]" in result.output


def test_no_fully_covered_tile_is_a_clear_error(realdata: Path, tmp_path: Path) -> None:
    # after alignment the 2018 tile no longer covers the edges: no 20 m quadrant is whole
    site = tmp_path / "site.toml"
    site.write_text(f"""
[parameters]
uav_gsd_m = 0.1
tile_px = 200
align_window_px = 384
[[flights]]
id = "y2017"
image = "{realdata / 'sjer_2017' / 'SJER_021.tif'}"
acquired = 2017-05-01
[[flights]]
id = "y2018"
image = "{realdata / 'sjer_2018' / 'SJER_021.tif'}"
acquired = 2018-05-01
""")
    out = tmp_path / "o"
    result = CliRunner().invoke(cli, ["run", str(site), "--out", str(out)])
    assert result.exit_code == 2
    assert "no tiles of 200 px" in result.output and "keep_partial_tiles" in result.output
    assert not (out / "tiles").exists()
