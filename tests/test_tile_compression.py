"""parameters.tile_compression: uncompressed UAV tiles hold the same pixels as the default
DEFLATE ones, are read by GDAL, OpenCV and Pillow, and degrade to the same outputs."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from PIL import Image

from geosim.cli.main import cli
from geosim.config import load_site
from geosim.errors import ConfigError

STEPS = ("grid", "footprints", "align", "tiles", "degrade")


def _site(samples_dir: Path, dst: Path, extra: str) -> Path:
    shutil.copytree(samples_dir, dst, ignore=shutil.ignore_patterns("run*", ".geosim"))
    site = dst / "site.toml"
    text = site.read_text().replace("[parameters]\n", f"[parameters]\nq = 2.0\n{extra}", 1)
    site.write_text(text)
    return site


def _run(site: Path, out: Path) -> None:
    args = ["run", str(site), "--out", str(out), "--workers", "1"]
    for s in STEPS:
        args += ["--only", s]
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output


def _decoded(path: Path) -> tuple[np.ndarray, np.ndarray]:
    with rasterio.open(path) as ds:
        return ds.read(), ds.read_masks(1)


def test_uncompressed_tiles_same_pixels_readable_and_same_degraded(
        samples_dir: Path, tmp_path: Path) -> None:
    default = _site(samples_dir, tmp_path / "a", "")
    raw = _site(samples_dir, tmp_path / "b", 'tile_compression = "none"\n')
    _run(default, tmp_path / "run_a")
    _run(raw, tmp_path / "run_b")
    tiles = sorted(p.relative_to(tmp_path / "run_a")
                   for p in (tmp_path / "run_a").glob("tiles/*/*.tif"))
    assert tiles
    for rel in tiles:
        a, b = tmp_path / "run_a" / rel, tmp_path / "run_b" / rel
        with rasterio.open(a) as da, rasterio.open(b) as db:
            assert da.compression is not None and da.compression.name == "deflate"
            assert db.compression is None  # stored uncompressed
        img_a, mask_a = _decoded(a)
        img_b, mask_b = _decoded(b)
        np.testing.assert_array_equal(img_b, img_a)
        np.testing.assert_array_equal(mask_b, mask_a)
        rgb = np.moveaxis(img_b[:3], 0, -1)
        bgr = cv2.imread(str(b), cv2.IMREAD_UNCHANGED)
        assert bgr is not None
        np.testing.assert_array_equal(bgr[..., 2::-1], rgb)
        with Image.open(b) as im:
            np.testing.assert_array_equal(np.asarray(im)[..., :3], rgb)
        assert b.stat().st_size > a.stat().st_size
    degraded = sorted((tmp_path / "run_a").glob("degraded/*/*.tif"))
    assert len(degraded) == len(tiles)
    for a in degraded:
        b = tmp_path / "run_b" / a.relative_to(tmp_path / "run_a")
        for x, y in zip(_decoded(a), _decoded(b), strict=True):
            np.testing.assert_array_equal(x, y)


def test_unknown_tile_compression_is_refused(samples_dir: Path, tmp_path: Path) -> None:
    site = _site(samples_dir, tmp_path / "s", 'tile_compression = "zstd"\n')
    with pytest.raises(ConfigError, match="tile_compression"):
        load_site(site)
