"""Reused scratch arrays (geosim.scratch) and the reads and pyramid levels that use them.

Truth: GDAL's own dataset mask (``dataset_mask``) and plain rasterio reads into new
arrays; the pyramid levels computed into new arrays.
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine

from geosim.degrade import core
from geosim.io.raster import read_raster, read_valid_mask
from geosim.scratch import release_scratch, scratch_array, scratch_nbytes
from tests.helpers import textured_rgb, write_raster


def test_scratch_array_is_reused_per_key_and_grows() -> None:
    release_scratch()
    a = scratch_array("t.a", (4, 5), np.float32)
    assert a.shape == (4, 5) and a.dtype == np.float32 and a.flags.c_contiguous
    a[...] = 7
    b = scratch_array("t.a", (2, 10), np.float32)  # same bytes: the same memory
    assert np.shares_memory(a, b) and (b == 7).all()
    c = scratch_array("t.a", (3, 3), np.uint8)  # fewer bytes: a view of the same memory
    assert np.shares_memory(a, c)
    d = scratch_array("t.a", (100, 100), np.float64)  # more: a new, larger array
    assert not np.shares_memory(a, d) and d.shape == (100, 100)
    other = scratch_array("t.b", (4, 5), np.float32)
    assert not np.shares_memory(d, other)
    assert scratch_nbytes() == d.nbytes + other.nbytes
    seen: list[np.ndarray] = []
    thread = threading.Thread(target=lambda: seen.append(scratch_array("t.b", (4, 5),
                                                                       np.float32)))
    thread.start()
    thread.join()
    assert not np.shares_memory(seen[0], other)  # each thread has its own pool
    release_scratch()
    assert scratch_nbytes() == 0


def _tile_with_internal_mask(path: Path, image: np.ndarray, valid: np.ndarray) -> Path:
    profile = {"driver": "GTiff", "width": image.shape[2], "height": image.shape[1],
               "count": image.shape[0], "dtype": "uint8", "crs": "EPSG:28356",
               "transform": Affine(0.05, 0, 250000.0, 0, -0.05, 6190000.0),
               "tiled": True, "blockxsize": 64, "blockysize": 64, "compress": "deflate",
               "predictor": 2}
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(path, "w", **profile) as ds:
        ds.write(image)
        ds.write_mask(valid.astype(np.uint8) * 255)
    return path


@pytest.mark.parametrize("kind", ["internal_mask", "nodata", "alpha", "none"])
def test_reads_into_reused_buffers_equal_fresh_reads(tmp_path: Path, kind: str) -> None:
    rng = np.random.default_rng(3)
    rows, cols = 150, 170
    files = []
    for i in range(2):  # two different rasters read one after the other into the buffers
        image = textured_rgb(rows, cols, seed=i)
        valid = np.ones((rows, cols), bool)
        valid[rng.integers(0, rows, 40), rng.integers(0, cols, 40)] = False
        valid[:, : 10 + 20 * i] = False
        path = tmp_path / f"{kind}{i}.tif"
        if kind == "internal_mask":
            _tile_with_internal_mask(path, image, valid)
        elif kind == "nodata":
            write_raster(path, np.where(valid, np.maximum(image, 1), 0).astype(np.uint8),
                         nodata=0)
        elif kind == "alpha":
            write_raster(path, np.concatenate([image, 255 * valid[None].astype(np.uint8)]))
        else:
            write_raster(path, image)
        files.append(path)
    for path in files:
        fresh = read_raster(path)
        for to_8bit in (True, False):  # 0/255 or 0/1 internal masks: both are "non-zero"
            with rasterio.Env(GDAL_TIFF_INTERNAL_MASK_TO_8BIT=to_8bit):
                reused = read_raster(path, reuse_buffers=True)
            np.testing.assert_array_equal(reused.array, fresh.array)
            np.testing.assert_array_equal(reused.valid, fresh.valid)
        with rasterio.open(path) as ds:  # GDAL's own dataset mask (alpha for RGBA)
            truth = (ds.read(4) if kind == "alpha" else ds.dataset_mask()) > 0
            out = np.empty((rows, cols), bool)
            assert read_valid_mask(ds, out=out) is out
        np.testing.assert_array_equal(out, truth)
        np.testing.assert_array_equal(reused.valid, truth)
    first = read_raster(files[0], reuse_buffers=True)
    second = read_raster(files[1], reuse_buffers=True)
    assert np.shares_memory(first.array, second.array)  # as documented: valid until next read


def test_pyramid_levels_in_reused_buffers_equal_fresh_ones() -> None:
    rng = np.random.default_rng(5)
    for shape in ((1024, 768), (512, 640), (1024, 768)):  # sizes change between calls
        for dtype in (np.uint8, np.float32):
            band = rng.integers(0, 256, shape).astype(dtype)
            fresh, g_r, g_c = core.reduce_band_limited(band, 43.4)
            reused, h_r, h_c = core.reduce_band_limited(band, 43.4, reuse_buffers=True)
            np.testing.assert_array_equal(reused, fresh)
            np.testing.assert_array_equal(h_r, g_r)
            np.testing.assert_array_equal(h_c, g_c)
    # the degrader's coefficients do not depend on what the buffers held before
    a, b = textured_rgb(640, 700, seed=1), textured_rgb(640, 700, seed=2)
    fresh = core.SpectralDegrader(a, phi=10, q_min=4.34).degrade(4.34)
    release_scratch()
    first = core.SpectralDegrader(a, phi=10, q_min=4.34, reuse_buffers=True).degrade(4.34)
    held = scratch_nbytes()
    assert held > 0
    core.SpectralDegrader(b, phi=10, q_min=4.34, reuse_buffers=True)
    again = core.SpectralDegrader(a, phi=10, q_min=4.34, reuse_buffers=True).degrade(4.34)
    np.testing.assert_array_equal(first, fresh)
    np.testing.assert_array_equal(again, fresh)
    assert scratch_nbytes() == held  # same size: the same buffers, nothing more held
    core.SpectralDegrader(b, phi=10, q_min=4.34)  # not asked to: leaves the pool alone
    assert scratch_nbytes() == held
    release_scratch()
