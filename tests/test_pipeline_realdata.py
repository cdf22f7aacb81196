"""`geosim run` on real imagery: NEON SJER years (0.1 m, EPSG:32611) as flights, no
satellite scene: the pipeline runs through with a fixed Q, skips what needs a satellite,
keeps the nested-grid invariants with φ = 5, and says what to do when it cannot go on."""

from __future__ import annotations

import json
from pathlib import Path

import rasterio
from affine import Affine
from click.testing import CliRunner

from geosim.cli.main import cli


def _sjer_site(tmp_path: Path, realdata: Path, *, years: tuple[str, ...],
               extra: str = "") -> Path:
    """A site file with SJER plot 021 of the given years as flights."""
    flights = "".join(f"""
[[flights]]
id = "y{year}"
image = "{realdata / f'sjer_{year}' / 'SJER_021.tif'}"
acquired = {year}-05-01T10:00:00-07:00
""" for year in years)
    site = tmp_path / "site.toml"
    site.write_text(f"""
[parameters]
uav_gsd_m = 0.1
sat_gsd_m = 0.5
tile_px = 200
align_window_px = 384
{extra}
{flights}""")
    return site


def _run(site: Path, out: Path):  # noqa: ANN202
    return CliRunner().invoke(cli, ["run", str(site), "--out", str(out)])


def test_run_on_sjer_years_without_satellite(realdata: Path, tmp_path: Path) -> None:
    site = _sjer_site(tmp_path, realdata, years=("2017", "2018"),
                      extra="keep_partial_tiles = true\nq = 2.0")
    out = tmp_path / "out"
    result = _run(site, out)
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
    site = _sjer_site(tmp_path, realdata, years=("2017",), extra="keep_partial_tiles = true")
    result = _run(site, tmp_path / "o")
    assert result.exit_code == 2
    assert "q = 4.34" in result.output and "[satellite]" in result.output


def test_no_fully_covered_tile_is_a_clear_error(realdata: Path, tmp_path: Path) -> None:
    # after alignment the 2018 tile no longer covers the edges: no 20 m quadrant is whole
    # q is set: without it (and without a satellite) the run is refused at pre-flight
    site = _sjer_site(tmp_path, realdata, years=("2017", "2018"), extra="q = 2.0")
    out = tmp_path / "o"
    result = _run(site, out)
    assert result.exit_code == 2
    assert "no tiles of 200 px" in result.output and "keep_partial_tiles" in result.output
    assert not (out / "tiles").exists()
