"""Benchmark: augmented pairs per second for a 5000 × 5000 and a 500 × 500 pair.

A 5000 × 5000 pair is a UAV tile pair at 0.05 m (250 m × 250 m); a 500 × 500 pair
is the same ground degraded to 0.5 m (the shipped config's lengths are rescaled
by the GSD, so its warp and shifts mean the same metres on both). Imagery: the
real Brazil pasture orthomosaic from ../shared/realdata resized to the pair size
(synthetic texture if absent), RGB uint8, 40 cattle-sized boxes per image.

Cases, each run once:

- ``shipped``: the shipped example config (geosim/augment/default_augment.toml)
  with its probabilities: the average cost of a typical output.
- ``all applied``: the same config with every probability set to 1 (worst case).
- per function: each function alone, probability 1 (where the time goes).
- ``end to end``: ``run_augment`` on a run folder (read GeoTIFF tiles, augment,
  write GeoTIFF + YOLO + CSVs).

Writes benchmarks/results/bench_augment.json and prints a markdown table.
Usage: ``python benchmarks/bench_augment.py [--quick]``.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geosim.augment import AugImage, Boxes, Pipeline, load_pipeline  # noqa: E402
from geosim.augment.runner import run_augment  # noqa: E402
from geosim.io.raster import write_geotiff  # noqa: E402

REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))
OUT = ROOT / "benchmarks" / "results" / "bench_augment.json"


def _texture(size: int, seed: int) -> np.ndarray:
    src = REALDATA / "brazil_pasture_10cm_epsg3395.tif"
    if src.is_file():
        import rasterio

        with rasterio.open(src) as ds:
            img = ds.read([1, 2, 3])
        hwc = np.ascontiguousarray(np.moveaxis(img, 0, -1))
        if seed:  # the second image of the pair: the same ground, slightly changed
            hwc = np.ascontiguousarray(np.roll(hwc, 3, axis=1))
        out = cv2.resize(hwc, (size, size), interpolation=cv2.INTER_CUBIC)
        return np.ascontiguousarray(np.moveaxis(out, -1, 0))
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (3, size // 16 + 1, size // 16 + 1), dtype=np.uint8)
    return np.stack([cv2.resize(b, (size, size), interpolation=cv2.INTER_CUBIC) for b in small])


def _pair(size: int) -> tuple[AugImage, AugImage]:
    rng = np.random.default_rng(0)
    cattle_px = 40 * size / 5000  # ~2 m at 0.05 m
    xy = rng.uniform(0.1 * size, 0.9 * size, (40, 2))
    boxes = Boxes(np.zeros(40, int), np.column_stack([xy, xy + [cattle_px, cattle_px / 2]]))
    mask = np.ones((size, size), bool)
    return (AugImage(_texture(size, 0), mask, boxes), AugImage(_texture(size, 1), mask, boxes))


def _time_pipeline(p: Pipeline, a: AugImage, b: AugImage, n: int, length_scale: float
                   ) -> dict:
    p.apply(a, b, np.random.default_rng(10_000), length_scale=length_scale)  # warm-up
    t0, c0 = time.perf_counter(), time.process_time()
    for i in range(n):
        p.apply(a, b, np.random.default_rng(i), length_scale=length_scale)
    dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"pairs": n, "seconds": round(dt, 3), "pairs_per_second": round(n / dt, 3),
            "seconds_per_pair": round(dt / n, 4), "cpu_seconds_per_pair": round(cpu / n, 4)}


def _all_applied(p: Pipeline) -> Pipeline:
    return replace(p, steps=tuple(replace(s, probability=1.0) for s in p.steps))


def _end_to_end(size: int, n: int, a: AugImage, b: AugImage) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "run"
        gsd = 0.05 if size >= 5000 else 0.05 * 5000 / size
        t = Affine(gsd, 0, 500000, 0, -gsd, 6200000)
        for flight, img in (("PA1", a), ("PA2", b)):
            write_geotiff(d / "tiles" / flight / "r000_c000.tif", img.image, transform=t,
                          crs="EPSG:32756")
            lab = d / "labels" / "yolo" / flight
            lab.mkdir(parents=True)
            lines = [f"{r[0]:.0f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} {r[4]:.6f}"
                     for r in img.boxes.to_yolo(img.shape)]
            (lab / "r000_c000.txt").write_text("\n".join(lines) + "\n")
        with open(d / "pairs.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["pair_id", "tile_id", "flight_a", "flight_b", "acquired_a", "acquired_b",
                        "path_a", "path_b", "minx", "miny", "maxx", "maxy", "crs"])
            w.writerow(["p0", "r000_c000", "PA1", "PA2", "", "", "tiles/PA1/r000_c000.tif",
                        "tiles/PA2/r000_c000.tif", 0, 0, 1, 1, "EPSG:32756"])
        t0, c0 = time.perf_counter(), time.process_time()
        s = run_augment(d / "pairs.csv", load_pipeline(), n=n, out_dir=Path(tmp) / "aug",
                        seed=1)
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"pairs": n, "seconds": round(dt, 3), "pairs_per_second": round(n / dt, 3),
            "seconds_per_pair": round(dt / n, 4), "cpu_seconds_per_pair": round(cpu / n, 4),
            "boxes_out": s["boxes_out"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    args = ap.parse_args()
    shipped = load_pipeline()
    full = _all_applied(shipped)
    reps = {5000: (2, 1) if args.quick else (4, 1), 500: (20, 10) if args.quick else (60, 20)}
    results: dict = {
        "machine": {"python": platform.python_version(), "platform": platform.platform(),
                    "cpus": os.cpu_count(), "numpy": np.__version__, "opencv": cv2.__version__,
                    "opencv_threads": cv2.getNumThreads(),
                    "load_average_at_start": [round(x, 2) for x in os.getloadavg()]},
        "imagery": "realdata brazil pasture resized" if (
            REALDATA / "brazil_pasture_10cm_epsg3395.tif").is_file() else "synthetic texture",
        "config": "geosim/augment/default_augment.toml", "cases": []}
    for size in (5000, 500):
        a, b = _pair(size)
        ls = 1.0 if size == 5000 else 0.1  # lengths: 0.05 m reference → this GSD
        n_main, n_fn = reps[size]
        for label, p, n in (("shipped", shipped, n_main), ("all applied", full, n_main)):
            r = _time_pipeline(p, a, b, n, ls)
            results["cases"].append({"size_px": size, "case": label, **r})
            print(f"{size} {label}: {r}", flush=True)
        for step in shipped.steps:
            p = Pipeline((replace(step, probability=1.0),), reference_gsd_m=None)
            r = _time_pipeline(p, a, b, n_fn, ls)
            results["cases"].append({"size_px": size, "case": f"only {step.function.name}", **r})
            print(f"{size} only {step.function.name}: {r}", flush=True)
        r = _end_to_end(size, n_fn, a, b)
        results["cases"].append({"size_px": size, "case": "end to end (GeoTIFF in/out)", **r})
        print(f"{size} end to end: {r}", flush=True)
        del a, b
    results["machine"]["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    results["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(results, indent=2) + "\n")
    print()
    print("| pair size (px) | case | pairs | pairs/s | wall s/pair | CPU s/pair |")
    print("|---|---|---|---|---|---|")
    for c in results["cases"]:
        print(f"| {c['size_px']} | {c['case']} | {c['pairs']} | {c['pairs_per_second']} | "
              f"{c['seconds_per_pair']} | {c['cpu_seconds_per_pair']} |")
    m = results["machine"]
    print(f"\n{m['cpus']} CPUs, load average {m['load_average_at_start'][0]} at start, "
          f"{m['load_average_at_end'][0]} at end (shared machine: wall times include waiting); "
          f"peak RSS {results['peak_rss_mb']} MB; results in {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
