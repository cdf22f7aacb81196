"""Degrading a UAV tile from its binomial first overview instead of its full resolution.

Truth not derived from the code under test: the binomial level computed in float64 from
its definition (the [1, 5, 10, 10, 5, 1]/32 filter on each 2 × 2 block, reflected edges),
GDAL reading the written overview, the paper's operation done the straightforward way
(``method="reference"``: full-resolution FFT blur + ``cv2.resize`` bicubic) on the full
tile, and the full-resolution path's own outputs where the overview must not be used.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine

from geosim.degrade.core import (
    ALIAS_TOLERANCE,
    degrade_array,
    degrade_level1,
    level1_allowed,
    to_dtype,
)
from geosim.degrade.steps import DEGRADE_READ_TAG, READ_FULL, READ_LEVEL1, degrade_tile
from geosim.io.cog import WholeRaster
from geosim.io.overviews import LEVEL1_BINOMIAL, LEVEL1_TAG, average_overviews
from geosim.io.raster import create_geotiff, read_binomial_level1
from geosim.physics.pyramid import halve_binomial6_exact_uint8

TRANSFORM = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
PHI = 10
WEIGHTS = np.array([1, 5, 10, 10, 5, 1], np.float64) / 32


def binomial_level_f64(band: np.ndarray) -> np.ndarray:
    """Level 1 by its definition: y[j] = Σ_t w[t] x[2j − 2 + t], x reflected at the edges
    (x[−1] = x[0], x[N] = x[N − 1]), per axis, in float64."""
    def axis0(x: np.ndarray) -> np.ndarray:
        pad = np.concatenate([x[1::-1], x, x[:-3:-1]])       # 2 reflected rows each side
        n = x.shape[0] // 2
        return sum(WEIGHTS[t] * pad[t:t + 2 * n:2] for t in range(6))
    return axis0(axis0(band.astype(np.float64)).T).T


def texture(rows: int, cols: int, seed: int = 0) -> np.ndarray:
    """(3, rows, cols) uint8 texture with detail at every scale up to the pixel."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((rows, cols), np.float32)
    for sigma, weight in ((0.7, 0.6), (3.0, 0.5), (12.0, 1.0)):
        acc += weight * sigma * cv2.GaussianBlur(
            rng.standard_normal((rows, cols)).astype(np.float32), (0, 0), sigma)
    grey = np.clip(128 + 45 * (acc - acc.mean()) / acc.std(), 0, 255)
    return np.stack([grey * 0.8, grey, np.clip(grey * 1.1, 0, 255)]).astype(np.uint8)


def write_tile(path, img, valid=None, *, binomial=True, block_px=None):
    valid = np.ones(img.shape[1:], bool) if valid is None else valid
    overrides = {} if block_px is None else {"BLOCKSIZE": block_px}
    with create_geotiff(path, width=img.shape[2], height=img.shape[1], count=img.shape[0],
                        dtype=img.dtype, crs="EPSG:32756", transform=TRANSFORM,
                        band_descriptions=["red", "green", "blue"][:img.shape[0]],
                        internal_mask=True, cog_overrides=overrides,
                        whole=WholeRaster(img, valid, binomial_level1=binomial)) as dst:
        dst.write(img)
        dst.write_mask(np.where(valid, 255, 0).astype(np.uint8))
    return path


def test_exact_level_matches_its_definition():
    rng = np.random.default_rng(1)
    band = rng.integers(0, 256, (64, 48), dtype=np.uint8)
    band[:8] = 255
    band[-8:] = 0
    got = halve_binomial6_exact_uint8(band)
    want = binomial_level_f64(band)
    assert np.array_equal(got.astype(np.float64), want)          # exact, not close
    assert np.all((want * 1024) % 1 == 0)                        # multiples of 1/1024
    with pytest.raises(TypeError):
        halve_binomial6_exact_uint8(band.astype(np.uint16))
    with pytest.raises(ValueError):
        halve_binomial6_exact_uint8(band[:63])


