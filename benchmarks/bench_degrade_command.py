"""Benchmark: the whole ``geosim degrade`` step against the straightforward reference.

Both run on the same 5000 × 5000 RGB uint8 tiles (the Brazil pasture orthomosaic of
../shared/realdata mirrored out, or synthetic texture), each in its own child process:

* ``command``: :func:`geosim.degrade.steps.run_degrade` on a run folder holding
  ``--tiles`` such tiles (tiled, deflate GeoTIFFs with an internal mask and the manifest
  entry of each, as ``geosim tile`` leaves them): reading, degrading (the fast method),
  writing the 0.5 m GeoTIFFs with their tags and manifest entries — everything the
  command does except starting Python;
* ``reference``: for one tile, read it with rasterio, then the paper's operation done
  the straightforward way (``method="reference"``: the full-resolution blur with the
  analytic circular-aperture OTF applied by FFT of the symmetric extension — a DCT-II
  — then ``cv2.resize`` bicubic), rounded to uint8.

The two alternate over ``--rounds`` rounds (same tiles, same load); each run is a fresh
process and every command run degrades every tile (its manifest is cleared). Reported:
per task the median over rounds (and min/median/max) of wall and CPU seconds per tile,
MP/s, the speed-up (reference / command) of the medians and the smallest per-round
speed-up, and the largest difference in DN between the command's output and the
reference (target: ≤ 1). ``--baseline DIR`` also times another checkout's command
(e.g. main's code, ``git archive main | tar -x -C DIR``) in the same rounds.

Usage: ``python benchmarks/bench_degrade_command.py [--size 5000] [--tiles 3] [--rounds 3]
[--baseline DIR] [--out FILE]``; writes benchmarks/results/bench_degrade_command.json
(at --size 5000) or ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULT = ROOT / "benchmarks" / "results" / "bench_degrade_command.json"
Q = 4.34


#: ``--tile-codec``: COG options of the benchmark's input tiles (``deflate``: as ``geosim
#: tile`` writes them; the others only measure what another codec of the tiles would change).
TILE_CODECS = {"deflate": {}, "zstd": {"COMPRESS": "ZSTD", "LEVEL": 9},
               "none": {"COMPRESS": "NONE", "PREDICTOR": "NO"}}


def setup(root: Path, size: int, n_tiles: int, codec: str = "deflate") -> Path:
    """Write the site (flights = the tiles themselves), the run folder's tiles/."""
    from affine import Affine

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_degrade import make_tile

    from geosim import manifest
    from geosim.io.raster import write_geotiff

    tile, _source = make_tile(size)
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    lines = ['[site]', 'name = "degrade benchmark"', 'crs = "EPSG:32756"',
             'reference_flight = "F0"', '', '[parameters]', f'tile_px = {size}', f'q = {Q}', '']
    for i in range(n_tiles):
        path = root / "run" / "tiles" / f"F{i}" / "r000_c000.tif"
        write_geotiff(path, np.roll(tile, 97 * i, axis=2), transform=t, crs="EPSG:32756",
                      mask=np.ones(tile.shape[1:], bool), cog_overrides=TILE_CODECS[codec])
        # the entry `geosim tile` records for each tile it writes (the degrade step's manifest
        # fingerprints such a tile by what made it instead of hashing its bytes)
        manifest.record_output(root / "run", path, [], {"benchmark_tile": i, "codec": codec})
        lines += ['[[flights]]', f'id = "F{i}"', f'image = "{path}"',
                  f'acquired = "2021-07-15T1{i}:00:00+10:00"', '']
    (root / "site.toml").write_text("\n".join(lines))
    return root / "site.toml"


def child(task: str, root: Path) -> dict:
    import rasterio

    from geosim.config import load_site
    from geosim.degrade.core import degrade_array, to_dtype
    from geosim.degrade.steps import run_degrade
    from geosim.io.raster import read_valid_mask

    site = load_site(root / "site.toml")
    c0 = time.process_time()
    if task == "command":
        t0 = time.perf_counter()
        run_degrade(site, root / "run")
        seconds = time.perf_counter() - t0
        n = len(site.flights)
    else:
        t0 = time.perf_counter()
        with rasterio.open(root / "run" / "tiles" / "F0" / "r000_c000.tif") as ds:
            img, valid = ds.read(), read_valid_mask(ds)
        out, _ = degrade_array(img, q=Q, phi=10, valid=valid, method="reference")
        np.save(root / "reference.npy", to_dtype(out, img.dtype))
        seconds = time.perf_counter() - t0
        n = 1
    cpu = time.process_time() - c0
    return {"task": task, "tiles": n, "seconds": round(seconds, 3),
            "seconds_per_tile": round(seconds / n, 3), "cpu_seconds_per_tile": round(cpu / n, 3),
            "peak_rss_mb": _peak_rss_mb()}


