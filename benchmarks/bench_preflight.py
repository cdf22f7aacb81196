"""Benchmark: the pre-flight full-read integrity check (geosim.validate).

Cases, each run once:

- ``sample site``: ``preflight`` on data/samples/site.toml (3 flights of ~2050 × 2030 px
  RGBA, the satellite scene; includes extents and label parsing).
- ``large flight``: ``check_raster_readable`` on a synthetic 12 000 × 12 000 px RGB
  uint8 tiled, deflate GeoTIFF (432 MB of pixels), with the peak Python-heap memory of
  the check (tracemalloc; numpy arrays are traced), to show that memory stays bounded by
  the window size and not the image size.

Writes benchmarks/results/bench_preflight.json and prints the numbers.
Usage: ``python benchmarks/bench_preflight.py``.
"""

from __future__ import annotations

import json
import platform
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

from geosim.config import load_site
from geosim.validate import check_raster_readable, preflight

ROOT = Path(__file__).resolve().parents[1]


def _large_raster(path: Path, side_px: int) -> None:
    profile = {"driver": "GTiff", "width": side_px, "height": side_px, "count": 3,
               "dtype": "uint8", "crs": "EPSG:32756", "tiled": True, "blockxsize": 256,
               "blockysize": 256, "compress": "deflate",
               "transform": Affine(0.05, 0, 255000, 0, -0.05, 6185000)}
    rng = np.random.default_rng(0)
    with rasterio.open(path, "w", **profile) as dst:
        for r in range(0, side_px, 1024):
            h = min(1024, side_px - r)
            row = rng.integers(60, 200, (3, h, side_px), dtype=np.uint8)
            dst.write(row, window=rasterio.windows.Window(0, r, side_px, h))


def main() -> None:
    results: dict[str, object] = {"python": platform.python_version()}
    site = load_site(ROOT / "data" / "samples" / "site.toml")
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        preflight(site, Path(tmp) / "run")
        results["sample_site_preflight_s"] = round(time.perf_counter() - t, 3)

        side = 12_000
        big = Path(tmp) / "big.tif"
        _large_raster(big, side)
        with rasterio.open(big) as ds:
            tracemalloc.start()
            t = time.perf_counter()
            n = check_raster_readable(ds, "large flight")
            seconds = time.perf_counter() - t
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
        results["large_flight"] = {
            "side_px": side, "pixels_read": n, "file_mb": round(big.stat().st_size / 1e6, 1),
            "image_mb": round(3 * side * side / 1e6, 1), "seconds": round(seconds, 2),
            "mpx_per_s": round(n / seconds / 1e6, 1),
            "peak_traced_mb": round(peak / 1e6, 1)}
    out = ROOT / "benchmarks" / "results" / "bench_preflight.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
