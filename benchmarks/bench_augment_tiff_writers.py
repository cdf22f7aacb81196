"""Benchmark: the direct TIFF writer against tifffile + imagecodecs for an augmented image.

Writes the same augmented-like 5000² RGB uint8 image (the real Brazil pasture resized, plus
N(0, 2 DN) noise, with 400 invalid rows, as an augmented output has) and its valid mask
with the same tags, in the same process, alternating:

- ``direct``: :func:`geosim.augment.tiff_writer.write_plain_tiff` (256 px tiles,
  predictor 2, ISA-L deflate level 1, GDAL's internal 1-bit mask IFD);
- ``tifffile_512``: :class:`tifffile.TiffWriter` with imagecodecs (512 px tiles, predictor 2,
  deflate level 1, the ``GDAL_METADATA`` tag, the mask as a second page with
  ``NewSubfileType = MASK``, ``Photometric = MASK``, 1 bit, deflated: GDAL's internal mask);
- ``tifffile_256``: the same with 256 px tiles;
- and the deflate codecs alone, level 1, on the direct writer's predicted 256 px tiles of
  the same image: ISA-L (the direct writer's), libdeflate (``imagecodecs.deflate_encode``,
  tifffile's deflate encoder when imagecodecs has it) and zlib-ng
  (``imagecodecs.zlibng_encode``).

CPU seconds per image (one thread), file size, and whether GDAL (rasterio) reads back the
same pixels, the same per-dataset mask and the same tags from each file (tifffile always adds
resolution tags, which GDAL reports as metadata: ``tags_equal_direct`` is False). Results to
``benchmarks/results/bench_augment_tiff_writers.json``.

Usage: ``python benchmarks/bench_augment_tiff_writers.py [--reps 5]``; needs ``tifffile`` and
``imagecodecs`` (not geosim dependencies).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geosim.augment import tiff_writer  # noqa: E402

REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))
OUT = ROOT / "benchmarks" / "results" / "bench_augment_tiff_writers.json"


def augmented_like(size: int = 5000) -> tuple[np.ndarray, np.ndarray]:
    """A ``(rows, cols, 3)`` uint8 image like an augmented output, and its valid mask."""
    import cv2
    import rasterio

    with rasterio.open(REALDATA / "brazil_pasture_10cm_epsg3395.tif") as ds:
        img = np.ascontiguousarray(np.moveaxis(ds.read([1, 2, 3]), 0, -1))
    hwc = cv2.resize(img, (size, size), interpolation=cv2.INTER_CUBIC)
    noise = np.random.default_rng(0).normal(0, 2, hwc.shape)
    hwc = np.clip(np.rint(hwc + noise), 0, 255).astype(np.uint8)
    mask = np.ones((size, size), bool)
    mask[:400] = False
    hwc[~mask] = 0
    return hwc, mask


TAGS = {"GEOSIM_ON_MAP_GRID": "false", "GEOSIM_SOURCE_TILE": "tiles/PA1/r000_c000.tif",
        "GEOSIM_TRANSFORM_CHAIN": '[{"step": "rotate", "rotation_deg": 7.5}]',
        "GEOSIM_NOTE": "values with <>&\"' and ü"}
DESC = ["red", "green", "blue"]


def write_tifffile(path: Path, hwc: np.ndarray, mask: np.ndarray, tile_px: int) -> None:
    """The same file through tifffile + imagecodecs (GDAL's metadata tag and mask IFD)."""
    import tifffile

    xml = tiff_writer.gdal_metadata_xml(TAGS, DESC).encode()  # UTF-8, as GDAL
    with tifffile.TiffWriter(path, bigtiff=False, byteorder="<") as tw:
        tw.write(hwc, photometric="rgb", planarconfig="contig", tile=(tile_px, tile_px),
                 compression="deflate", compressionargs={"level": 1}, predictor=2,
                 extratags=[(42112, "s", 0, xml, True)], metadata=None, software=False,
                 maxworkers=1)
        tw.write(mask, photometric=4, tile=(tile_px, tile_px),  # bool: 1-bit (bilevel)
                 compression="deflate", compressionargs={"level": 1},
                 subfiletype=4, metadata=None, software=False, maxworkers=1)


def write_direct(path: Path, hwc: np.ndarray, mask: np.ndarray) -> None:
    tiff_writer.write_plain_tiff(path, hwc, mask, tags=TAGS, band_descriptions=DESC,
                                 compress="deflate")


def read_back(path: Path) -> dict:
    """What GDAL (through rasterio) reads from a file."""
    import rasterio

    with rasterio.open(path) as ds:
        return {"pixels": ds.read(), "mask": ds.dataset_mask(), "flags": ds.mask_flag_enums,
                "tags": ds.tags(), "desc": ds.descriptions, "crs": ds.crs,
                "transform": ds.transform, "blocks": ds.block_shapes,
                "compression": str(ds.compression)}


def _codecs(hwc: np.ndarray, reps: int) -> dict[str, dict[str, float]]:
    """CPU s (median of ``reps``) and MB of each deflate codec, level 1, on the same tiles."""
    import imagecodecs
    from isal import isal_zlib

    tiles = list(tiff_writer._image_tiles(hwc, True))
    codecs = {"isal": lambda t: isal_zlib.compress(t, 1),
              "libdeflate": lambda t: imagecodecs.deflate_encode(t, level=1),
              "zlib_ng": lambda t: imagecodecs.zlibng_encode(t, level=1)}
    out = {}
    for name, enc in codecs.items():
        times = []
        for _ in range(reps):
            c0 = time.process_time()
            n = sum(len(enc(t)) for t in tiles)
            times.append(time.process_time() - c0)
        out[name] = {"cpu_s": round(float(np.median(times)), 4), "mb": round(n / 1e6, 2)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args()
    import cv2

    cv2.setNumThreads(1)
    hwc, mask = augmented_like()
    writers = {"direct": write_direct,
               "tifffile_512": lambda p, a, m: write_tifffile(p, a, m, 512),
               "tifffile_256": lambda p, a, m: write_tifffile(p, a, m, 256),
               }
    cpu: dict[str, list[float]] = {k: [] for k in writers}
    sizes: dict[str, int] = {}
    loads = []
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.reps + 1):  # rep 0: warm-up, untimed
            loads.append(round(os.getloadavg()[0], 2))
            for name, write in writers.items():
                path = Path(tmp) / f"{name}.tif"
                c0 = time.process_time()
                write(path, hwc, mask)
                dt = time.process_time() - c0
                if rep:
                    cpu[name].append(round(dt, 4))
                sizes[name] = path.stat().st_size
        ref = read_back(Path(tmp) / "direct.tif")
        same = {}
        for name in writers:
            got = read_back(Path(tmp) / f"{name}.tif")
            same[name] = {
                "pixels_equal_input": bool(np.array_equal(got["pixels"],
                                                          np.moveaxis(hwc, -1, 0))),
                "mask_equal_input": bool(np.array_equal(got["mask"] > 0, mask)),
                "mask_flags": [str(f) for f in got["flags"][0]],
                "tags_equal_direct": got["tags"] == ref["tags"],
                "descriptions_equal_direct": got["desc"] == ref["desc"],
                "no_crs": got["crs"] is None, "blocks": got["blocks"][0],
                "compression": got["compression"]}
        codec_cpu = _codecs(hwc, args.reps)
    res = {"image": "brazil pasture 5000² RGB uint8 + N(0, 2 DN) noise, 400 invalid rows",
           "codec_cpu_seconds_per_image": codec_cpu,
           "cpu_seconds_per_image": cpu,
           "cpu_seconds_median": {k: round(float(np.median(v)), 4) for k, v in cpu.items()},
           "file_mb": {k: round(v / 1e6, 2) for k, v in sizes.items()},
           "gdal_reads": same, "load_average": loads}
    Path(args.out).write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
