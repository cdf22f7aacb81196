"""Small builders shared by tests (no fixtures with hidden state)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rasterio
from affine import Affine


def textured_rgb(rows: int, cols: int, *, seed: int = 0) -> np.ndarray:
    """A uint8 (3, rows, cols) image with multi-scale texture (filtered noise)."""
    import cv2

    rng = np.random.default_rng(seed)
    acc = np.zeros((rows, cols), np.float32)
    for sigma, weight in ((1.0, 0.3), (4.0, 0.5), (16.0, 1.0)):
        noise = rng.standard_normal((rows, cols)).astype(np.float32)
        acc += weight * cv2.GaussianBlur(noise, (0, 0), sigma) * sigma
    acc = (acc - acc.mean()) / (acc.std() + 1e-9)
    grey = np.clip(120 + 40 * acc, 1, 254)
    return np.stack([grey * 0.9, grey, grey * 0.7]).astype(np.uint8)


def pillow_jpeg(img: np.ndarray, quality: int, *, subsampling: int = -1) -> np.ndarray:
    """Pillow (libjpeg) JPEG round trip of a (3, rows, cols) image, 0–255, as float.
    ``subsampling``: -1 Pillow's default (4:2:0), 0 for 4:4:4."""
    import io

    from PIL import Image

    hwc = np.moveaxis(np.clip(np.rint(img), 0, 255).astype(np.uint8), 0, -1)
    buf = io.BytesIO()
    Image.fromarray(hwc, "RGB").save(buf, format="JPEG", quality=int(quality),
                                     subsampling=subsampling)
    buf.seek(0)
    return np.moveaxis(np.asarray(Image.open(buf).convert("RGB"), float), -1, 0)


def area_averaged_rgb(path: Path, *, start_px: int, size_px: int, side_px: int
                      ) -> np.ndarray:
    """The first three bands of a square window of the raster at ``path`` (rows and cols
    from ``start_px``, ``size_px`` wide), area-averaged to ``side_px``: float, bands first."""
    import cv2

    window = ((start_px, start_px + size_px), (start_px, start_px + size_px))
    with rasterio.open(path) as ds:
        a = ds.read(window=window)[:3].astype(np.float32)
    return np.stack([cv2.resize(b, (side_px, side_px), interpolation=cv2.INTER_AREA)
                     for b in a]).astype(float)


def write_raster(path: Path, array: np.ndarray, *, crs: str | None = "EPSG:28356",
                 transform: Affine | None = None, nodata: float | None = None) -> Path:
    """Write a plain GeoTIFF with rasterio (independent of geosim's writer)."""
    arr = array[np.newaxis] if array.ndim == 2 else array
    profile = {"driver": "GTiff", "width": arr.shape[2], "height": arr.shape[1],
               "count": arr.shape[0], "dtype": arr.dtype.name}
    if crs is not None:
        profile["crs"] = crs
        profile["transform"] = transform or Affine(0.05, 0, 250000.0, 0, -0.05, 6190000.0)
    if nodata is not None:
        profile["nodata"] = nodata
    with rasterio.open(path, "w", **profile) as dst:
        dst.write(arr)
    return path


def gdal_cache_bytes() -> int | None:
    """GDAL's block cache limit in bytes, asked of the libgdal rasterio loaded (through
    ctypes, not through rasterio, whose option handling it checks); None where that library
    cannot be found (no ``/proc/self/maps``; several libgdal, none from rasterio's wheel).

    Other packages may load their own libgdal (pyogrio's wheel does), with a cache of its
    own: rasterio's is the one in its wheel's ``rasterio.libs``, or the only one loaded.
    """
    import ctypes

    import rasterio  # noqa: F401  (loads libgdal)

    maps = Path("/proc/self/maps")
    if not maps.is_file():
        return None
    libs = {line.split()[-1] for line in maps.read_text().splitlines()
            if "libgdal" in line.split()[-1]}
    wheel = [p for p in libs if Path(p).parent.name == "rasterio.libs"]
    if len(wheel) == 1:
        path = wheel[0]
    elif len(libs) == 1:
        path = libs.pop()
    else:
        return None
    lib = ctypes.CDLL(path)
    lib.GDALGetCacheMax64.restype = ctypes.c_int64
    return int(lib.GDALGetCacheMax64())


def no_registration():
    """A diagnosis :class:`~geosim.diagnose.model.Registration` that leaves the simulation
    where it is (no shift, no field)."""
    from geosim.diagnose.model import Registration

    return Registration(estimate=None, affine=None, applied=False,  # type: ignore[arg-type]
                        shift_px=(0.0, 0.0), whole_px=(0.0, 0.0))
