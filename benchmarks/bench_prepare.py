"""Benchmark of the preparation steps on a synthetic 10000 × 10000 RGB flight.

Makes two synthetic flights (RGB, 0.05 m, EPSG:32756, written window by window):
``B1`` shows a smooth random "world"; ``B2`` shows the same world but states a
georeference displaced by a known similarity (rotation 0.2°, scale 1.001, shift
(0.8, −0.5) m). Then runs each step (grid, footprints, align, tiles, pairs) in a
fresh Python process and records wall time and peak resident memory of that
process (``VmHWM`` from ``/proc/self/status``; ``ru_maxrss`` elsewhere), plus the
baseline of a process that only imports geosim and loads the site.

Usage::

    python benchmarks/bench_prepare.py [--size-px 10000] [--keep DIR]

Writes ``benchmarks/results/bench_prepare.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "bench_prepare.json"
GSD_M = 0.05
LATTICE_M = 0.25           # spacing of the world's random lattice (texture scale)
ORIGIN = (300000.0, 6200000.0)
ERROR = {"rotation_deg": 0.2, "scale": 1.001, "shift_m": (0.8, -0.5)}


def similarity_about(cx: float, cy: float, rotation_deg: float, scale: float,
                     shift_m: tuple[float, float]) -> Affine:
    """Rotate counter-clockwise and scale about (cx, cy), then shift (map metres)."""
    return (Affine.translation(cx + shift_m[0], cy + shift_m[1]) @ Affine.rotation(rotation_deg)
            @ Affine.scale(scale) @ Affine.translation(-cx, -cy))


def make_flight(path: Path, lattice: np.ndarray, *, size_px: int, stated: Affine,
                error: Affine, block_px: int = 2048) -> None:
    """Write a flight window by window: pixel (c, r) shows the world at error⁻¹(stated(c, r))."""
    lat_t = Affine(LATTICE_M, 0, ORIGIN[0] - 20.0, 0, -LATTICE_M, ORIGIN[1] + 20.0)
    to_lat = ~lat_t @ ~error @ stated        # flight corner coords → lattice corner coords
    profile = {"driver": "GTiff", "width": size_px, "height": size_px, "count": 3,
               "dtype": "uint8", "crs": "EPSG:32756", "transform": stated, "tiled": True,
               "blockxsize": 512, "blockysize": 512, "compress": "deflate", "BIGTIFF": "YES"}
    rng = np.random.default_rng(1)
    with rasterio.open(path, "w", **profile) as dst:
        for r0 in range(0, size_px, block_px):
            for c0 in range(0, size_px, block_px):
                h, w = min(block_px, size_px - r0), min(block_px, size_px - c0)
                cc, rr = np.meshgrid(np.arange(c0, c0 + w) + 0.5, np.arange(r0, r0 + h) + 0.5)
                mx = (to_lat.a * cc + to_lat.b * rr + to_lat.c - 0.5).astype(np.float32)
                my = (to_lat.d * cc + to_lat.e * rr + to_lat.f - 0.5).astype(np.float32)
                g = cv2.remap(lattice, mx, my, cv2.INTER_CUBIC)
                g = g + rng.normal(0, 2.0, g.shape).astype(np.float32)
                img = np.clip(np.stack([g, 0.9 * g + 10, 0.75 * g + 20]), 0, 255)
                dst.write(img.astype(np.uint8), window=((r0, r0 + h), (c0, c0 + w)))


STEP_CODE = """
import json, resource, sys, time
from pathlib import Path
from geosim.config import load_site
from geosim.prepare import steps

def peak_rss_mb():
    # VmHWM: this process's own high-water mark (ru_maxrss would include the parent's
    # peak at fork time, which Linux carries across exec)
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

site = load_site(sys.argv[1]); out = Path(sys.argv[2]); name = sys.argv[3]
t0 = time.perf_counter()
summary = getattr(steps, "run_" + name)(site, out) if name != "baseline" else {}
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "peak_rss_mb": peak_rss_mb(), "summary": summary},
                 default=str))
