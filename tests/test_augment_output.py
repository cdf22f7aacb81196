"""Augmented images on disk: the plain tiled GeoTIFF (and PNG) as trainers and GDAL open
them, and the pixel-interleaved layout kept from the tile read to the file written."""

from __future__ import annotations

import json
import shutil
import subprocess
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from PIL import Image
from rasterio.errors import NotGeoreferencedWarning

from geosim.augment import AugImage, Boxes, Pipeline
from geosim.augment.io import read_tile, write_image
from geosim.io.raster import write_geotiff

ROWS, COLS = 300, 270  # larger than one 256 px block: a tiled file


def _image() -> tuple[np.ndarray, np.ndarray]:
    """A smooth RGB uint8 image (pixel-interleaved) with an invalid corner set to 0."""
    rng = np.random.default_rng(4)
    small = rng.integers(0, 255, (ROWS // 10 + 1, COLS // 10 + 1, 3), dtype=np.uint8)
    hwc = cv2.resize(small, (COLS, ROWS), interpolation=cv2.INTER_CUBIC)
    mask = np.ones((ROWS, COLS), bool)
    mask[:40, :70] = False
    hwc[~mask] = 0
    return hwc, mask


def _read(path: Path) -> tuple[np.ndarray, np.ndarray, rasterio.profiles.Profile, dict]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(), ds.dataset_mask(), ds.profile, ds.tags()


@pytest.mark.parametrize("compress", ["deflate", "none"])
def test_tiff_is_plain_tiled_with_internal_mask_and_trainers_read_it(tmp_path: Path,
                                                                      compress: str) -> None:
    hwc, mask = _image()
    path = tmp_path / f"x_{compress}.tif"
    img = AugImage(np.moveaxis(hwc, -1, 0), mask)  # the pipeline's layout: a view
    write_image(path, img, georef=None, tags={"GEOSIM_ON_MAP_GRID": "false"},
                band_descriptions=("red", "green", "blue"), compress=compress)
    data, dmask, profile, tags = _read(path)
    assert np.array_equal(data, np.moveaxis(hwc, -1, 0))           # lossless
    assert np.array_equal(dmask > 0, mask) and set(np.unique(dmask)) == {0, 255}
    assert profile["tiled"] and (profile["blockxsize"], profile["blockysize"]) == (256, 256)
    assert profile["crs"] is None and tags["GEOSIM_ON_MAP_GRID"] == "false"
    assert profile.get("compress", "none").lower() == compress
    # what a trainer does: OpenCV (BGR) and Pillow read the image, first page = pixels
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1], hwc)
    with Image.open(path) as im:
        assert im.mode == "RGB" and np.array_equal(np.asarray(im), hwc)
    if compress == "none":
        assert path.stat().st_size >= hwc.nbytes
    else:
        assert path.stat().st_size < 0.8 * hwc.nbytes


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (gdal-bin) not installed")
def test_gdalinfo_sees_no_overviews_a_per_dataset_mask_and_deflate(tmp_path: Path) -> None:
    hwc, mask = _image()
    path = tmp_path / "x.tif"
    write_image(path, AugImage(np.moveaxis(hwc, -1, 0), mask), georef=None, tags={})
    doc = json.loads(subprocess.run(["gdalinfo", "-json", str(path)], capture_output=True,
                                    text=True, check=True).stdout)
    band = doc["bands"][0]
    assert not band.get("overviews") and band["block"] == [256, 256]
    assert band["mask"]["flags"] == ["PER_DATASET"]
    assert doc["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"] == "DEFLATE"
    assert doc["metadata"]["IMAGE_STRUCTURE"].get("LAYOUT") != "COG"
    assert "coordinateSystem" not in doc or not doc["coordinateSystem"].get("wkt")


@pytest.mark.parametrize("layout", ["interleaved view", "bands first"])
def test_png_holds_the_pixels_and_the_mask_as_alpha(tmp_path: Path, layout: str) -> None:
    hwc, mask = _image()
    image = (np.moveaxis(hwc, -1, 0) if layout == "interleaved view"
             else np.ascontiguousarray(np.moveaxis(hwc, -1, 0)))
    path = tmp_path / "x.png"
    write_image(path, AugImage(image, mask), georef=None, tags={})
    bgra = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(bgra[..., 2::-1], hwc)
    assert np.array_equal(bgra[..., 3], mask.astype(np.uint8) * 255)


def test_read_tile_gives_an_interleaved_view_of_the_file(tmp_path: Path) -> None:
    hwc, mask = _image()
    bands = np.ascontiguousarray(np.moveaxis(hwc, -1, 0))
    from affine import Affine

    path = tmp_path / "t.tif"
    write_geotiff(path, bands, transform=Affine(0.05, 0, 500000, 0, -0.05, 6200000),
                  crs="EPSG:32756", mask=mask)
    tile = read_tile(path, what="tile")
    assert np.array_equal(tile.data.image, bands) and np.array_equal(tile.data.mask, mask)
    assert np.moveaxis(tile.data.image, 0, -1).flags.c_contiguous   # the buffer is (r, c, b)
    plain = tmp_path / "plain.tif"   # no mask at all: everything valid
    write_geotiff(plain, bands, transform=Affine(0.05, 0, 500000, 0, -0.05, 6200000),
                  crs="EPSG:32756")
    assert read_tile(plain, what="tile").data.mask.all()


EVERY_KIND = {"pipeline": {}, "functions": [
    {"name": "mirror", "p_ud": 0.5, "p_lr": 0.5},
    {"name": "rotate", "min_deg": -10.0, "max_deg": 10.0},
    {"name": "shift", "sigma_px": 3.0},
    {"name": "local_warp", "max_px": 3.0, "filter_sigma_px": 30.0, "mode": "independent"},
    {"name": "colour", "sigma_dn": 8.0},
    {"name": "hue", "sigma_deg": 10.0},
    {"name": "noise", "sigma_dn": 2.0},
]}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_layout_of_the_input_does_not_change_the_output(seed: int) -> None:
    """A pixel-interleaved view (as tiles are read) and a contiguous bands-first array of
    the same pixels give identical outputs; neither input is modified or shared."""
    hwc, mask = _image()
    boxes = Boxes(np.zeros(1, int), np.array([[100.0, 120.0, 140.0, 150.0]]))
    view = AugImage(np.moveaxis(hwc, -1, 0), mask, boxes)
    first = AugImage(np.ascontiguousarray(np.moveaxis(hwc, -1, 0)), mask.copy(), boxes)
    before = hwc.copy()
    p = Pipeline.from_dict(EVERY_KIND)
    r1 = p.apply(view, view, np.random.default_rng(seed))
    r2 = p.apply(first, first, np.random.default_rng(seed))
    for x, y in ((r1.a, r2.a), (r1.b, r2.b)):
        assert np.array_equal(x.image, y.image) and np.array_equal(x.mask, y.mask)
        assert np.array_equal(x.boxes.xyxy_px, y.boxes.xyxy_px)
        assert not np.may_share_memory(x.image, hwc) and not np.may_share_memory(x.mask, mask)
    assert np.array_equal(hwc, before)
