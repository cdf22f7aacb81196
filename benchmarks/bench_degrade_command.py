"""Benchmark: the whole ``geosim degrade`` command against the straightforward reference.

Both run on the same 5000 × 5000 RGB uint8 tiles (the Brazil pasture orthomosaic of
../shared/realdata mirrored out, or synthetic texture), each in its own child process:

* ``command``: ``geosim degrade SITE --out RUN --workers 1`` run in the child's own
  process (``geosim.cli.main.cli``, exactly what ``python -m geosim`` calls) on a run
  folder holding ``--tiles`` such tiles (tiled, DEFLATE COGs with an internal mask and
  the manifest entry of each, as ``geosim tile`` leaves them; the site's flights are
  separate files, hard links of the tiles): site loading and preflight, run.json with
  the input checksums (known from the previous run, as after ``geosim tile``), reading,
  degrading (the fast method), writing the 0.5 m COGs with their tags and manifest
  entries — everything the command does except starting Python and importing, which is
  reported on its own (``startup_cpu_seconds``: interpreter start and the imports of the
  command's modules, CPU);
* ``reference``: for one tile, read it with rasterio, then the paper's operation done
  the straightforward way (``method="reference"``: the full-resolution blur with the
  analytic circular-aperture OTF applied by FFT of the symmetric extension — a DCT-II
  — then ``cv2.resize`` bicubic), rounded to uint8 (its start-up is reported alike).

``--threads N`` (default 1) is the thread budget of both: the command runs with
``GEOSIM_THREADS=N`` (GDAL block decoding, FFTs, OpenCV) and the reference with
``cv2.setNumThreads(N)`` (its FFTs use one thread, SciPy's default); BLAS and OpenMP get
one thread in both. With 1 the two are compared CPU for CPU; ``--threads 0`` leaves the
command its default (one thread since 23 Nov; every core before, for ``--baseline`` code of
then) and the reference OpenCV's.

The two alternate over ``--rounds`` rounds (same tiles, same load); each run is a fresh
process and every command run degrades every tile (its manifest is cleared). Reported:
per task the median over rounds (and min/median/max) of wall and CPU seconds per tile,
MP/s, the speed-up (reference / command) of the medians in wall and in CPU time and the
smallest per-round speed-ups, the load average at the start of each round, and the
largest difference in DN between the command's output and the reference (target: ≤ 1).
``--baseline DIR`` also times another checkout's code (e.g. main's, ``git archive main |
tar -x -C DIR``) through this same script, in the same rounds, and reports whether its
outputs are bit-identical to the command's.

Usage: ``python benchmarks/bench_degrade_command.py [--size 5000] [--tiles 3] [--rounds 3]
[--threads 1] [--baseline DIR] [--out FILE]``; writes
benchmarks/results/bench_degrade_command.json (at --size 5000) or ``--out``.
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
#: The geosim code a child imports: this checkout, or ``--baseline DIR`` (set by the parent).
CODE = Path(os.environ.get("BENCH_GEOSIM_CODE", str(ROOT)))
sys.path.insert(0, str(CODE))
RESULT = ROOT / "benchmarks" / "results" / "bench_degrade_command.json"
Q = 4.34


#: ``--tile-codec``: COG options of the benchmark's input tiles (``deflate``: as ``geosim
#: tile`` writes them; the others only measure what another codec of the tiles would change).
TILE_CODECS = {"deflate": {}, "zstd": {"COMPRESS": "ZSTD", "LEVEL": 9},
               "none": {"COMPRESS": "NONE", "PREDICTOR": "NO"}}


def setup(root: Path, size: int, n_tiles: int, codec: str = "deflate") -> Path:
    """Write the site (its flights: hard links of the tiles, outside the run folder) and
    the run folder's tiles/ with their manifest entries; return the site file."""
    from affine import Affine

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_degrade import make_tile

    from geosim import manifest
    from geosim.prepare.tiles import write_tile_array

    tile, _source = make_tile(size)
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    lines = ['[site]', 'name = "degrade benchmark"', 'crs = "EPSG:32756"',
             'reference_flight = "F0"', '', '[parameters]', f'tile_px = {size}', f'q = {Q}', '']
    (root / "flights").mkdir(parents=True, exist_ok=True)
    for i in range(n_tiles):
        path = root / "run" / "tiles" / f"F{i}" / "r000_c000.tif"
        # written as `geosim tile` writes a tile (with its binomial first overview)
        write_tile_array(path, np.roll(tile, 97 * i, axis=2), np.ones(tile.shape[1:], bool),
                         transform=t, crs="EPSG:32756", cog_overrides=TILE_CODECS[codec])
        # the entry `geosim tile` records for each tile it writes (the degrade step's manifest
        # fingerprints such a tile by what made it instead of hashing its bytes)
        manifest.record_output(root / "run", path, [], {"benchmark_tile": i, "codec": codec})
        flight = root / "flights" / f"F{i}.tif"
        try:
            os.link(path, flight)
        except OSError:
            shutil.copy2(path, flight)
        lines += ['[[flights]]', f'id = "F{i}"', f'image = "{flight}"',
                  f'acquired = "2021-07-15T1{i}:00:00+10:00"', '']
    (root / "site.toml").write_text("\n".join(lines))
    return root / "site.toml"