def test_tile_first_overview_is_the_rounded_binomial_level(tmp_path):
    """GDAL reads back the first overview as the float64 binomial level rounded half up;
    the raster is tagged; the deeper levels are still the block means (within rounding)."""
    img = texture(1200, 1040)
    path = write_tile(tmp_path / "t.tif", img)
    with rasterio.open(path) as ds:
        assert ds.tags()[LEVEL1_TAG] == LEVEL1_BINOMIAL
        assert ds.overviews(1) == [2, 4, 8]
        assert np.array_equal(ds.read(), img)                   # full resolution untouched
    with rasterio.open(path, overview_level=0) as ds:
        level1 = ds.read()
        assert ds.dataset_mask().all()
    want = np.floor(np.stack([binomial_level_f64(b) for b in img]) + 0.5)
    assert np.array_equal(level1.astype(np.float64), want)
    with rasterio.open(path, overview_level=1) as ds:
        level2 = ds.read().astype(np.float64)
    unrounded = np.stack([binomial_level_f64(b) for b in img])
    block = unrounded.reshape(3, 300, 2, 260, 2).mean(axis=(2, 4))
    assert np.abs(level2 - block).max() <= 0.5 + 1e-3


@pytest.mark.parametrize("case", ["partial", "odd", "uint16", "not asked"])
def test_no_binomial_level_where_it_does_not_apply(tmp_path, case):
    """Partial, odd-sized, 16-bit rasters, or writers that do not ask: GDAL-style average
    levels and no tag, so the degradation reads them at full resolution."""
    img, valid, binomial = texture(600, 520), None, True
    if case == "partial":
        valid = np.ones((600, 520), bool)
        valid[:, :7] = False
    elif case == "odd":
        img = img[:, :599]
    elif case == "uint16":
        img = img.astype(np.uint16) * 200
    else:
        binomial = False
    path = write_tile(tmp_path / "t.tif", img, valid, binomial=binomial)
    with rasterio.open(path) as ds:
        assert LEVEL1_TAG not in ds.tags()
    with rasterio.open(path, overview_level=0) as ds:
        level1 = ds.read()
    average = average_overviews(img, valid, 256)[0].array
    assert np.array_equal(level1, average)
    assert read_binomial_level1(path) is None


def test_level1_allowed_at_the_alias_tolerance():
    """The first level may stand in exactly where a p = 5 level leaks ≤ ALIAS_TOLERANCE
    at the optics cutoff 1 / (Q φ): tan(π / (Q φ))^5 = tolerance at Q*."""
    q_star = math.pi / (PHI * math.atan(ALIAS_TOLERANCE ** 0.2))
    assert level1_allowed((5000, 5000), q_star * 1.001 * PHI)
    assert not level1_allowed((5000, 5000), q_star * 0.999 * PHI)
    assert not level1_allowed((5000, 4999), 4.34 * PHI)           # odd side
    assert not level1_allowed((14, 14), 4.34 * PHI)               # too small to halve


