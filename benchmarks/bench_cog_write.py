"""Benchmark: CPU cost of writing one 5000 x 5000 RGB tile with its mask as a COG.

The tile is written exactly as ``geosim tile`` writes it (:func:`geosim.io.raster.write_geotiff`
with an internal mask: scratch GeoTIFF, then GDAL's COG driver with overviews). Imagery:
the real Brazil pasture orthomosaic mirrored out to 5000² (synthetic texture if absent),
a mask with invalid margins. Cases, alternated round by round so they see the same load:

- ``level 6, zstd scratch``: geosim before this change (GDAL's default deflate level,
  ZSTD level 1 scratch);
- ``level N, raw scratch``: deflate level N, uncompressed scratch (N = 1, 2, 3; 1 ships);
- ``level 1, zstd scratch``: the level alone;
- where the time goes: the shipped write with ``COMPRESS=NONE`` (scratch + copy +
  overviews, no deflate), with ``OVERVIEWS=NONE``, and both.

Every delivered case's decoded pixels and mask are checked equal to the array written.
Writes benchmarks/results/bench_cog_write.json and prints a markdown table.
Usage: ``python benchmarks/bench_cog_write.py [--rounds 3]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_degrade import make_tile  # noqa: E402

import geosim.io.cog as cog  # noqa: E402
from geosim.io.raster import write_geotiff  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_cog_write.json"

#: name -> (deflate level, scratch raw-bytes limit, COG overrides, delivered?)
CASES = {
    "level 6, zstd scratch (before)": (6, 0, {}, True),
    "level 1, raw scratch (shipped)": (1, cog.SCRATCH_RAW_MAX_BYTES, {}, True),
    "level 2, raw scratch": (2, cog.SCRATCH_RAW_MAX_BYTES, {}, True),
    "level 3, raw scratch": (3, cog.SCRATCH_RAW_MAX_BYTES, {}, True),
    "level 1, zstd scratch": (1, 0, {}, True),
    "raw scratch, COMPRESS=NONE": (1, cog.SCRATCH_RAW_MAX_BYTES, {"COMPRESS": "NONE"}, False),
    "raw scratch, level 1, OVERVIEWS=NONE": (1, cog.SCRATCH_RAW_MAX_BYTES,
                                              {"OVERVIEWS": "NONE"}, False),
    "raw scratch, COMPRESS=NONE, OVERVIEWS=NONE": (1, cog.SCRATCH_RAW_MAX_BYTES,
                                                    {"COMPRESS": "NONE", "OVERVIEWS": "NONE"},
                                                    False),
}


def write_once(tile: np.ndarray, mask: np.ndarray, path: Path, case: str) -> float:
    """Write the tile as ``case``; CPU seconds (this process, all threads)."""
    level, raw_max, overrides, _ = CASES[case]
    saved = cog.DEFLATE_LEVEL, cog.SCRATCH_RAW_MAX_BYTES
    cog.DEFLATE_LEVEL, cog.SCRATCH_RAW_MAX_BYTES = level, raw_max
    try:
        c0 = time.process_time()
        write_geotiff(path, tile, transform=Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0),
                      crs="EPSG:32756", mask=mask, cog_overrides=overrides)
        return time.process_time() - c0
    finally:
        cog.DEFLATE_LEVEL, cog.SCRATCH_RAW_MAX_BYTES = saved


def check_decoded(path: Path, tile: np.ndarray, mask: np.ndarray) -> None:
    with rasterio.open(path) as ds:
        assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG", path
        assert ds.overviews(1), "no overviews"
        assert np.array_equal(ds.read(), tile), "decoded pixels differ"
        assert np.array_equal(ds.read_masks(1) > 0, mask), "decoded mask differs"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    tile, source = make_tile(5000)
    mask = np.ones(tile.shape[1:], bool)
    mask[:, :300] = False
    mask[4700:, :] = False
    cpu: dict[str, list[float]] = {c: [] for c in CASES}
    size: dict[str, int] = {}
    loads = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(args.rounds):
            loads.append(round(os.getloadavg()[0], 2))
            for case in CASES:
                path = Path(tmp) / "tile.tif"
                cpu[case].append(write_once(tile, mask, path, case))
                size[case] = path.stat().st_size
                if CASES[case][3]:
                    check_decoded(path, tile, mask)
                path.unlink()
    base = "level 6, zstd scratch (before)"
    rows = [{"case": c, "cpu_s_min": round(min(v), 3),
             "cpu_s_median": round(statistics.median(v), 3), "cpu_s": [round(x, 3) for x in v],
             "file_mb": round(size[c] / 1e6, 2),
             "file_vs_before": round(size[c] / size[base] - 1, 4)} for c, v in cpu.items()]
    out = {"imagery": source, "tile": "5000x5000 RGB uint8 + internal mask",
           "rounds": args.rounds, "load_average_per_round": loads,
           "gdal": rasterio.__gdal_version__, "cases": rows}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(out, indent=2) + "\n")
    print("| case | CPU s (min / median) | file MB | vs before |\n|---|---|---|---|")
    for r in rows:
        print(f"| {r['case']} | {r['cpu_s_min']} / {r['cpu_s_median']} | {r['file_mb']} | "
              f"{100 * r['file_vs_before']:+.1f} % |")
    print(f"load average per round: {loads}; {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