def _cpu_seconds() -> float:
    """CPU (user + system) of this process since it started, all threads."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def child(task: str, root: Path, threads: int) -> dict:
    """One timed run of ``task`` in this (fresh) process; its record."""
    if task == "command":
        import geosim.cli.degrade  # noqa: F401  (the modules `geosim degrade` imports)
        import geosim.degrade.steps  # noqa: F401
        from geosim.cli.main import cli
    else:
        import cv2
        import rasterio

        from geosim.degrade.core import degrade_array, to_dtype
        from geosim.io.raster import read_valid_mask

        if threads > 0:
            cv2.setNumThreads(threads)
    startup_cpu = _cpu_seconds()
    n = len(list((root / "run" / "tiles").glob("*/*.tif"))) if task == "command" else 1
    c0 = time.process_time()
    t0 = time.perf_counter()
    if task == "command":
        cli.main(["degrade", str(root / "site.toml"), "--out", str(root / "run"),
                  "--workers", "1"], prog_name="geosim", standalone_mode=False)
    else:
        # GDAL's block cache as the command sets it (geosim.pipeline.GDAL_CACHE_MB): the
        # file is read alike (GDAL's default cache decodes the tile with ~0.05 s more CPU)
        with rasterio.Env(GDAL_CACHEMAX=256), \
                rasterio.open(root / "run" / "tiles" / "F0" / "r000_c000.tif") as ds:
            img, valid = ds.read(), read_valid_mask(ds)
        out, _ = degrade_array(img, q=Q, phi=10, valid=valid, method="reference")
        np.save(root / "reference.npy", to_dtype(out, img.dtype))
    seconds = time.perf_counter() - t0
    cpu = time.process_time() - c0
    return {"task": task, "tiles": n, "seconds": round(seconds, 3),
            "seconds_per_tile": round(seconds / n, 3), "cpu_seconds_per_tile": round(cpu / n, 3),
            "startup_cpu_seconds": round(startup_cpu, 3), "peak_rss_mb": _peak_rss_mb(),
            "geosim_code": str(Path(sys.modules["geosim"].__file__).parents[1])}


def _peak_rss_mb() -> float:
    """Peak resident memory of this process (VmHWM; ru_maxrss would include the parent's)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _child_env(threads: int, code: Path) -> dict[str, str]:
    """Environment of a child: its thread budget and the geosim code it imports."""
    env = {**os.environ, "BENCH_GEOSIM_CODE": str(code), "OMP_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    env.pop("GEOSIM_THREADS", None)
    if threads > 0:
        env["GEOSIM_THREADS"] = str(threads)
    return env


def _run_child(task: str, root: Path, threads: int, code: Path) -> dict:
    """Run one timed child (its own process) and return its record."""
    if task == "command":  # every command run degrades every tile (no manifest skips)
        for sub in ("degraded", ".geosim/manifest/degraded"):
            shutil.rmtree(root / "run" / sub, ignore_errors=True)
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", task,
                           "--root", str(root), "--threads", str(threads)],
                          capture_output=True, text=True, check=False,
                          env=_child_env(threads, code))
    if proc.returncode != 0:
        raise RuntimeError(f"{task} child failed ({proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _read_degraded(root: Path) -> np.ndarray:
    """Every degraded tile's pixels, (tiles, bands, rows, cols), flight F0 first."""
    import rasterio

    tiles = []
    for path in sorted((root / "run" / "degraded").glob("F*/r000_c000.tif")):
        with rasterio.open(path) as ds:
            tiles.append(ds.read().astype(int))
    return np.stack(tiles)


def _median_row(runs: list[dict], mp: float) -> dict:
    """The run with the median wall time, plus the min/median/max of wall and CPU."""
    by_wall = sorted(runs, key=lambda r: r["seconds_per_tile"])
    row = dict(by_wall[len(by_wall) // 2])
    row["startup_cpu_seconds"] = float(np.median([r["startup_cpu_seconds"] for r in runs]))
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
    ap.add_argument("--threads", type=int, default=1,
                    help="thread budget of both (0: the command's and OpenCV's defaults)")
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
        print(json.dumps(child(args.child, args.root, args.threads)))
        return
    codes = {"command": ROOT, "reference": ROOT}
    if args.baseline is not None:
        codes["baseline"] = args.baseline.resolve()
    mp = args.size ** 2 / 1e6
    runs: dict[str, list[dict]] = {task: [] for task in codes}
    rounds = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        setup(root, args.size, args.tiles, args.tile_codec)
        tile_mb = (root / "run" / "tiles" / "F0" / "r000_c000.tif").stat().st_size / 1e6
        # a first command run records the flights' checksums in run.json, as the earlier
        # steps of a real run have (every timed run then finds them current)
        _run_child("command", root, args.threads, ROOT)
        load_start = [round(x, 2) for x in os.getloadavg()]
        outputs: dict[str, np.ndarray] = {}
        for i in range(args.rounds):
            this_round = {"load_average_at_start": [round(x, 2) for x in os.getloadavg()]}
            for task, code in codes.items():
                row = _run_child("command" if task == "baseline" else task, root,
                                 args.threads, code)
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
    fast = outputs["command"][0]
    rows = {task: _median_row(r, mp) for task, r in runs.items()}
    doc = {"benchmark": "bench_degrade_command", "tile_px": args.size, "q": Q,
           "tiles_in_command": args.tiles, "rounds": args.rounds,
           "threads": args.threads or "default",
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
           # whole processes: start-up (interpreter and imports) shared by the command's tiles
           "cpu_seconds_per_tile_with_startup": {
               task: round((rows[task]["startup_cpu_seconds"]
                            + rows[task]["cpu_seconds_per_tile"] * rows[task]["tiles"])
                           / rows[task]["tiles"], 3) for task in ("command", "reference")},
           "per_round": rounds}
    with_startup = doc["cpu_seconds_per_tile_with_startup"]
    doc["speedup_cpu_time_with_startup"] = round(with_startup["reference"]
                                                 / with_startup["command"], 1)
    if "baseline" in rows:
        base = outputs["baseline"]
        doc["baseline"] = {**rows["baseline"], "code": str(args.baseline),
                           "speedup": round(rows["reference"]["seconds_per_tile"]
                                            / rows["baseline"]["seconds_per_tile"], 1),
                           "speedup_cpu_time": round(rows["reference"]["cpu_seconds_per_tile"]
                                                     / rows["baseline"]["cpu_seconds_per_tile"],
                                                     1),
                           "max_abs_diff_dn": int(np.abs(base[0] - ref_out).max()),
                           "max_abs_diff_dn_vs_command": int(np.abs(base
                                                                    - outputs["command"]).max())}
    out = args.out if args.out is not None else (RESULT if args.size == 5000 else None)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(doc, indent=2) + "\n")
    print(json.dumps(doc, indent=2))


if __name__ == "__main__":
    main()
