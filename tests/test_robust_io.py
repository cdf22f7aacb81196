"""Write failures are one line naming the path (issue 12, item 4): a full disk is simulated
with RLIMIT_FSIZE (writes beyond the limit fail with EFBIG, as on a full disk, since Python
ignores SIGXFSZ)."""

from __future__ import annotations

import errno
import os
import resource
from pathlib import Path

import numpy as np
import pytest
from affine import Affine

from geosim.errors import OutputError
from geosim.io.atomic import write_failure, write_json
from geosim.io.raster import write_geotiff
from tests.robust_helpers import assert_one_line_error, copy_site, run_cli


def _limit_file_size(max_bytes: int):
    def apply() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (max_bytes, max_bytes))
    return apply


def test_full_disk_during_a_run_is_one_line_naming_the_file(samples_dir: Path,
                                                            tmp_path: Path) -> None:
    # On the old main: a rasterio traceback ("Write failed"), exit 1.
    site = copy_site(samples_dir, tmp_path / "site")
    out = tmp_path / "run"
    result = run_cli("run", site, "--out", out,
                     preexec_fn=_limit_file_size(300_000))  # a 500 px tile is ~550 kB
    line = assert_one_line_error(result, "cannot be written", str(out))
    assert "free disk space" in line
    leftovers = [p for p in out.rglob("*") if ".part" in p.name]
    assert leftovers == []  # nothing half-written left behind


def test_write_failure_translates_os_and_gdal_write_errors(tmp_path: Path) -> None:
    err = write_failure(OSError(errno.ENOSPC, "No space left on device"), tmp_path / "a.tif")
    assert isinstance(err, OutputError) and "No space left on device" in str(err)
    assert str(tmp_path / "a.tif") in str(err)
    from rasterio.errors import RasterioIOError

    assert write_failure(RasterioIOError("Write failed. See previous exception for details."),
                         tmp_path / "b.tif") is not None
    # A read error or a bug is not dressed up as a write failure.
    assert write_failure(RasterioIOError("Read failed. See previous exception."), tmp_path) \
        is None
    assert write_failure(ValueError("shapes do not match"), tmp_path) is None


def test_writers_raise_output_error_in_process(tmp_path: Path) -> None:
    """In-process check of the JSON and GeoTIFF writers (limit set and restored here)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    arr = np.random.default_rng(0).integers(0, 255, (3, 600, 600), dtype=np.uint8)
    resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, hard))
    try:
        with pytest.raises(OutputError, match="a.json: cannot be written"):
            write_json(tmp_path / "a.json", {"x": "y" * 100_000})
        with pytest.raises(OutputError, match="a.tif: cannot be written"):
            write_geotiff(tmp_path / "a.tif", arr, transform=Affine(0.05, 0, 0, 0, -0.05, 0),
                          crs="EPSG:32756")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.slow
def test_truncated_file_in_the_run_folder_is_one_line(samples_dir: Path, tmp_path: Path) -> None:
    """Inputs are checked at pre-flight; a run-folder raster cut short fails in one line."""
    site = copy_site(samples_dir, tmp_path / "site")
    out = tmp_path / "run"
    first = run_cli("run", site, "--out", out, "--only", "grid", "--only", "footprints",
                    "--only", "align", "--only", "tiles")
    assert first.code == 0, first.stderr[-2000:]
    tile = sorted((out / "tiles" / "PA2").glob("*.tif"))[0]
    os.truncate(tile, tile.stat().st_size // 2)
    result = run_cli("degrade", site, "--out", out, "--q", "2", "--workers", "1")
    assert_one_line_error(result, tile.name, "truncated or corrupt", "rerun the step")
