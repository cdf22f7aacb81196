"""Site-file validation: every mistake is named, nothing half-loaded."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest

from geosim.config import Parameters, load_site, site_from_images
from geosim.errors import ConfigError, GeosimError, InputFileError, RasterError
from tests.helpers import textured_rgb, write_raster


def _site(tmp_path: Path, body: str, *, image_crs: str | None = "EPSG:28356") -> Path:
    (tmp_path / "flights").mkdir(exist_ok=True)
    write_raster(tmp_path / "flights" / "A.tif", textured_rgb(64, 64), crs=image_crs)
    site = tmp_path / "site.toml"
    site.write_text(body)
    return site


GOOD = """
[site]
name = "t"
[parameters]
tile_px = 500
[[flights]]
id = "A"
image = "flights/A.tif"
acquired = 2021-07-15T11:00:00+10:00
"""


def test_good_site_loads_with_absolute_paths_and_defaults(tmp_path: Path) -> None:
    site = load_site(_site(tmp_path, GOOD))
    assert site.flights[0].image == (tmp_path / "flights" / "A.tif").resolve()
    assert site.flights[0].acquired == dt.datetime(
        2021, 7, 15, 11, tzinfo=dt.timezone(dt.timedelta(hours=10)))
    assert site.parameters.tile_px == 500
    assert site.parameters.phi == 10
    assert site.crs == "auto" and site.reference_flight == "A"


@pytest.mark.parametrize(("body", "needle", "exc"), [
    (GOOD + "\nbogus = 1\n", "bogus", ConfigError),
    (GOOD.replace("tile_px = 500", "tile_px = 500\ntile_size = 3"), "parameters.tile_size",
     ConfigError),
    (GOOD.replace("tile_px = 500", 'tile_px = "big"'), "parameters.tile_px", ConfigError),
    (GOOD.replace("tile_px = 500", "tile_px = 505"), "multiple of", ConfigError),
    (GOOD.replace("tile_px = 500", "uav_gsd_m = 0.07"), "whole number", ConfigError),
    (GOOD.replace("flights/A.tif", "flights/missing.tif"), "missing.tif", InputFileError),
    (GOOD.replace('name = "t"', 'name = "t"\ncrs = "EPSG:4326"'), "projected", ConfigError),
    (GOOD.replace('name = "t"', 'name = "t"\nreference_flight = "Z"'), "reference_flight",
     ConfigError),
    (GOOD.replace('acquired = 2021-07-15T11:00:00+10:00', 'acquired = "yesterday"'),
     "flights[0].acquired", ConfigError),
    (GOOD + '\n[[flights]]\nid = "A"\nimage = "flights/A.tif"\nacquired = 2021-07-15\n',
     "duplicate flight id", ConfigError),
    ("[site]\nname='x'\n", "no flights", ConfigError),
    ("[[flights]\n", "not valid TOML", ConfigError),
])
def test_bad_site_names_the_problem(tmp_path: Path, body: str, needle: str, exc: type) -> None:
    with pytest.raises(exc) as info:
        load_site(_site(tmp_path, body))
    assert needle in str(info.value)
    assert isinstance(info.value, GeosimError)


def test_image_without_crs_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RasterError, match="no CRS"):
        load_site(_site(tmp_path, GOOD, image_crs=None))


def test_missing_site_file(tmp_path: Path) -> None:
    with pytest.raises(InputFileError, match="does not exist"):
        load_site(tmp_path / "nope.toml")


def test_errors_also_inherit_builtins() -> None:
    assert issubclass(ConfigError, ValueError)
    assert issubclass(InputFileError, FileNotFoundError)


def test_parameters_validate_q_bracket() -> None:
    with pytest.raises(ConfigError, match="q_min"):
        Parameters(q_min=3.0, q_max=2.0)


def test_site_from_images_makes_unique_ids(tmp_path: Path) -> None:
    a = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    (tmp_path / "b").mkdir()
    b = write_raster(tmp_path / "b" / "a.tif", textured_rgb(32, 32))
    site = site_from_images([a, b], None, tile_px=100)
    assert site.flight_ids == ("a", "a_2")
    assert site.parameters.tile_px == 100


def test_fixed_q_parameter(tmp_path: Path) -> None:
    site = load_site(_site(tmp_path, GOOD.replace("tile_px = 500", "tile_px = 500\nq = 4.34")))
    assert site.parameters.q == 4.34
    assert Parameters().q is None
    for bad in ('q = "high"', "q = -1.0", "q = 0"):
        with pytest.raises(ConfigError, match="parameters.q"):
            load_site(_site(tmp_path, GOOD.replace("tile_px = 500", f"tile_px = 500\n{bad}")))
