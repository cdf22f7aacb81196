"""The CLI contract: --version/--help, bad input → one line on stderr, exit 2, nothing written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from geosim import __version__
from geosim.cli.main import cli
from tests.helpers import textured_rgb, write_raster


def test_version_and_help() -> None:
    runner = CliRunner()
    result = runner.invoke(cli, ["--version"])
    assert result.exit_code == 0 and __version__ in result.output
    result = runner.invoke(cli, ["--help"])
    assert result.exit_code == 0
    for command in ("run", "demo"):
        assert command in result.output


def _bad_sites(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    write_raster(tmp_path / "nocrs.tif", textured_rgb(32, 32), crs=None)
    write_raster(tmp_path / "ok.tif", textured_rgb(32, 32))
    flight = '[[flights]]\nid = "A"\nimage = "{}"\nacquired = 2021-07-15T11:00:00\n'
    cases = {
        "unknown key": ("[site]\ncolour = 'red'\n" + flight.format("ok.tif"), "site.colour"),
        "missing image": (flight.format("gone.tif"), "gone.tif"),
        "image without CRS": (flight.format("nocrs.tif"), "no CRS"),
    }
    out = {}
    for name, (body, needle) in cases.items():
        p = tmp_path / f"{name.replace(' ', '_')}.toml"
        p.write_text(body)
        out[name] = (p, needle)
    return out


@pytest.mark.parametrize("case", ["unknown key", "missing image", "image without CRS"])
def test_bad_site_file_one_line_exit_2_writes_nothing(tmp_path: Path, case: str) -> None:
    site, needle = _bad_sites(tmp_path)[case]
    out = tmp_path / "out"
    # a real subprocess: the console entry point, stderr and exit code as a user sees them
    proc = subprocess.run([sys.executable, "-m", "geosim", "run", str(site), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("geosim: error:") and needle in lines[0]
    assert "Traceback" not in proc.stderr
    assert not out.exists()


def test_debug_flag_shows_traceback(tmp_path: Path) -> None:
    site, _ = _bad_sites(tmp_path)["missing image"]
    proc = subprocess.run([sys.executable, "-m", "geosim", "--debug", "run", str(site), "--out",
                           str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_anchor_option_needs_a_satellite(tmp_path: Path) -> None:
    write_raster(tmp_path / "ok.tif", textured_rgb(32, 32))
    site = tmp_path / "site.toml"
    site.write_text('[[flights]]\nid = "A"\nimage = "ok.tif"\nacquired = 2021-07-15\n')
    out = tmp_path / "out"
    result = CliRunner().invoke(cli, ["run", str(site), "--out", str(out), "--anchor",
                                      "satellite"])
    assert result.exit_code == 2
    assert "needs a satellite scene" in result.output
    assert not out.exists()


@pytest.mark.slow
def test_anchor_option_overrides_the_site_file(samples_dir: Path, tmp_path: Path) -> None:
    import json

    out = tmp_path / "out"
    args = ["align", str(samples_dir / "site.toml"), "--out", str(out), "--anchor", "satellite"]
    runner = CliRunner()
    grid = runner.invoke(cli, ["grid", str(samples_dir / "site.toml"), "--out", str(out)])
    assert grid.exit_code == 0, grid.output
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    alignment = json.loads((out / "alignment.json").read_text())
    assert alignment["anchor"]["to"] == "satellite"
    assert alignment["anchor"]["shift_m"] != [0.0, 0.0]
