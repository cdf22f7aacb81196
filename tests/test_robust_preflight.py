"""Everything that can be checked is checked before a run writes anything (issue 12, item 3):
corrupt rasters (file and block named), flights in the wrong place, a satellite scene that
misses the flights, bad labels, no Q, φ = 1, unusable band layouts."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from geosim.config import load_site
from geosim.errors import ConfigError, ExtentError, LabelError, RasterError
from geosim.validate import check_extents, check_raster_readable, preflight, site_extents
from tests.robust_helpers import assert_one_line_error, copy_site, run_cli, set_site_value


@pytest.fixture()
def site_copy(samples_dir: Path, tmp_path: Path) -> Path:
    return copy_site(samples_dir, tmp_path / "site")


def test_truncated_flight_is_named_with_its_block_before_anything_is_written(
        site_copy: Path, tmp_path: Path) -> None:
    # On the old main: a traceback ("Read failed", no file named) from the grid step.
    tif = site_copy.parent / "flights" / "PA2.tif"
    os.truncate(tif, int(tif.stat().st_size * 0.6))
    out = tmp_path / "run"
    result = run_cli("run", site_copy, "--out", out)
    line = assert_one_line_error(result, "PA2.tif", "truncated or corrupt", "block (")
    assert "row" in line and "column" in line
    assert not out.exists()


def test_corrupt_block_is_located(tmp_path: Path) -> None:
    """Garbage written over one known block (GDAL's own block offset) is reported there."""
    rng = np.random.default_rng(1)
    path = tmp_path / "tiled.tif"
    profile = {"driver": "GTiff", "width": 1024, "height": 768, "count": 3, "dtype": "uint8",
               "crs": "EPSG:32756", "transform": Affine(0.05, 0, 255000, 0, -0.05, 6185000),
               "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate"}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(rng.integers(0, 255, (3, 768, 1024), dtype=np.uint8))
    with rasterio.open(path) as ds:
        # block in block-row 1, block-column 2 (GDAL names it BLOCK_OFFSET_<col>_<row>)
        offset = int(ds.get_tag_item("BLOCK_OFFSET_2_1", "TIFF", bidx=1))
        size = int(ds.get_tag_item("BLOCK_SIZE_2_1", "TIFF", bidx=1))
    with open(path, "r+b") as f:
        f.seek(offset)
        f.write(bytes(rng.integers(0, 255, size, dtype=np.uint8)))
    with rasterio.open(path) as ds, pytest.raises(RasterError) as err:
        check_raster_readable(ds, "flight X")
    msg = str(err.value)
    assert "tiled.tif" in msg and "block (1, 2)" in msg and "row 256, column 512" in msg


def _raster_with_bad_blocks(path: Path, bad: list[tuple[int, int]]) -> None:
    """A 1024 × 2048 px tiled GeoTIFF (256 px blocks) with garbage over blocks ``(row, col)``."""
    rng = np.random.default_rng(2)
    profile = {"driver": "GTiff", "width": 1024, "height": 2048, "count": 3, "dtype": "uint8",
               "crs": "EPSG:32756", "transform": Affine(0.05, 0, 255000, 0, -0.05, 6185000),
               "tiled": True, "blockxsize": 256, "blockysize": 256, "compress": "deflate"}
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(rng.integers(0, 255, (3, 2048, 1024), dtype=np.uint8))
    for row, col in bad:
        with rasterio.open(path) as ds:
            offset = int(ds.get_tag_item(f"BLOCK_OFFSET_{col}_{row}", "TIFF", bidx=1))
            size = int(ds.get_tag_item(f"BLOCK_SIZE_{col}_{row}", "TIFF", bidx=1))
        with open(path, "r+b") as f:
            f.seek(offset)
            f.write(bytes(rng.integers(0, 255, size, dtype=np.uint8)))


@pytest.mark.parametrize("workers", [1, 2])
def test_read_check_in_parts_reports_the_first_bad_block_in_file_order(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, workers: int) -> None:
    """The integrity read split into strips (engine tasks; 2 workers: on a local cluster)
    reports the block a read from start to end meets first, whichever strip ends first."""
    from types import SimpleNamespace

    from geosim import validate
    from geosim.engine import open_engine

    path = tmp_path / "two_bad.tif"
    _raster_with_bad_blocks(path, [(1, 2), (6, 0)])  # in the first and the second strip
    monkeypatch.setattr(validate, "CHECK_TASK_PX", 1024 * 1024)  # 2 strips of 1024 rows
    site = SimpleNamespace(flights=[SimpleNamespace(id="X", image=path)], satellite=None)
    with open_engine(workers), pytest.raises(RasterError) as err:
        validate.check_rasters(site)
    msg = str(err.value)
    assert "two_bad.tif" in msg and "block (1, 2)" in msg and "row 256, column 512" in msg


def test_read_check_strips_cover_every_pixel_once(tmp_path: Path) -> None:
    path = tmp_path / "sound.tif"
    _raster_with_bad_blocks(path, [])
    with rasterio.open(path) as ds:
        parts = [check_raster_readable(ds, "x", (r, min(r + 1024, 2048))) for r in (0, 1024)]
        assert parts == [1024 * 1024, 1024 * 1024]
        assert sum(parts) == check_raster_readable(ds, "x") == ds.width * ds.height


def test_sound_raster_reads_every_pixel(samples_dir: Path) -> None:
    with rasterio.open(samples_dir / "flights" / "PA1.tif") as ds:
        assert check_raster_readable(ds, "flight PA1") == ds.width * ds.height


def test_flight_in_the_neighbouring_utm_zone_fails_fast_naming_it(site_copy: Path,
                                                                 tmp_path: Path) -> None:
    # On the old main: minutes in the grid step building a ~550 km grid, then a temp file.
    tif = site_copy.parent / "flights" / "PA3.tif"
    with rasterio.open(tif, "r+") as ds:
        ds.crs = "EPSG:28355"  # GDA94 / MGA zone 55: same numbers, ~550 km further west
    out = tmp_path / "run"
    start = time.perf_counter()
    result = run_cli("run", site_copy, "--out", out)
    seconds = time.perf_counter() - start
    line = assert_one_line_error(result, "flight PA3", "does not overlap", "km from")
    km = float(line.split("it is ")[1].split(" km")[0])
    assert 450 < km < 700, line  # one UTM zone is 6° of longitude, ~550 km at 34° S
    assert not out.exists()
    print(f"neighbouring-zone flight refused in {seconds:.1f} s (including interpreter start)")


def test_satellite_that_misses_the_flights_says_no_overlap(site_copy: Path,
                                                          tmp_path: Path) -> None:
    tif = site_copy.parent / "satellite" / "satellite.tif"
    with rasterio.open(tif, "r+") as ds:
        ds.transform = ds.transform * Affine.translation(4000, 0)  # 2 km east (0.5 m px)
    result = run_cli("run", site_copy, "--out", tmp_path / "run")
    line = assert_one_line_error(result, "satellite scene", "no overlap")
    assert "km away" in line
    assert not (tmp_path / "run").exists()


def test_extents_of_the_sample_site_pass_and_overlap_truthfully(samples_dir: Path) -> None:
    site = load_site(samples_dir / "site.toml")
    ext = site_extents(site)
    common = check_extents(ext, uav_gsd_m=0.05)
    # every flight contains the common extent, and the satellite scene covers it
    for b in ext.flights.values():
        assert b[0] <= common[0] < common[2] <= b[2] and b[1] <= common[1] < common[3] <= b[3]
    s = ext.satellite
    assert s[0] <= common[0] and common[2] <= s[2]


def test_bad_label_line_fails_before_the_grid_is_built(site_copy: Path, tmp_path: Path) -> None:
    # On the old main this failed at step 6, after grid, alignment and tiles were written.
    yolo = site_copy.parent / "labels" / "PA1" / "PA1.txt"
    yolo.write_text(yolo.read_text() + "0 0.5 0.5 not-a-number 0.1\n")
    out = tmp_path / "run"
    with pytest.raises(LabelError, match="PA1.txt"):
        preflight(load_site(site_copy), out)
    result = run_cli("run", site_copy, "--out", out)
    assert_one_line_error(result, "PA1.txt")
    assert not out.exists()


def test_no_satellite_and_no_q_is_refused_at_validation(site_copy: Path, tmp_path: Path) -> None:
    text = site_copy.read_text()
    start = text.index("[satellite]")
    site_copy.write_text(text[:start] + text[text.index("[paddocks]"):])
    with pytest.raises(ConfigError, match="no satellite scene and no parameters.q"):
        preflight(load_site(site_copy), tmp_path / "run")
    # Steps that do not degrade need no Q; with q set the whole pipeline may run.
    preflight(load_site(site_copy), tmp_path / "run", ["grid", "footprints"])
    set_site_value(site_copy, r"^tile_px = 500$", "tile_px = 500\nq = 2.0")
    preflight(load_site(site_copy), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_phi_of_one_is_refused(site_copy: Path) -> None:
    set_site_value(site_copy, r"^tile_px = 500$", "tile_px = 500\nsat_gsd_m = 0.05")
    with pytest.raises(ConfigError, match="φ ≥ 2"):
        load_site(site_copy)


def _grey_two_band_untagged(src: Path, dst: Path) -> None:
    with rasterio.open(src) as ds:
        profile = {**ds.profile, "count": 2}
        grey, alpha = ds.read(1), ds.read(4)
    profile.pop("photometric", None)
    with rasterio.open(dst, "w", **profile) as out:
        out.write(np.stack([grey, alpha]))
        out.colorinterp = [rasterio.enums.ColorInterp.gray,
                           rasterio.enums.ColorInterp.undefined]


def test_two_image_bands_without_alpha_are_refused(site_copy: Path, tmp_path: Path) -> None:
    tif = site_copy.parent / "flights" / "PA1.tif"
    tmp = tmp_path / "two.tif"
    _grey_two_band_untagged(tif, tmp)
    os.replace(tmp, tif)
    with pytest.raises(RasterError, match="2 image bands and no band tagged alpha"):
        load_site(site_copy)


def test_unsupported_dtype_is_refused(site_copy: Path) -> None:
    tif = site_copy.parent / "satellite" / "satellite.tif"
    with rasterio.open(tif) as ds:
        profile, data = ds.profile, ds.read()
    profile.update(dtype="int8", photometric=None)
    profile.pop("photometric")
    with rasterio.open(tif, "w", **profile) as out:
        out.write((data // 2).astype(np.int8))
    with pytest.raises(RasterError, match="int8"):
        load_site(site_copy)


def test_far_flights_beyond_grid_ceiling(monkeypatch: pytest.MonkeyPatch,
                                         samples_dir: Path) -> None:
    import geosim.validate as v

    ext = site_extents(load_site(samples_dir / "site.toml"))
    monkeypatch.setattr(v, "MAX_GRID_PX", 1e6)  # the sample grid is ~4.6e6 px
    with pytest.raises(ExtentError, match="limit"):
        v.check_extents(ext, uav_gsd_m=0.05)
