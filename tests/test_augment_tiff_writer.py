"""The direct TIFF writer of augmented outputs against GDAL writing the same image.

The reference is GDAL itself (:func:`geosim.augment.io.write_geotiff_gdal`, the writer
used before): both files must read back identically through GDAL (pixels, per-dataset
mask, metadata, band descriptions, colour interpretation, structure), and through the
readers a trainer uses (OpenCV, Pillow, tifffile).
"""

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
import tifffile
from affine import Affine
from PIL import Image
from pyproj import CRS

from geosim.augment import AugImage, tiff_writer
from geosim.augment.io import write_geotiff_gdal, write_image
from geosim.io.georef import Georef

#: Values that need XML escaping, and JSON (as the runner's tags), must round-trip.
TAGS = {"GEOSIM_ON_MAP_GRID": "false", "ODD": "a<b & \"c\" 'd' >\nsecond line\ttab é",
        "GEOSIM_TRANSFORM_CHAIN": json.dumps([{"op": "rotate", "deg": 3.5, "s": "x<y"}])}


def _image(dtype: str, bands: int, shape: tuple[int, int], seed: int = 0
           ) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    hi = 255 if dtype == "uint8" else 65535
    smooth = cv2.resize(rng.integers(0, hi, (shape[0] // 8 + 2, shape[1] // 8 + 2, bands))
                        .astype(np.float32), shape[::-1], interpolation=cv2.INTER_CUBIC)
    hwc = np.clip(smooth.reshape(*shape, bands) + rng.normal(0, hi / 100, (*shape, bands)),
                  0, hi).astype(dtype)
    mask = np.ones(shape, bool)
    mask[: shape[0] // 5, : shape[1] // 3] = False     # a corner rotated out
    mask[-3:, 7:11] = False                            # a few pixels in the last tile row
    return hwc, mask


def _read_gdal(path: Path) -> dict:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with rasterio.open(path) as ds:
            return {"pixels": ds.read(), "mask": ds.dataset_mask(), "tags": ds.tags(),
                    "structure": ds.tags(ns="IMAGE_STRUCTURE"), "desc": ds.descriptions,
                    "colorinterp": ds.colorinterp, "flags": ds.mask_flag_enums,
                    "dtypes": ds.dtypes, "blocks": ds.block_shapes, "crs": ds.crs,
                    "compression": ds.compression, "overviews": ds.overviews(1)}


@pytest.mark.parametrize(("dtype", "bands", "shape"), [
    ("uint8", 3, (700, 600)), ("uint8", 3, (512, 256)), ("uint8", 1, (256, 1000)),
    ("uint16", 3, (513, 300)), ("uint16", 1, (300, 257))])
@pytest.mark.parametrize("compress", ["deflate", "none"])
def test_reads_back_through_gdal_exactly_as_the_gdal_written_file(
        tmp_path: Path, dtype: str, bands: int, shape: tuple[int, int], compress: str) -> None:
    hwc, mask = _image(dtype, bands, shape)
    img = AugImage(np.moveaxis(hwc, -1, 0), mask)      # a view, as the pipeline hands it
    desc = ["red", "band 2", "blue"][:bands]
    assert tiff_writer.supports(img.image, georeferenced=False, compress=compress)
    ours, gdal = tmp_path / "ours.tif", tmp_path / "gdal.tif"
    write_image(ours, img, georef=None, tags=TAGS, band_descriptions=desc, compress=compress)
    write_geotiff_gdal(gdal, img, georef=None, tags=TAGS, band_descriptions=desc,
                       compress=compress)
    a, b = _read_gdal(ours), _read_gdal(gdal)
    assert np.array_equal(a["pixels"], np.moveaxis(hwc, -1, 0))   # lossless
    assert np.array_equal(a["mask"] > 0, mask)
    for key in a:
        if key in ("pixels", "mask"):
            assert np.array_equal(a[key], b[key]), key
        else:
            assert a[key] == b[key], key
    assert a["tags"]["ODD"] == TAGS["ODD"] and a["desc"] == tuple(desc)
    # the internal mask is the second IFD, 1 bit, flagged as a mask (as GDAL writes it)
    with tifffile.TiffFile(ours) as tf:
        assert len(tf.pages) == 2
        assert np.array_equal(tf.pages[0].asarray().reshape(*shape, bands), hwc)
        page = tf.pages[1]
        assert page.tags["NewSubfileType"].value == 4 and page.bitspersample == 1
        assert page.photometric == 4 and page.compression == 8   # deflated, as GDAL does


@pytest.mark.parametrize("compress", ["deflate", "none"])
def test_trainers_read_it(tmp_path: Path, compress: str) -> None:
    hwc, mask = _image("uint8", 3, (600, 520), seed=1)
    path = tmp_path / "x.tif"
    write_image(path, AugImage(np.moveaxis(hwc, -1, 0), mask), georef=None, tags={},
                compress=compress)
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1], hwc)
    with Image.open(path) as im:
        assert im.mode == "RGB" and np.array_equal(np.asarray(im), hwc)
    grey, _ = _image("uint8", 1, (300, 300), seed=2)
    write_image(path, AugImage(np.moveaxis(grey, -1, 0), mask[:300, :300]), georef=None,
                tags={}, compress=compress)
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), grey[..., 0])


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (gdal-bin) not installed")
def test_system_gdal_checksums_equal_the_gdal_written_file(tmp_path: Path) -> None:
    """Debian's GDAL (a different build from rasterio's) reads the same checksums."""
    hwc, mask = _image("uint8", 3, (700, 600), seed=3)
    img = AugImage(np.moveaxis(hwc, -1, 0), mask)
    ours, gdal = tmp_path / "ours.tif", tmp_path / "gdal.tif"
    write_image(ours, img, georef=None, tags=TAGS)
    write_geotiff_gdal(gdal, img, georef=None, tags=TAGS, band_descriptions=[])

    def info(p: Path) -> list:
        doc = json.loads(subprocess.run(["gdalinfo", "-json", "-checksum", str(p)],
                                        capture_output=True, text=True, check=True).stdout)
        return [(b["checksum"], b["mask"]["flags"], b["block"]) for b in doc["bands"]]

    assert info(ours) == info(gdal)
    assert info(ours)[0][1] == ["PER_DATASET"]