def _peak_rss_mb() -> float:
    """Peak resident memory of this process (VmHWM; ru_maxrss would include the parent's)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _run_child(script: Path, task: str, root: Path) -> dict:
    """Run one timed child (its own process) and return its record."""
    if task != "reference":  # every command run degrades every tile (no manifest skips)
        for sub in ("degraded", ".geosim/manifest/degraded"):
            shutil.rmtree(root / "run" / sub, ignore_errors=True)
    proc = subprocess.run([sys.executable, str(script), "--child", task, "--root", str(root)],
                          capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _read_degraded(root: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(root / "run" / "degraded" / "F0" / "r000_c000.tif") as ds:
        return ds.read().astype(int)


def _median_row(runs: list[dict], mp: float) -> dict:
    """The run with the median wall time, plus the min/median/max of wall and CPU."""
    by_wall = sorted(runs, key=lambda r: r["seconds_per_tile"])
    row = dict(by_wall[len(by_wall) // 2])
    for key in ("seconds_per_tile", "cpu_seconds_per_tile"):
        vals = sorted(r[key] for r in runs)
        row[f"{key}_min_median_max"] = [vals[0], float(np.median(vals)), vals[-1]]
        row[key] = float(np.median(vals))
    row["mp_per_s"] = round(mp / row["seconds_per_tile"], 2)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=5000)
    ap.add_argument("--tiles", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3,
                    help="alternated rounds of command (baseline) and reference runs")
    ap.add_argument("--baseline", type=Path,
                    help="another geosim checkout (e.g. main's code) whose command is timed "
                         "in the same rounds, on the same tiles")
    ap.add_argument("--tile-codec", choices=sorted(TILE_CODECS), default="deflate",
                    help="compression of the input tiles (default: as geosim tile writes them)")
    ap.add_argument("--out", type=Path, help=f"result JSON (default {RESULT} at --size 5000)")
    ap.add_argument("--child")
    ap.add_argument("--root", type=Path)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.root)))
        return
    here = Path(__file__).resolve()
    scripts = {"command": here, "reference": here}
    if args.baseline is not None:
        scripts["baseline"] = args.baseline.resolve() / "benchmarks" / here.name
    mp = args.size ** 2 / 1e6
    runs: dict[str, list[dict]] = {task: [] for task in scripts}
    rounds = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        setup(root, args.size, args.tiles, args.tile_codec)
        tile_mb = (root / "run" / "tiles" / "F0" / "r000_c000.tif").stat().st_size / 1e6
        load_start = [round(x, 2) for x in os.getloadavg()]
        outputs: dict[str, np.ndarray] = {}
        for i in range(args.rounds):
            this_round = {"load_average_at_start": [round(x, 2) for x in os.getloadavg()]}
            for task, script in scripts.items():
                row = _run_child(script, "command" if task == "baseline" else task, root)
                runs[task].append(row)
                this_round[task] = {k: row[k] for k in ("seconds_per_tile",
                                                        "cpu_seconds_per_tile")}
                if task != "reference":
                    outputs[task] = _read_degraded(root)
                print(i, task, row, flush=True)
            ref = this_round["reference"]
            for task in runs:
                if task != "reference":
                    this_round[f"speedup_{task}"] = round(
                        ref["seconds_per_tile"] / this_round[task]["seconds_per_tile"], 1)
                    this_round[f"speedup_cpu_{task}"] = round(
                        ref["cpu_seconds_per_tile"] / this_round[task]["cpu_seconds_per_tile"],
                        1)
            rounds.append(this_round)
        ref_out = np.load(root / "reference.npy").astype(int)
    fast = outputs["command"]
    rows = {task: _median_row(r, mp) for task, r in runs.items()}
    doc = {"benchmark": "bench_degrade_command", "tile_px": args.size, "q": Q,
           "tiles_in_command": args.tiles, "rounds": args.rounds,
           "tile_codec": args.tile_codec, "tile_file_mb": round(tile_mb, 1),
           "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                       "load_average_at_start": load_start,
                       "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
           "command": rows["command"], "reference": rows["reference"],
           "speedup": round(rows["reference"]["seconds_per_tile"]
                            / rows["command"]["seconds_per_tile"], 1),
           "speedup_cpu_time": round(rows["reference"]["cpu_seconds_per_tile"]
                                     / rows["command"]["cpu_seconds_per_tile"], 1),
           "speedup_per_round_min": min(r["speedup_command"] for r in rounds),
           "speedup_cpu_per_round_min": min(r["speedup_cpu_command"] for r in rounds),
           "max_abs_diff_dn": int(np.abs(fast - ref_out).max()),
           "fraction_pixels_differing": float((fast != ref_out).mean()),
           "per_round": rounds}
    if "baseline" in rows:
        base = outputs["baseline"]
        doc["baseline"] = {**rows["baseline"], "code": str(args.baseline),
                           "speedup": round(rows["reference"]["seconds_per_tile"]
                                            / rows["baseline"]["seconds_per_tile"], 1),
                           "speedup_cpu_time": round(rows["reference"]["cpu_seconds_per_tile"]
                                                     / rows["baseline"]["cpu_seconds_per_tile"],
                                                     1),
                           "max_abs_diff_dn": int(np.abs(base - ref_out).max()),
                           "max_abs_diff_dn_vs_command": int(np.abs(base - fast).max())}
    out = args.out if args.out is not None else (RESULT if args.size == 5000 else None)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
