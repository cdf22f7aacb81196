"""Overviews computed in memory (geosim.io.overviews) against an analytic block mean and
against GDAL's own COG overviews of the same raster (an independent implementation)."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import rasterio
from affine import Affine

from geosim.io.cog import WholeRaster
from geosim.io.overviews import average_overviews, overview_shapes
from geosim.io.raster import create_geotiff, write_geotiff

TRANSFORM = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)


def _write(path, array, valid, *, own: bool, nodata=None, block_px=None):
    """Write ``array`` with its mask as a COG, overviews from memory (``own``) or by GDAL."""
    overrides = {} if block_px is None else {"BLOCKSIZE": block_px}
    with create_geotiff(path, width=array.shape[2], height=array.shape[1],
                        count=array.shape[0], dtype=array.dtype, crs="EPSG:32756",
                        transform=TRANSFORM, nodata=nodata, internal_mask=True,
                        band_descriptions=[f"b{i}" for i in range(array.shape[0])],
                        tags={"GEOSIM_TEST": "yes"}, cog_overrides=overrides,
                        whole=WholeRaster(array, valid, 0 if nodata is None else nodata)
                        if own else None) as dst:
        dst.write(array)
        dst.write_mask(np.where(valid, 255, 0).astype(np.uint8))
    return path


def _levels(path):
    """(pixels, mask) of every overview level of a file, as GDAL reads them."""
    with rasterio.open(path) as ds:
        n = len(ds.overviews(1))
    out = []
    for i in range(n):
        with rasterio.open(path, overview_level=i) as ds:
            out.append((ds.read(), ds.dataset_mask() > 0))
    return out


@pytest.mark.parametrize("rows, cols", [(5000, 5000), (625, 300), (257, 1000), (256, 256),
                                        (513, 513), (1, 600)])
def test_shapes_are_gdals(tmp_path, rows, cols):
    """The level sizes are those GDAL's COG driver makes for the same raster."""
    img = np.zeros((1, rows, cols), np.uint8)
    path = _write(tmp_path / "a.tif", img, np.ones((rows, cols), bool), own=False)
    with rasterio.open(path) as ds:
        gdal = [(ds.height // f, ds.width // f) for f in ds.overviews(1)]
    got = [(r, c) for r, c in overview_shapes(rows, cols, 256)]
    # rasterio gives factors; GDAL's sizes are the floor-halvings, as overview_shapes says
    assert len(got) == len(gdal)
    assert [lvl[0].shape[1:] for lvl in _levels(path)] == got


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_masked_block_mean(dtype):
    """Each level is the mean of the valid base pixels in its 2^k × 2^k block (rounded half
    up for integers), valid where any is; from the base in float64, not from the code."""
    rng = np.random.default_rng(3)
    top = 255 if dtype == np.uint8 else 60000
    base = (rng.random((2, 128, 96)) * top).astype(dtype)
    valid = rng.random((128, 96)) > 0.4
    valid[:32] = True
    valid[96:, 48:] = False          # whole blocks without data at every level
    levels = average_overviews(base, valid, 16, fill=7)
    assert [lvl.array.shape[1:] for lvl in levels] == [(64, 48), (32, 24), (16, 12)]
    for k, lvl in enumerate(levels, start=1):
        f = 2 ** k
        v = valid.reshape(128 // f, f, 96 // f, f)
        count = v.sum(axis=(1, 3))
        total = (base.astype(np.float64) * valid).reshape(2, 128 // f, f, 96 // f, f).sum(
            axis=(2, 4))
        mean = total / np.maximum(count, 1)
        assert np.array_equal(lvl.valid, count > 0)
        assert lvl.array.dtype == dtype
        assert np.all(lvl.array[:, count == 0] == 7)
        got = lvl.array[:, count > 0].astype(np.float64)
        if dtype == np.float32:
            np.testing.assert_allclose(got, mean[:, count > 0], rtol=1e-5)
        else:
            want = np.floor(mean[:, count > 0] + 0.5)
            tie = np.abs(mean[:, count > 0] % 1 - 0.5) < 1e-3  # float32 may round a tie down
            assert np.all((got == want) | (tie & (np.abs(got - want) <= 1)))


def test_all_valid_and_no_levels():
    img = np.arange(3 * 40 * 40, dtype=np.uint16).reshape(3, 40, 40)
    full = average_overviews(img, np.ones((40, 40), bool), 16)
    assert [lvl.array.shape for lvl in full] == [(3, 20, 20), (3, 10, 10)]
    assert all(lvl.valid.all() for lvl in full)
    assert average_overviews(img, None, 64) == []


@pytest.mark.parametrize("partial", [False, True])
def test_cog_matches_gdals_own_overviews(tmp_path, partial):
    """A COG written with overviews from memory reads like GDAL's: same full-resolution
    pixels and mask, metadata, level sizes and masks; pixels within GDAL's rounding."""
    rng = np.random.default_rng(5)
    rows, cols = 1300, 1100
    yy, xx = np.mgrid[:rows, :cols]
    img = np.stack([(xx * 0.17 + yy * 0.05 + 40 * np.sin(xx / 37.0) + rng.normal(0, 9, xx.shape)
                     ) % 256 for _ in range(3)]).astype(np.uint8)
    valid = np.ones((rows, cols), bool)
    if partial:
        valid &= (xx + yy + rng.integers(0, 9, xx.shape)) < 1700
        img[:, ~valid] = 0
    own = _write(tmp_path / "own.tif", img, valid, own=True)
    gdal = _write(tmp_path / "gdal.tif", img, valid, own=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["gdal.tif", "own.tif"]  # no leftovers
    with rasterio.open(own) as a, rasterio.open(gdal) as b:
        assert a.profile == b.profile and a.tags() == b.tags()
        assert a.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
        assert a.descriptions == b.descriptions and a.colorinterp == b.colorinterp
        assert a.overviews(1) == b.overviews(1) and a.mask_flag_enums == b.mask_flag_enums
        assert np.array_equal(a.read(), b.read())
        assert np.array_equal(a.dataset_mask(), b.dataset_mask())
    mine, theirs = _levels(own), _levels(gdal)
    assert len(mine) == len(theirs) == 3
    for (pa, ma), (pb, mb) in zip(mine, theirs, strict=True):
        assert np.array_equal(ma, mb)
        diff = np.abs(pa.astype(int) - pb.astype(int))[:, ma]
        assert np.percentile(diff, 99) <= 1
        if not partial:
            assert diff.max() <= 1
    # Levels 1 and 2 are exact 2 × 2 and 4 × 4 block means: ours is the mean of the valid
    # base pixels (within rounding). GDAL's level 2 is made from its level 1 weighting each
    # level-1 pixel alike however few valid pixels it came from, so along the data's edge
    # it is off by tens of DN (39 on this raster), which is why the partial case above
    # bounds only the 99th percentile of the difference.
    for (px, ok), f in zip(mine[:2], (2, 4), strict=True):
        r, c = rows // f, cols // f
        count = valid[:r * f, :c * f].reshape(r, f, c, f).sum(axis=(1, 3))
        total = (img[:, :r * f, :c * f] * valid[:r * f, :c * f].astype(np.float64)).reshape(
            3, r, f, c, f).sum(axis=(2, 4))
        assert np.array_equal(ok, count > 0)
        assert np.abs(px - total / np.maximum(count, 1))[:, ok].max() <= 0.5 + 1e-3


def test_nodata_fill_and_write_geotiff(tmp_path):
    """write_geotiff with a mask and a nodata value: overview pixels without data hold it."""
    img = np.full((1, 600, 600), 100, np.uint16)
    mask = np.zeros((600, 600), bool)
    mask[:, :300] = True
    path = write_geotiff(tmp_path / "n.tif", img, transform=TRANSFORM, crs="EPSG:32756",
                         nodata=9, mask=mask)
    (px, valid), _ = _levels(path)        # 300 px, then 150 px
    assert valid[:, :150].all() and not valid[:, 150:].any()
    assert np.all(px[:, :, :150] == 100) and np.all(px[:, :, 150:] == 9)


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (gdal-bin) not installed")
def test_gdalinfo_reads_overviews_and_mask_overviews(tmp_path):
    img = np.random.default_rng(1).integers(0, 255, (3, 700, 700), dtype=np.uint8)
    valid = np.ones((700, 700), bool)
    valid[:, :100] = False
    path = _write(tmp_path / "g.tif", img, valid, own=True)
    info = json.loads(subprocess.run(["gdalinfo", "-json", str(path)], check=True,
                                     capture_output=True, text=True).stdout)
    assert info["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
    for band in info["bands"]:
        assert [o["size"] for o in band["overviews"]] == [[350, 350], [175, 175]]
        assert band["mask"]["flags"] == ["PER_DATASET"]
        assert [o["size"] for o in band["mask"]["overviews"]] == [[350, 350], [175, 175]]