@pytest.mark.parametrize("q", [4.34, 2.0])
def test_degrade_tile_from_level1_within_1dn_of_the_reference(tmp_path, q):
    """The degraded tile made from the first overview: within 1 DN of the paper's
    straightforward operation on the full tile, and its float values within 0.1 DN of the
    full-resolution fast path (the overview's rounding to whole DN is the difference)."""
    img = texture(1000, 1200, seed=2)
    src = write_tile(tmp_path / "t.tif", img)
    done = degrade_tile(src, tmp_path / "d.tif", q=q, phi=PHI, uav_gsd_m=0.05,
                        tags={"GEOSIM_Q": str(q)}, trust_first_overview=True)
    assert done["read_from"] == READ_LEVEL1
    with rasterio.open(tmp_path / "d.tif") as ds:
        out = ds.read()
        assert ds.tags()[DEGRADE_READ_TAG] == READ_LEVEL1 and ds.tags()["GEOSIM_Q"] == str(q)
        assert ds.transform == TRANSFORM * Affine.scale(PHI)
        assert ds.dataset_mask().all() and out.shape == (3, 100, 120)
    ref, _ = degrade_array(img, q=q, phi=PHI, method="reference")
    assert np.abs(out.astype(int) - to_dtype(ref, np.uint8)).max() <= 1
    full, _ = degrade_array(img, q=q, phi=PHI)
    with rasterio.open(src, overview_level=0) as ds:
        from_level, _ = degrade_level1(ds.read(), img.shape[1:], q=q, phi=PHI)
    diff = np.abs(from_level - full)
    assert diff.max() < 0.1 and np.sqrt(np.mean(diff ** 2)) < 0.03
    assert np.array_equal(out, to_dtype(from_level, np.uint8))


@pytest.mark.parametrize("case", ["low q", "partial", "reference", "untagged", "not vouched"])
def test_full_resolution_where_the_level_cannot_stand_in(tmp_path, case):
    """Q too small for the level, a partial tile, the reference method, a tile without the
    tag or one nobody vouches for (it may have been edited in place: stale overviews):
    degraded from full resolution, bit-identical to degrading the array."""
    img = texture(600, 800, seed=4)
    valid = np.ones((600, 800), bool)
    q, method = 4.34, "fast"
    if case == "low q":
        q = 1.2
    elif case == "partial":
        valid[:, 700:] = False
        img[:, ~valid] = 0
    elif case == "reference":
        method = "reference"
    src = write_tile(tmp_path / "t.tif", img, valid, binomial=case != "untagged")
    done = degrade_tile(src, tmp_path / "d.tif", q=q, phi=PHI, method=method,
                        trust_first_overview=case != "not vouched")
    assert done["read_from"] == READ_FULL
    with rasterio.open(tmp_path / "d.tif") as ds:
        out, tags = ds.read(), ds.tags()
    assert tags[DEGRADE_READ_TAG] == READ_FULL
    want, valid_out = degrade_array(img, q=q, phi=PHI, valid=valid, method=method)
    assert np.array_equal(out[:, valid_out], to_dtype(want, np.uint8)[:, valid_out])


def test_degrade_level1_refuses_what_it_cannot_do():
    level = np.zeros((3, 50, 60), np.uint8)
    with pytest.raises(ValueError, match="cannot stand in"):
        degrade_level1(level, (100, 120), q=1.0, phi=PHI)
    with pytest.raises(ValueError, match="first level"):
        degrade_level1(level, (100, 122), q=4.34, phi=PHI)


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (gdal-bin) not installed")
def test_gdalinfo_reads_the_tile_and_its_tag(tmp_path):
    """Debian's GDAL (another build than rasterio's) reads the tile: a COG, the tag, the
    overview sizes, and checksums of the first overview equal to rasterio's."""
    img = texture(800, 800, seed=6)
    path = write_tile(tmp_path / "t.tif", img)
    info = json.loads(subprocess.run(["gdalinfo", "-json", "-checksum", str(path)],
                                     check=True, capture_output=True, text=True).stdout)
    assert info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
    assert info["metadata"][""][LEVEL1_TAG] == LEVEL1_BINOMIAL
    with rasterio.open(path, overview_level=0) as ds:
        level1 = ds.read()
    for b, band in enumerate(info["bands"]):
        assert [o["size"] for o in band["overviews"]] == [[400, 400], [200, 200]]
        # GDAL's checksum of the overview, recomputed on what rasterio decodes
        with rasterio.MemoryFile() as mem, mem.open(driver="GTiff", width=400, height=400,
                                                    count=1, dtype="uint8", crs="EPSG:32756",
                                                    transform=TRANSFORM) as one:
            one.write(level1[b], 1)
            assert one.checksum(1) == band["overviews"][0]["checksum"]