"""


def run_step(site: Path, out: Path, name: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", STEP_CODE, str(site), str(out), name],
                         capture_output=True, text=True, env=env, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"step {name} failed:\n{res.stderr[-3000:]}")
    info = json.loads(res.stdout.strip().splitlines()[-1])
    info["wall_seconds"] = time.perf_counter() - t0
    return info


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-px", type=int, default=10000)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: temp)")
    args = ap.parse_args()
    n = args.size_px
    with tempfile.TemporaryDirectory(prefix="bench_prepare_") as tmp:
        work = args.keep or Path(tmp)
        (work / "flights").mkdir(parents=True, exist_ok=True)
        side_m = n * GSD_M
        rng = np.random.default_rng(0)
        lat_n = int(math.ceil((side_m + 40.0) / LATTICE_M)) + 4
        lattice = cv2.GaussianBlur(rng.normal(0, 1, (lat_n, lat_n)).astype(np.float32),
                                   (0, 0), 1.0)
        lattice = (120 + 35 * lattice / lattice.std()).astype(np.float32)
        stated = Affine(GSD_M, 0, ORIGIN[0], 0, -GSD_M, ORIGIN[1])
        centre = (ORIGIN[0] + side_m / 2, ORIGIN[1] - side_m / 2)
        t0 = time.perf_counter()
        make_flight(work / "flights" / "B1.tif", lattice, size_px=n, stated=stated,
                    error=Affine.identity())
        make_flight(work / "flights" / "B2.tif", lattice, size_px=n, stated=stated,
                    error=similarity_about(*centre, **ERROR))
        gen_s = time.perf_counter() - t0
        del lattice
        (work / "site.toml").write_text(
            '[site]\nname = "bench"\ncrs = "EPSG:32756"\nreference_flight = "B1"\n'
            '[parameters]\nkeep_partial_tiles = true\n'
            '[[flights]]\nid = "B1"\nimage = "flights/B1.tif"\n'
            'acquired = "2021-07-15T11:00:00+10:00"\n'
            '[[flights]]\nid = "B2"\nimage = "flights/B2.tif"\n'
            'acquired = "2021-07-16T11:00:00+10:00"\n')
        out = work / "run"
        results = {"baseline": run_step(work / "site.toml", out, "baseline")}
        for name in ("grid", "footprints", "align", "tiles", "pairs"):
            results[name] = run_step(work / "site.toml", out, name)
            print(f"{name}: {results[name]['seconds']:.1f} s, "
                  f"peak {results[name]['peak_rss_mb']:.0f} MB", file=sys.stderr)
        doc = json.loads((out / "alignment.json").read_text())
        b2 = doc["flights"]["B2"]
        truth = ~similarity_about(*centre, **ERROR)
        c = b2["center_m"]
        tc = truth @ c
        record = {
            "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                        "platform": platform.platform()},
            "flight_px": [n, n], "bands": 3, "dtype": "uint8", "flights": 2,
            "parameters": {"tile_px": 5000, "align_window_px": 2000, "keep_partial_tiles": True},
            "tiles": results["tiles"]["summary"],
            "generate_seconds": round(gen_s, 1),
            "one_flight_uncompressed_mb": round(n * n * 3 / 2**20, 1),
            "steps": {k: {"seconds": round(v["seconds"], 2),
                          "peak_rss_mb": round(v["peak_rss_mb"], 1)}
                      for k, v in results.items()},
            "alignment_B2": {
                "recovered": {k: b2[k] for k in ("shift_m", "rotation_deg", "scale",
                                                 "confidence")},
                "truth": {"shift_m": [tc[0] - c[0], tc[1] - c[1]],
                          "rotation_deg": math.degrees(math.atan2(truth.d, truth.a)),
                          "scale": math.sqrt(abs(truth.determinant))},
                "local_check": doc["local_check"].get("B2"),
            },
        }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(record, indent=2) + "\n")
    base = record["steps"]["baseline"]["peak_rss_mb"]
    print(f"\nprepare steps, 2 synthetic {n}×{n} RGB flights "
          f"({record['one_flight_uncompressed_mb']} MB each uncompressed); "
          f"baseline process {base:.0f} MB\n")
    print("| step | time (s) | peak RSS (MB) |\n|---|---:|---:|")
    for k, v in record["steps"].items():
        if k != "baseline":
            print(f"| {k} | {v['seconds']:.1f} | {v['peak_rss_mb']:.0f} |")
    print(f"\nB2 recovered {record['alignment_B2']['recovered']}\n"
          f"B2 truth     {record['alignment_B2']['truth']}")


if __name__ == "__main__":
    main()
