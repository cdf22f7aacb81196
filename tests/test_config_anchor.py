"""``site.anchor``: the frame of the aligned flights ("reference_flight" or "satellite")."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from geosim.config import ANCHORS, SiteConfig, load_site, site_from_images
from geosim.errors import ConfigError
from tests.helpers import textured_rgb, write_raster

BODY = """
[site]
name = "t"
{anchor}
[[flights]]
id = "A"
image = "flights/A.tif"
acquired = 2021-07-15T11:00:00+10:00
"""
SATELLITE = """
[satellite]
image = "sat.tif"
"""


def _site(tmp_path: Path, anchor_line: str, *, satellite: bool) -> Path:
    (tmp_path / "flights").mkdir(exist_ok=True)
    write_raster(tmp_path / "flights" / "A.tif", textured_rgb(64, 64), crs="EPSG:28356")
    write_raster(tmp_path / "sat.tif", textured_rgb(32, 32, seed=1), crs="EPSG:32756")
    path = tmp_path / "site.toml"
    path.write_text(BODY.format(anchor=anchor_line) + (SATELLITE if satellite else ""))
    return path


def test_default_is_the_reference_flight(tmp_path: Path) -> None:
    site = load_site(_site(tmp_path, "", satellite=True))
    assert site.anchor == "reference_flight"
    assert ANCHORS == ("reference_flight", "satellite")
    assert site.to_dict()["anchor"] == "reference_flight"


@pytest.mark.parametrize("value", ["reference_flight", "satellite"])
def test_allowed_values_load(tmp_path: Path, value: str) -> None:
    site = load_site(_site(tmp_path, f'anchor = "{value}"', satellite=True))
    assert site.anchor == value


@pytest.mark.parametrize("line", ['anchor = "sattelite"', 'anchor = "Satellite"', "anchor = 1",
                                  'anchor = ""', "anchor = true"])
def test_bad_values_name_the_key_and_the_allowed_values(tmp_path: Path, line: str) -> None:
    path = _site(tmp_path, line, satellite=True)
    with pytest.raises(ConfigError) as err:
        load_site(path)
    msg = str(err.value)
    assert "site.anchor" in msg and "'reference_flight'" in msg and "'satellite'" in msg
    assert str(path.resolve()) in msg


def test_satellite_anchor_needs_a_satellite_scene(tmp_path: Path) -> None:
    path = _site(tmp_path, 'anchor = "satellite"', satellite=False)
    with pytest.raises(ConfigError) as err:
        load_site(path)
    msg = str(err.value)
    assert "site.anchor" in msg and "[satellite]" in msg and "reference_flight" in msg
    # without the anchor the same file is fine
    assert load_site(_site(tmp_path, "", satellite=False)).anchor == "reference_flight"


def test_dataclass_validates_on_construction_and_replace(tmp_path: Path) -> None:
    site = load_site(_site(tmp_path, "", satellite=False))
    with pytest.raises(ConfigError, match="site.anchor"):
        dataclasses.replace(site, anchor="satellite")        # no satellite scene
    with pytest.raises(ConfigError, match="site.anchor"):
        SiteConfig(path=None, name="x", crs="auto", reference_flight="A",
                   flights=site.flights, anchor="uav")


def test_site_from_images_takes_the_anchor(tmp_path: Path) -> None:
    path = _site(tmp_path, "", satellite=True)
    uav = path.parent / "flights" / "A.tif"
    assert site_from_images([uav]).anchor == "reference_flight"
    site = site_from_images([uav], path.parent / "sat.tif", anchor="satellite", tile_px=500)
    assert site.anchor == "satellite" and site.parameters.tile_px == 500
    with pytest.raises(ConfigError, match="site.anchor"):
        site_from_images([uav], None, anchor="satellite")
    with pytest.raises(ConfigError, match="'reference_flight', 'satellite'"):
        site_from_images([uav], path.parent / "sat.tif", anchor="both")
