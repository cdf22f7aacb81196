"""Benchmark: the paper's degradation, reference vs fast path, on a 5000 × 5000 RGB tile.

Each measurement runs in its own child process so that the peak resident memory
(``ru_maxrss``) belongs to that method alone; ``tracemalloc`` gives the peak of
the Python/numpy allocations within it. The tile is real drone imagery (the
Brazil pasture orthomosaic from ../shared/realdata, mirrored out to 5000 × 5000)
or, without it, multi-scale synthetic texture.

Usage::

    python benchmarks/bench_degrade.py            # writes benchmarks/results/bench_degrade.json
    python benchmarks/bench_degrade.py --size 2000  # quicker
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))
RESULT = ROOT / "benchmarks" / "results" / "bench_degrade.json"
PHI = 10


def make_tile(size: int) -> tuple[np.ndarray, str]:
    """(3, size, size) uint8 tile and a description of where it came from."""
    src = REALDATA / "brazil_pasture_10cm_epsg3395.tif"
    if src.is_file():
        import rasterio

        with rasterio.open(src) as ds:
            img = ds.read([1, 2, 3])
        reps = -(-size // img.shape[1])
        pad = (reps * img.shape[1] - img.shape[1])
        big = np.pad(img, ((0, 0), (0, pad), (0, pad)), mode="symmetric")
        return np.ascontiguousarray(big[:, :size, :size]), f"{src.name}, mirrored to {size}²"
    import cv2

    rng = np.random.default_rng(0)
    acc = np.zeros((size, size), np.float32)
    for sigma, weight in ((1.0, 0.3), (4.0, 0.5), (16.0, 1.0)):
        acc += weight * sigma * cv2.GaussianBlur(
            rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigma)
    grey = np.clip(120 + 40 * (acc - acc.mean()) / acc.std(), 1, 254)
    return np.stack([grey * 0.9, grey, grey * 0.7]).astype(np.uint8), "synthetic texture"


def _status_mb(key: str) -> float | None:
    """VmRSS / VmHWM of this process from /proc (MB), None where unavailable."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (Linux ≥ 4.0: write 5 to clear_refs)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def child(task: str, q: float, tile_npy: str, out_npy: str) -> dict:
    """Run one measurement in this (fresh) process."""
    sys.path.insert(0, str(ROOT))
    from geosim.degrade.calibrate import DegradedLV
    from geosim.degrade.core import degrade_array

    tile = np.load(tile_npy)
    size = tile.shape[1]
    reset = _reset_peak_rss()
    rss0 = _status_mb("VmRSS") if reset else resource.getrusage(
        resource.RUSAGE_SELF).ru_maxrss / 1024
    tracemalloc.start()
    t0 = time.perf_counter()
    extra: dict = {}
    if task in ("reference", "fast"):
        out, _ = degrade_array(tile, q=q, phi=PHI, method=task)
        np.save(out_npy, out)
    else:  # calibration: prepare the grey spectrum once, then LV at several Q
        model = DegradedLV.from_image(tile, None, phi=PHI, q_min=0.5)
        t1 = time.perf_counter()
        for qq in np.linspace(0.5, 8.0, 16):
            model(qq)
        extra = {"prepare_s": round(t1 - t0, 3),
                 "lv_eval_ms_mean": round((time.perf_counter() - t1) / 16 * 1e3, 1)}
    seconds = time.perf_counter() - t0
    _, peak_py = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    rss1 = _status_mb("VmHWM") if reset else resource.getrusage(
        resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"task": task, "q": q, "seconds": round(seconds, 3),
            "mp_per_s": round(size * size / 1e6 / seconds, 2),
            "peak_tracemalloc_mb": round(peak_py / 2**20, 1),
            "peak_rss_increase_mb": round(rss1 - rss0, 1), "peak_rss_mb": round(rss1, 1),
            "rss_peak_method": "VmHWM after clear_refs" if reset else "ru_maxrss", **extra}


def run(size: int, qs: list[float]) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tile, source = make_tile(size)
        tile_npy = str(Path(tmp) / "tile.npy")
        np.save(tile_npy, tile)
        del tile
        for q in qs:
            outs = {}
            for task in ("reference", "fast"):
                npy = str(Path(tmp) / f"{task}_{q}.npy")
                proc = subprocess.run([sys.executable, __file__, "--child", task, "--q", str(q),
                                       "--tile", tile_npy, "--npy", npy],
                                      capture_output=True, text=True, check=True)
                rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
                outs[task] = np.load(npy)
            ref, fast = outs["reference"], outs["fast"]
            dn = np.abs(np.clip(np.rint(ref), 0, 255).astype(int)
                        - np.clip(np.rint(fast), 0, 255).astype(int))
            for r in rows[-2:]:
                r["max_abs_diff_float_dn"] = float(np.abs(ref - fast).max())
                r["max_abs_diff_uint8_dn"] = int(dn.max())
                r["fraction_pixels_differing_uint8"] = float((dn > 0).mean())
            rows[-1]["speedup_vs_reference"] = round(rows[-2]["seconds"] / rows[-1]["seconds"], 1)
        proc = subprocess.run([sys.executable, __file__, "--child", "calibration", "--q", "0",
                               "--tile", tile_npy, "--npy", ""],
                              capture_output=True, text=True, check=True)
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    return {"benchmark": "bench_degrade", "tile": f"{size}x{size} RGB uint8 ({source})",
            "phi": PHI, "machine": {"python": platform.python_version(),
                                    "cpus": os.cpu_count(), "platform": platform.platform()},
            "results": rows}


def markdown(doc: dict) -> str:
    lines = [f"Tile: {doc['tile']}, φ = {doc['phi']}, {doc['machine']['cpus']} CPU(s)", "",
             "| task | Q | time (s) | MP/s | peak RSS +MB | peak tracemalloc MB | "
             "max diff float DN | max diff uint8 DN | speed-up |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["results"]:
        if r["task"] == "calibration":
            continue
        lines.append(f"| {r['task']} | {r['q']} | {r['seconds']} | {r['mp_per_s']} | "
                     f"{r['peak_rss_increase_mb']} | {r['peak_tracemalloc_mb']} | "
                     f"{r['max_abs_diff_float_dn']:.2e} | {r['max_abs_diff_uint8_dn']} | "
                     f"{r.get('speedup_vs_reference', '')} |")
    for r in doc["results"]:
        if r["task"] == "calibration":
            lines += ["", f"Calibration model (grey, q_min 0.5): prepare {r['prepare_s']} s, "
                          f"LV(Q) {r['lv_eval_ms_mean']} ms per Q (mean over 16 Q in 0.5–8), "
                          f"peak RSS +{r['peak_rss_increase_mb']} MB"]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=5000)
    ap.add_argument("--q", type=float, nargs="*", default=[1.0, 4.34])
    ap.add_argument("--child", choices=["reference", "fast", "calibration"])
    ap.add_argument("--npy", default="")
    ap.add_argument("--tile", default="")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.q[0], args.tile, args.npy)))
        return
    doc = run(args.size, args.q)
    if args.size == 5000:
        RESULT.parent.mkdir(parents=True, exist_ok=True)
        RESULT.write_text(json.dumps(doc, indent=2) + "\n")
    print(markdown(doc))


if __name__ == "__main__":
    main()
