"""Readers that reduce while they read return RasterData with the right georeference.

Truth is GDAL's own command-line tools run on the same file: ``gdal_translate -srcwin
-outsize -r average`` for an area average by φ and a plain window, ``gdalwarp -te -tr
-r average`` for the overlay check's common grid. Their geotransforms and pixels are
compared with what the geosim readers return.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from rasterio.windows import Window

from geosim.degrade.steps import _grey_reader
from geosim.io.raster import RasterData
from geosim.overlay.check import common_grid, read_on_grid
from geosim.prepare.anchor import read_averaged_window
from tests.helpers import textured_rgb, write_raster

pytestmark = pytest.mark.skipif(shutil.which("gdal_translate") is None
                                or shutil.which("gdalwarp") is None,
                                reason="GDAL command-line tools (gdal-bin) not installed")

#: BT.601 luma weights (R, G, B), written out here rather than taken from geosim.
LUMA = (0.299, 0.587, 0.114)

UAV_T = Affine(0.05, 0.0, 250000.0, 0.0, -0.05, 6190000.0)


def _gdal(*args: str | Path) -> None:
    subprocess.run([str(a) for a in args], check=True, capture_output=True)


def _gdal_read(path: Path) -> tuple[np.ndarray, Affine, rasterio.crs.CRS]:
    with rasterio.open(path) as ds:
        return ds.read().astype(np.float64), ds.transform, ds.crs


def _luma(bands: np.ndarray) -> np.ndarray:
    return sum(w * bands[i] for i, w in enumerate(LUMA))


def _assert_same_transform(got: Affine, want: Affine) -> None:
    np.testing.assert_allclose(list(got)[:6], list(want)[:6], rtol=0, atol=1e-9)


@pytest.fixture(scope="module")
def uav_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-band float32 raster on a 0.05 m grid (plain rasterio writer); float so that
    GDAL's average is not rounded to whole DN."""
    path = tmp_path_factory.mktemp("edges") / "uav.tif"
    rgb = textured_rgb(240, 360, seed=41).astype(np.float32) + np.float32(0.25)
    return write_raster(path, rgb, transform=UAV_T)


@pytest.mark.parametrize("window", [Window(20, 40, 200, 120),    # inside
                                    Window(-30, -20, 150, 90),   # reaches outside (NW)
                                    Window(300, 200, 90, 60)])   # reaches outside (SE)
