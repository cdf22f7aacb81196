"""Benchmark: how a UAV tile's compression changes what the degrade step pays to read it.

One 5000 × 5000 RGB uint8 tile of real imagery (the Brazil pasture orthomosaic of
../shared/realdata mirrored out, or synthetic texture; as bench_degrade_command.py makes
it) with its internal mask is written as ``geosim tile`` writes tiles (COG, overviews,
internal mask) with each set of compression options below. For each: the file size, the
CPU of writing it (the COG copy included), the CPU of reading it the way the degrade step
does (:func:`geosim.io.raster.read_raster` of image + mask, one GDAL thread as on a Dask
worker, the 1-bit mask read as 0/1), read ``--rounds`` times with the codecs alternated
(median and min), and whether OpenCV (``cv2.imread``) and Pillow (``Image.open``) —
what detector trainers read tiles with — decode the full-resolution image to the same
pixels.

Usage: ``python benchmarks/bench_tile_codec.py [--size 5000] [--rounds 7] [--out FILE]``
(default benchmarks/results/bench_tile_codec.json at --size 5000).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
RESULT = ROOT / "benchmarks" / "results" / "bench_tile_codec.json"

#: Name → COG options replacing geosim's (``geosim.io.cog.cog_options``: DEFLATE level 1,
#: horizontal predictor, 256 px blocks).
CODECS: dict[str, dict] = {
    "deflate1_pred (shipped)": {},
    "deflate1_nopred": {"PREDICTOR": "NO"},
    "deflate6_pred": {"LEVEL": 6},
    "deflate9_pred": {"LEVEL": 9},
    "deflate1_pred_512px": {"BLOCKSIZE": 512},
    "lzw_pred": {"COMPRESS": "LZW"},
    "packbits": {"COMPRESS": "PACKBITS", "PREDICTOR": "NO"},
    "none": {"COMPRESS": "NONE", "PREDICTOR": "NO"},
    "zstd9_pred": {"COMPRESS": "ZSTD", "LEVEL": 9},
}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _read_cpu(path: Path) -> float:
    import rasterio

    from geosim.io.raster import read_raster

    c0 = _cpu()
    with rasterio.Env(GDAL_NUM_THREADS="1", GDAL_TIFF_INTERNAL_MASK_TO_8BIT=False):
        read_raster(path, what="tile", reuse_buffers=True)
    return _cpu() - c0


def _external_readers(path: Path, rgb: np.ndarray) -> dict[str, str]:
    """Whether OpenCV and Pillow decode the full-resolution image to the same pixels."""
    import cv2
    from PIL import Image

    out = {}
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            out["opencv"] = "cannot read"
        else:
            same = img.shape == rgb.shape and np.array_equal(img[..., ::-1], rgb)
            out["opencv"] = "same pixels" if same else f"different pixels {img.shape}"
    except Exception as exc:  # noqa: BLE001 - any failure of the reader is the answer
        out["opencv"] = f"error: {type(exc).__name__}: {exc}"[:200]
    try:
        Image.MAX_IMAGE_PIXELS = None
        with Image.open(path) as im:
            arr = np.asarray(im)
        same = arr.shape == rgb.shape and np.array_equal(arr, rgb)
        out["pillow"] = "same pixels" if same else f"different pixels {arr.shape}"
    except Exception as exc:  # noqa: BLE001
        out["pillow"] = f"error: {type(exc).__name__}: {exc}"[:200]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=5000)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    from affine import Affine
    from bench_degrade import make_tile

    from geosim.engine import task_limits
    from geosim.io.raster import write_geotiff

    tile, source = make_tile(args.size)
    rgb = np.ascontiguousarray(np.moveaxis(tile, 0, -1))
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    mask = np.ones(tile.shape[1:], bool)
    rows: dict[str, dict] = {}
    load0 = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory() as tmp, task_limits(1):
        paths = {}
        for name, opts in CODECS.items():
            path = Path(tmp) / f"{name.split()[0]}.tif"
            c0 = _cpu()
            write_geotiff(path, tile, transform=t, crs="EPSG:32756", mask=mask,
                          cog_overrides=opts)
            rows[name] = {"options": opts, "file_mb": round(path.stat().st_size / 1e6, 1),
                          "write_cpu_s": round(_cpu() - c0, 2),
                          **_external_readers(path, rgb)}
            paths[name] = path
            print(name, rows[name], flush=True)
        for name in CODECS:  # warm: first read of each file (page cache, GDAL's first open)
            _read_cpu(paths[name])
        reads: dict[str, list[float]] = {name: [] for name in CODECS}
        for _ in range(args.rounds):
            for name in CODECS:
                reads[name].append(_read_cpu(paths[name]))
    for name, vals in reads.items():
        rows[name]["read_cpu_s_median"] = round(float(np.median(vals)), 4)
        rows[name]["read_cpu_s_min"] = round(min(vals), 4)
        print(name, rows[name], flush=True)
    import cv2
    import PIL
    import rasterio

    doc = {"benchmark": "bench_tile_codec", "tile_px": args.size, "imagery": source,
           "rounds": args.rounds,
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                       "gdal": rasterio.__gdal_version__, "opencv": cv2.__version__,
                       "pillow": PIL.__version__, "load_average_at_start": load0,
                       "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
           "codecs": rows}
    out = args.out if args.out is not None else (RESULT if args.size == 5000 else None)
    if out is not None:
        out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