def test_what_it_does_not_cover_goes_through_gdal(tmp_path: Path) -> None:
    hwc, mask = _image("uint8", 3, (300, 300))
    img = AugImage(np.moveaxis(hwc, -1, 0), mask)
    georef = Georef(Affine(0.05, 0, 500000, 0, -0.05, 6200000), CRS.from_epsg(32756), 300, 300)
    assert not tiff_writer.supports(img.image, georeferenced=True, compress="deflate")
    path = tmp_path / "geo.tif"
    write_image(path, img, georef=georef, tags={})
    with rasterio.open(path) as ds:                    # GDAL wrote the georeference
        assert ds.crs.to_epsg() == 32756 and ds.transform == georef.transform
        assert np.array_equal(ds.read(), img.image)
    for dtype, bands, shape in (("uint8", 4, (300, 300)), ("uint8", 3, (255, 600))):
        other, m = _image(dtype, bands, shape)
        assert not tiff_writer.supports(np.moveaxis(other, -1, 0), georeferenced=False,
                                        compress="deflate")
        write_image(tmp_path / "o.tif", AugImage(np.moveaxis(other, -1, 0), m), georef=None,
                    tags={})
        assert np.array_equal(_read_gdal(tmp_path / "o.tif")["pixels"],
                              np.moveaxis(other, -1, 0))
    f32 = np.moveaxis(hwc.astype(np.float32), -1, 0)
    assert not tiff_writer.supports(f32, georeferenced=False, compress="deflate")