def test_area_average_carries_the_averaged_grid(uav_tif: Path, tmp_path: Path,
                                                window: Window) -> None:
    """read_averaged_window = gdal_translate -srcwin … -outsize /φ -r average, georeference
    and pixels (where every UAV pixel under a satellite pixel is inside the raster)."""
    phi = 10
    data = read_averaged_window(uav_tif, window, phi, block_px=50)  # several blocks
    assert isinstance(data, RasterData)
    rows, cols = int(window.height) // phi, int(window.width) // phi
    assert data.array.shape == (1, rows, cols) and data.array.dtype == np.float32
    assert data.band_names == ("grey",) and data.crs == "EPSG:28356"
    # the exact reduced transform, from the file's transform by hand
    _assert_same_transform(data.transform, Affine(
        0.5, 0.0, 250000.0 + 0.05 * window.col_off, 0.0, -0.5,
        6190000.0 - 0.05 * window.row_off))

    out = tmp_path / "gdal.tif"
    _gdal("gdal_translate", "-q", "-ot", "Float32", "-r", "average",
          "-srcwin", int(window.col_off), int(window.row_off), int(window.width),
          int(window.height), "-outsize", cols, rows, uav_tif, out)
    bands, t_gdal, crs = _gdal_read(out)
    _assert_same_transform(data.transform, t_gdal)
    assert data.crs == crs

    inside = np.zeros((rows, cols), bool)
    r0, c0 = int(window.row_off) // phi, int(window.col_off) // phi
    for i in range(rows):
        for j in range(cols):
            inside[i, j] = (0 <= r0 + i < 240 // phi) and (0 <= c0 + j < 360 // phi)
    np.testing.assert_array_equal(data.valid, inside)
    np.testing.assert_allclose(data.array[0][inside], _luma(bands)[inside], rtol=0, atol=1e-3)


def test_calibrate_grey_window_is_georeferenced(uav_tif: Path, tmp_path: Path) -> None:
    """The calibration's grey window reader: window offsets relative to (row0, col0),
    partly outside the raster; georeference and pixels as gdal_translate -srcwin."""
    row0, col0 = 100, 150
    r, c, h, w = -140, 120, 180, 130   # raster rows -40..140, cols 270..400 (cols > 360 out)
    from geosim.prepare.aligned import AlignedFlight

    # the reader takes a flight on the aligned grid (here: a stored raster on that grid)
    with AlignedFlight.from_raster("F", uav_tif).open() as ds:
        data = _grey_reader(ds, row0, col0, None)(r, c, h, w)
        empty = _grey_reader(ds, row0, col0, None)(500, 0, 20, 20)
    assert data.array.shape == (1, h, w) and data.band_names == ("grey",)
    _assert_same_transform(data.transform, Affine(
        0.05, 0.0, 250000.0 + 0.05 * (col0 + c), 0.0, -0.05, 6190000.0 - 0.05 * (row0 + r)))

    out = tmp_path / "gdal.tif"
    _gdal("gdal_translate", "-q", "-srcwin", col0 + c, row0 + r, w, h, uav_tif, out)
    bands, t_gdal, crs = _gdal_read(out)
    _assert_same_transform(data.transform, t_gdal)
    assert data.crs == crs
    rows = np.arange(h)[:, None] + row0 + r
    cols = np.arange(w)[None, :] + col0 + c
    inside = (rows >= 0) & (rows < 240) & (cols >= 0) & (cols < 360)
    np.testing.assert_array_equal(data.valid, inside)
    np.testing.assert_allclose(data.array[0][inside], _luma(bands)[inside], rtol=0, atol=1e-3)
    assert not data.array[0][~inside].any()
    # a window wholly outside: no data, still placed where asked
    assert not empty.valid.any() and not empty.array.any()
    _assert_same_transform(empty.transform, UAV_T * Affine.translation(col0, row0 + 500))


def test_overlay_grid_read_matches_gdalwarp(tmp_path: Path) -> None:
    """read_on_grid of a finer raster in another CRS = gdalwarp -r average onto the common
    grid: same georeference, same pixels (a one-pixel misplacement would not match)."""
    a = write_raster(tmp_path / "a.tif", textured_rgb(200, 200, seed=42), crs="EPSG:32756",
                     transform=Affine(0.2, 0.0, 500000.0, 0.0, -0.2, 6200000.0))
    # b: the same area in GDA94 / MGA 56, 0.05 m (4× finer: averaged onto the grid)
    b = tmp_path / "b.tif"
    _gdal("gdalwarp", "-q", "-t_srs", "EPSG:28356", "-tr", "0.05", "0.05", "-r", "cubic",
          a, b)
    with rasterio.open(a) as da, rasterio.open(b) as db:
        grid = common_grid(da, db)
        data = read_on_grid(db, grid)
    assert grid.gsd_m == pytest.approx(0.2)
    assert data.array.shape == (1, *grid.shape) and data.band_names == ("grey",)
    assert data.crs == "EPSG:32756"

    out = tmp_path / "gdal.tif"
    left, top = grid.transform.c, grid.transform.f
    rows, cols = grid.shape
    _gdal("gdalwarp", "-q", "-t_srs", "EPSG:32756", "-te", left, top - 0.2 * rows,
          left + 0.2 * cols, top, "-ts", cols, rows, "-r", "average", "-ot", "Float32",
          "-dstnodata", "nan", b, out)
    bands, t_gdal, crs = _gdal_read(out)
    _assert_same_transform(data.transform, t_gdal)
    assert data.crs == crs
    want = bands.mean(axis=0)
    ok = data.valid & np.isfinite(want)
    assert ok.mean() > 0.9
    diff = np.abs(data.array[0][ok] - want[ok])
    assert np.median(diff) < 0.05 and diff.max() < 1.0
    # the check can fail: the same comparison one grid pixel off is far from equal
    shifted = np.abs(data.array[0][:, 1:] - want[:, :-1])[ok[:, 1:] & ok[:, :-1]]
    assert np.median(shifted) > 1.0
