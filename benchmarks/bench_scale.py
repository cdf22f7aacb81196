"""Benchmark at orthomosaic scale: a 3-flight site of SIZE × SIZE px per flight.

The flights are made from real imagery (the Brazil pasture orthomosaic of
../shared/realdata, 10 cm, mirrored out without end and upsampled to 0.05 m) or,
without it, from synthetic multi-scale texture. They cover the same ground with
known georeferencing errors (flight B shifted by 0.37 m east / 0.21 m south, flight C
rotated 0.05° and shifted) and fractional grid origins, so the grid reprojection
and the alignment both really resample. Every flight is a tiled, deflate-compressed
RGB GeoTIFF with an internal mask, in WGS 84 / UTM 56S.

Each pipeline step (grid, footprints, align, tiles, degrade at a fixed Q = 4.34)
runs in its own child process, once per worker count of ``--workers`` (default 1 and 2:
in-process, then a local Dask cluster of 2 single-threaded worker processes, started
before the clock), each into its own run folder; per step it reports wall time,
throughput (MP/s: megapixels of the flights — or of the tiles for ``degrade`` — per
second), CPU seconds (driver and workers apart), the step function's own time without the
runner's per-command work (``step_s``), on a cluster the workers' busy fraction (sum of the
task durations from Dask's task stream ÷ (workers × wall time)), the 1-minute load average
before and after, the peak resident memory (VmHWM) of the driver and of every worker
process, and the bytes written; then the speed-up per step and whether the tiles and
degraded tiles of the runs are identical. ``GEOSIM_BENCH_PROFILE=DIR`` writes a cProfile
of the driver per step and worker count. ``--site-cache DIR`` keeps the generated flights
for later runs of the same ``--size``. In the same
run, GDAL's own ``gdalwarp`` (Debian gdal-bin; skipped with a note when absent) does
the same reprojection of the same flights onto the site grid (bicubic, 256 MB warp
memory, all CPUs), and the resample-once prepare path (grid + align + tiles) is
compared to it. Finally the per-tile cost is extrapolated to the paper's dataset
(1869 tiles of 5000 px).

Usage::

    python benchmarks/bench_scale.py --size 20000          # the full size (long)
    python benchmarks/bench_scale.py --size 6000 --tile-px 2000   # a smaller run
    python benchmarks/bench_scale.py --workers 1                  # one process only
    python benchmarks/bench_scale.py --workers 1t2,1,2            # also in-process on 2 threads
    python benchmarks/bench_scale.py --steps grid,footprints,align  # only the first steps
    python benchmarks/bench_scale.py --workers 1,2 --repeat 3     # 1, 2, 1, 2, 1, 2: median

``1`` runs in this process on one core, like one single-threaded worker without Dask: the
baseline of pure multi-process scaling. ``1tK`` runs in this process with K threads per task
(``GEOSIM_THREADS=K``; ``1t`` = ``1t1``, the same as ``1`` since 23 Nov): ``1t2`` is what
``--workers 1`` did before, every core of this machine for FFTs, OpenCV and GDAL.

Before the steps (unless ``--no-ceiling``), ``machine_ceiling.py`` measures what this
machine gives two single-threaded processes over one on plain reference workloads
(compute-bound in cache, a 5000² bicubic warpAffine, 2048² FFT filtering, a memory
stream; ≈ 40 s): the results record it with ``lscpu`` under ``machine_ceiling``, and each
step's speed-up is printed next to the ceiling of the workload it is shaped like
(``speedup_vs_ceiling``).

Writes benchmarks/results/bench_scale.json (or --out) and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import math
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
REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))
RESULT = ROOT / "benchmarks" / "results" / "bench_scale.json"
CRS = "EPSG:32756"
GSD_M = 0.05
X0, Y0 = 300000.0, 6200000.0
Q_FIXED = 4.34
PAPER_TILES = 1869
STEPS = ("grid", "footprints", "align", "tiles", "degrade")
BLOCK = 2048


# --------------------------------------------------------------------------- the site


def _texture_period() -> tuple[np.ndarray, float, str]:
    """(3, H, W) uint8 texture repeated by mirroring, its pixel size (m) and its origin."""
    src = REALDATA / "brazil_pasture_10cm_epsg3395.tif"
    if src.is_file():
        import rasterio

        with rasterio.open(src) as ds:
            img = ds.read([1, 2, 3])
        # one mirrored period (2H × 2W): sampling it modulo its size is seamless
        per = np.concatenate([img, img[:, ::-1]], axis=1)
        per = np.concatenate([per, per[:, :, ::-1]], axis=2)
        return np.ascontiguousarray(per), 0.10, f"{src.name} (10 cm), mirrored out"
    import cv2

    rng = np.random.default_rng(0)
    n = 4096
    acc = np.zeros((n, n), np.float32)
    for sigma, weight in ((1.0, 0.3), (4.0, 0.5), (16.0, 1.0)):
        acc += weight * sigma * cv2.GaussianBlur(
            rng.standard_normal((n, n)).astype(np.float32), (0, 0), sigma)
    grey = np.clip(120 + 40 * (acc - acc.mean()) / acc.std(), 1, 254)
    return np.stack([grey * 0.9, grey, grey * 0.7]).astype(np.uint8), 0.05, "synthetic texture"


def _similarity(rotation_deg: float, shift_m: tuple[float, float], centre: tuple[float, float]):
    from affine import Affine

    th = math.radians(rotation_deg)
    lin = Affine(math.cos(th), -math.sin(th), 0, math.sin(th), math.cos(th), 0)
    return (Affine.translation(centre[0] + shift_m[0], centre[1] + shift_m[1]) @ lin
            @ Affine.translation(-centre[0], -centre[1]))


def make_flight(path: Path, size: int, offset_px: tuple[float, float], error) -> None:
    """Write one flight: ground = texture at C(stated position), window by window."""
    import cv2
    from affine import Affine
    from rasterio.windows import Window

    from geosim.io.raster import create_geotiff

    per, per_gsd, _ = _texture_period()
    ph, pw = per.shape[1:]
    hwc = [np.ascontiguousarray(per[i]) for i in range(3)]
    t = Affine(GSD_M, 0, X0 + offset_px[0] * GSD_M, 0, -GSD_M, Y0 - offset_px[1] * GSD_M)
    with create_geotiff(path, width=size, height=size, count=3, dtype="uint8", crs=CRS,
                        transform=t, band_descriptions=["red", "green", "blue"],
                        internal_mask=True) as dst:
        for r0 in range(0, size, BLOCK):
            for c0 in range(0, size, BLOCK):
                h, w = min(BLOCK, size - r0), min(BLOCK, size - c0)
                cc, rr = np.meshgrid(np.arange(c0, c0 + w) + 0.5, np.arange(r0, r0 + h) + 0.5)
                x, y = t * (cc, rr)
                gx, gy = error * (x, y)
                # texture pixel coordinates, wrapped into one mirrored period
                mx = np.mod((gx - X0) / per_gsd - 0.5, pw).astype(np.float32)
                my = np.mod((Y0 - gy) / per_gsd - 0.5, ph).astype(np.float32)
                out = np.stack([cv2.remap(b, mx, my, cv2.INTER_LINEAR,
                                          borderMode=cv2.BORDER_WRAP) for b in hwc])
                win = Window(c0, r0, w, h)
                dst.write(out, window=win)
                dst.write_mask(np.full((h, w), 255, np.uint8), window=win)


#: Bump when the flights :func:`make_flights` writes change (invalidates --site-cache).
SITE_VERSION = 1


def make_flights(flight_dir: Path, size: int) -> dict[str, Path]:
    """Write the three flights into ``flight_dir``; return their paths by id."""
    centre = (X0 + size * GSD_M / 2, Y0 - size * GSD_M / 2)
    flights = {
        "A": ((0.0, 0.0), _similarity(0.0, (0.0, 0.0), centre)),
        "B": ((0.3, 0.6), _similarity(0.0, (0.37, -0.21), centre)),
        "C": ((0.45, 0.15), _similarity(0.05, (-0.18, 0.29), centre)),
    }
    flight_dir.mkdir(parents=True, exist_ok=True)
    for fid, (off, err) in flights.items():
        make_flight(flight_dir / f"{fid}.tif", size, off, err)
    return {fid: flight_dir / f"{fid}.tif" for fid in flights}


def cached_flights(cache: Path, size: int) -> tuple[dict[str, Path], bool]:
    """The flights of a ``size`` site from ``cache`` (made there when absent or stale);
    returns them and whether they were reused.

    A stamp (``site.json``: generator version, size, imagery, file sizes) written after
    the flights says the folder is complete; a folder without it is made again.
    """
    folder = cache / f"site_{size}"
    stamp = folder / "site.json"
    want = {"site_version": SITE_VERSION, "size": size, "imagery": _texture_period()[2]}
    if stamp.is_file():
        doc = json.loads(stamp.read_text())
        paths = {fid: folder / "flights" / f"{fid}.tif" for fid in doc.get("files", {})}
        if ({k: doc.get(k) for k in want} == want and paths
                and all(p.is_file() and p.stat().st_size == doc["files"][fid]
                        for fid, p in paths.items())):
            return paths, True
        stamp.unlink()
    paths = make_flights(folder / "flights", size)
    stamp.write_text(json.dumps({**want, "files": {k: p.stat().st_size
                                                   for k, p in paths.items()}}, indent=2))
    return paths, False


def make_site(root: Path, size: int, tile_px: int, cache: Path | None = None
              ) -> tuple[Path, str, bool]:
    """Write site.toml (and the three flights, or reuse them from ``cache``) under ``root``;
    return the site file, the imagery's description and whether the flights were reused."""
    if cache is None:
        flights, reused = make_flights(root / "flights", size), False
    else:
        flights, reused = cached_flights(cache, size)
    root.mkdir(parents=True, exist_ok=True)
    lines = ['[site]', 'name = "scale benchmark"', f'crs = "{CRS}"', 'reference_flight = "A"',
             '', '[parameters]', f'tile_px = {tile_px}', 'align_window_px = 2000',
             f'q = {Q_FIXED}', 'keep_partial_tiles = true', '']
    for i, (fid, path) in enumerate(flights.items()):
        lines += ['[[flights]]', f'id = "{fid}"', f'image = "{path.resolve().as_posix()}"',
                  f'acquired = "2021-07-15T{10 + i:02d}:00:00+10:00"', '']
    (root / "site.toml").write_text("\n".join(lines))
    return root / "site.toml", _texture_period()[2], reused


# --------------------------------------------------------------------------- measuring


def _dir_bytes(path: Path) -> dict[str, int]:
    return {str(p.relative_to(path)): p.stat().st_size for p in path.rglob("*") if p.is_file()}


def child_step(step: str, site_file: str, out: str, workers: int | None) -> dict:
    """Run one pipeline step in this process; report its time, peak RSS and, on a local
    cluster, each worker process's peak RSS (the cluster is started before the clock)."""
    sys.path.insert(0, str(ROOT))
    from geosim.config import load_site
    from geosim.pipeline import run_pipeline

    site = load_site(site_file)
    rec: dict = {}
    _warm_worker()  # the step's modules imported before the clock here too, as on the workers
    with _engine(workers) as eng:
        client = getattr(eng, "client", None) if workers and workers > 1 else None
        if client is not None:
            # cluster up (when `client` was first asked for) and geosim imported on every
            # worker before the clock, as in one `geosim run` where it serves every step
            t_start = time.perf_counter()
            client.run(_warm_worker)
            rec["worker_warm_up_s"] = round(time.perf_counter() - t_start, 2)
        load0 = os.getloadavg()[0]
        driver0, workers0 = _own_cpu_seconds(), _workers_cpu_seconds(client)
        profile = os.environ.get("GEOSIM_BENCH_PROFILE")
        threads = os.environ.get("GEOSIM_THREADS")
        name = f"{step}_w{workers}" + (f"t{threads}" if threads else "")
        with _task_stream(client) as stream, _profiled(profile, name):
            t0, epoch0 = time.perf_counter(), time.time()
            doc = run_pipeline(site, out, only=[step], echo=lambda s: None)
            seconds = time.perf_counter() - t0
        rec["driver_cpu_s"] = round(_own_cpu_seconds() - driver0, 2)
        rec["workers_cpu_s"] = round(_workers_cpu_seconds(client) - workers0, 2)
        rec["cpu_s"] = round(rec["driver_cpu_s"] + rec["workers_cpu_s"], 2)
        # the step function alone (without the runner's preflight, input checksums, run.json)
        rec["step_s"] = doc["steps"][step]["seconds"]
        if client is not None:
            rec["worker_peak_rss_mb"] = sorted(client.run(_peak_rss_mb).values())
            rec.update(_task_summary(stream.data if stream is not None else [], seconds,
                                     len(rec["worker_peak_rss_mb"])))
            rec["timeline"] = _timeline(stream.data if stream is not None else [], epoch0,
                                        seconds, len(rec["worker_peak_rss_mb"]))
    rec.update({"seconds": round(seconds, 2), "peak_rss_mb": _peak_rss_mb(),
                "load_average_1min": [round(load0, 2), round(os.getloadavg()[0], 2)]})
    return rec


def _warm_worker() -> None:
    """Import what the steps' tasks import (on a worker)."""
    import geosim.degrade.steps  # noqa: F401
    import geosim.prepare.aligned  # noqa: F401
    import geosim.prepare.steps  # noqa: F401


def _workers_cpu_seconds(client) -> float:
    """CPU seconds (user + system) used so far by the cluster's workers (0 without one)."""
    return sum(client.run(_own_cpu_seconds).values()) if client is not None else 0.0


def _task_stream(client):
    """Dask's record of every task (worker, start, stop) in the block; None in-process."""
    import contextlib

    if client is None:
        return contextlib.nullcontext()
    from distributed import get_task_stream

    return get_task_stream(client)


def _profiled(folder: str | None, name: str):
    """cProfile of this process (the driver) into ``folder/name.prof`` when asked."""
    import contextlib

    if not folder:
        return contextlib.nullcontext()

    @contextlib.contextmanager
    def prof():
        import cProfile

        pr = cProfile.Profile()
        pr.enable()
        try:
            yield
        finally:
            pr.disable()
            Path(folder).mkdir(parents=True, exist_ok=True)
            pr.dump_stats(str(Path(folder) / f"{name}.prof"))

    return prof()


def _task_summary(tasks: list[dict], seconds: float, n_workers: int) -> dict:
    """Tasks run, the workers' busy time (sum of task durations) and their busy fraction
    of the step's wall time: 1.0 = every worker computed all along; the rest is the
    driver's serial work, scheduling and idle workers."""
    busy = sum(max(0.0, s["stop"] - s["start"]) for t in tasks
               for s in t.get("startstops", ()) if s.get("action") == "compute")
    return {"tasks": len(tasks), "worker_busy_s": round(busy, 2),
            "worker_busy_fraction": round(busy / (n_workers * seconds), 3)
            if seconds > 0 and n_workers else None}


def _timeline(tasks: list[dict], epoch0: float, seconds: float, n_workers: int) -> dict:
    """Where a cluster step's wall time went, from Dask's task stream.

    ``busy_workers_s``: seconds of the step during which 0, 1, … ``n_workers`` workers were
    computing (the rest of "all busy" is the tail, the driver's serial work and the
    scheduling gaps); ``first_task_s`` / ``last_task_end_s``: when the first task started
    and the last one ended, from the step's start; ``by_task``: per task function, the
    tasks, their summed and longest compute seconds and the span from the first start to
    the last stop (s from the step's start).
    """
    spans = [(s["start"] - epoch0, s["stop"] - epoch0, str(t.get("key", "")))
             for t in tasks for s in t.get("startstops", ()) if s.get("action") == "compute"]
    if not spans:
        return {}
    edges = sorted({0.0, seconds, *(min(max(a, 0.0), seconds) for a, _, _ in spans),
                    *(min(max(b, 0.0), seconds) for _, b, _ in spans)})
    busy = {k: 0.0 for k in range(n_workers + 1)}
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        mid = (lo + hi) / 2
        k = min(n_workers, sum(a <= mid < b for a, b, _ in spans))
        busy[k] += hi - lo
    by_task: dict[str, dict] = {}
    for a, b, key in spans:
        name = key.split("-")[0] if key else "?"
        rec = by_task.setdefault(name, {"tasks": 0, "compute_s": 0.0, "longest_s": 0.0,
                                        "first_start_s": a, "last_stop_s": b})
        rec["tasks"] += 1
        rec["compute_s"] += b - a
        rec["longest_s"] = max(rec["longest_s"], b - a)
        rec["first_start_s"] = min(rec["first_start_s"], a)
        rec["last_stop_s"] = max(rec["last_stop_s"], b)
    return {"busy_workers_s": {str(k): round(v, 2) for k, v in busy.items()},
            "first_task_s": round(min(a for a, _, _ in spans), 2),
            "last_task_end_s": round(max(b for _, b, _ in spans), 2),
            "by_task": {k: {kk: round(vv, 2) if isinstance(vv, float) else vv
                            for kk, vv in v.items()}
                        for k, v in sorted(by_task.items(), key=lambda kv: kv[1]["first_start_s"])}}


def _own_cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def _peak_rss_mb() -> float:
    """This process's peak resident memory: VmHWM (ru_maxrss on Linux also counts the
    parent's memory at fork time, which would charge the site generator to every step)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _engine(workers: int | None):
    """The engine of ``--workers``: in-process for 1, else a local cluster of ``workers``
    single-threaded processes, active (and closed) in the block."""
    from geosim import engine

    return engine.open_engine(workers or 1)


def run_gdalwarp(flights: list[Path], out_dir: Path, grid: dict) -> dict:
    """Time gdalwarp reprojecting every flight onto the site UAV grid (bicubic)."""
    exe = shutil.which("gdalwarp")
    if exe is None:
        return {"skipped": "gdalwarp not found (install Debian's gdal-bin)"}
    t = grid["uav"]["transform"]
    rows, cols = grid["uav"]["shape"]
    xmin, ymax = t[2], t[5]
    xmax, ymin = xmin + cols * t[0], ymax + rows * t[4]
    out_dir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for f in flights:
        subprocess.run([exe, "-q", "-overwrite", "-r", "cubic", "-t_srs", CRS, "-tr", str(t[0]),
                        str(-t[4]), "-te", str(xmin), str(ymin), str(xmax), str(ymax),
                        "-wm", "256", "-multi", "-wo", "NUM_THREADS=ALL_CPUS",
                        "-co", "TILED=YES", "-co", "COMPRESS=DEFLATE", "-co", "PREDICTOR=2",
                        "-co", "BIGTIFF=IF_SAFER", str(f), str(out_dir / f.name)], check=True)
    seconds = time.perf_counter() - t0
    written = sum(p.stat().st_size for p in out_dir.glob("*.tif"))
    return {"seconds": round(seconds, 2), "bytes_written": written,
            "command": "gdalwarp -r cubic -tr 0.05 0.05 -te <site grid> -wm 256 -multi "
                       "-wo NUM_THREADS=ALL_CPUS -co TILED=YES -co COMPRESS=DEFLATE"}


def run_steps(site_file: Path, out: Path, workers: str, size: int, tile_px: int,
              steps: tuple[str, ...] = STEPS) -> list[dict]:
    """Every step of ``steps``, each in its own child process, on ``workers`` (a count, or
    ``1tK``: in this process on K threads per task); one record per step."""
    flight_mp = 3 * size * size / 1e6
    rows = []
    count, _, threads = workers.partition("t")
    env = {k: v for k, v in os.environ.items() if k != "GEOSIM_THREADS"}
    if workers != count:
        env["GEOSIM_THREADS"] = threads or "1"
    for step in steps:
        before = _dir_bytes(out) if out.is_dir() else {}
        cmd = [sys.executable, __file__, "--child", step, "--site", str(site_file),
               "--run", str(out), "--workers", count]
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        if proc.returncode != 0:
            raise RuntimeError(f"step {step} failed:\n{proc.stderr[-3000:]}")
        rec = json.loads(proc.stdout.strip().splitlines()[-1])
        after = _dir_bytes(out)
        rec["bytes_written"] = sum(v for k, v in after.items() if before.get(k) != v)
        if step == "degrade":
            tiles = list((out / "tiles").glob("*/*.tif"))
            mp = len(tiles) * tile_px * tile_px / 1e6
            rec["tiles"] = len(tiles)
        else:
            mp = flight_mp
        rec["mp_per_s"] = round(mp / rec["seconds"], 2)
        rows.append({"step": step, "workers": workers, **rec})
        print(f"{workers} worker(s) {step}: {rec}", flush=True)
    return rows


def _same_outputs(a: Path, b: Path) -> bool:
    """Tiles and degraded tiles of two runs: same pixels and masks (decoded)."""
    import rasterio

    files = sorted(p.relative_to(a) for p in a.glob("*/*/*.tif")
                   if p.parts[-3] in ("tiles", "degraded"))
    for rel in files:
        with rasterio.open(a / rel) as x, rasterio.open(b / rel) as y:
            if not (np.array_equal(x.read(), y.read())
                    and np.array_equal(x.read_masks(1), y.read_masks(1))):
                return False
    return bool(files)


def run(size: int, tile_px: int, workers: list[str], keep: bool,
        site_cache: Path | None = None, gdalwarp: bool = True,
        steps: tuple[str, ...] = STEPS, ceiling_s: float | None = 2.5,
        repeats: int = 1) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="geosim-scale-"))
    try:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        import machine_ceiling

        ceiling = None
        if ceiling_s:
            ceiling = machine_ceiling.probe(seconds=ceiling_s)
            print("machine ceiling (2 processes ÷ 1):\n" + machine_ceiling.describe(ceiling),
                  flush=True)
        t0 = time.perf_counter()
        site_file, imagery, reused = make_site(tmp / "site", size, tile_px, site_cache)
        make_s = time.perf_counter() - t0
        print(f"site: {'reused from ' + str(site_cache) if reused else 'generated'} in "
              f"{make_s:.1f} s", flush=True)
        rows: list[dict] = []
        for w in workers:
            rows += run_steps(site_file, tmp / f"run_w{w}", w, size, tile_px, steps)
        # further rounds of every setting, in the same order (1, 2, 1, 2, ...): the speed-up
        # per round and its median, since one pair of runs moves by ±25 % on a small VM;
        # their run folders are removed after each round (1.8 GB of tiles each at 20000 px)
        later: list[dict] = []
        for r in range(1, repeats):
            for w in workers:
                again = tmp / f"run_w{w}_r{r}"
                later += [{**row, "round": r}
                          for row in run_steps(site_file, again, w, size, tile_px, steps)]
                shutil.rmtree(again, ignore_errors=True)
        out = tmp / f"run_w{workers[0]}"
        grid = json.loads((out / "grid" / "grid.json").read_text())
        from geosim.config import load_site

        flights = [f.image for f in load_site(site_file).flights]
        gw = (run_gdalwarp(flights, tmp / "gdalwarp", grid) if gdalwarp
              else {"skipped": "--no-gdalwarp"})
        n_tiles = len(list((out / "tiles").glob("*/*.tif")))
        print(f"gdalwarp: {gw}", flush=True)
        same = (all(_same_outputs(out, tmp / f"run_w{w}") for w in workers[1:])
                if len(workers) > 1 and n_tiles else None)
        doc = summarise(rows, gw, size, tile_px, n_tiles, imagery, make_s, workers, same)
        if later:
            doc["later_rounds"] = later
            doc["speedup_rounds"] = speedup_rounds(rows, later, workers)
        doc["site_reused_from_cache"] = reused
        doc["machine"]["lscpu"] = machine_ceiling.lscpu()
        if ceiling is not None:
            doc["machine_ceiling"] = ceiling
            doc["speedup_vs_ceiling"] = against_ceiling(doc, ceiling)
    finally:
        if keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    return doc


def summarise(rows: list[dict], gw: dict, size: int, tile_px: int, n_tiles: int,
              imagery: str, make_s: float, workers: list[str], same: bool | None) -> dict:
    by = {(r["workers"], r["step"]): r for r in rows}
    doc: dict = {
        "benchmark": "bench_scale", "flights": 3, "flight_px": size, "tile_px": tile_px,
        "tiles_per_flight": n_tiles // 3 if n_tiles else 0, "imagery": imagery,
        "site_generation_s": round(make_s, 1),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                    "platform": platform.platform(),
                    "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
        "workers": workers, "steps": rows, "gdalwarp": gw,
        "peak_rss_mb_max": {
            "driver": max(r["peak_rss_mb"] for r in rows),
            "worker": max((m for r in rows for m in r.get("worker_peak_rss_mb", [])),
                          default=None)},
        "outputs_identical_across_workers": same,
    }
    run_steps_ = [s for s in STEPS if (workers[0], s) in by]
    doc["steps_run"] = run_steps_
    prepare = ({w: round(sum(by[(w, s)]["seconds"] for s in ("grid", "align", "tiles")), 2)
                for w in workers} if {"grid", "align", "tiles"} <= set(run_steps_) else {})
    doc["prepare_resample_once_s"] = prepare
    if "seconds" in gw and prepare:
        doc["prepare_vs_gdalwarp"] = {w: round(v / gw["seconds"], 2) for w, v in prepare.items()}
    if len(workers) > 1:
        # against the in-process run ("1", one core) when there is one; "1t" apart below
        w1, wn = ("1" if "1" in workers[:-1] else workers[0]), workers[-1]
        doc["speedup"] = {s: round(by[(w1, s)]["seconds"] / by[(wn, s)]["seconds"], 2)
                          for s in run_steps_}
        doc["speedup_of"] = f"{wn} workers vs {w1}"
        if "1t" in workers and wn != "1t":  # pure multi-process scaling
            doc["speedup_vs_one_thread"] = {
                s: round(by[("1t", s)]["seconds"] / by[(wn, s)]["seconds"], 2)
                for s in run_steps_}
        # the step function alone, without the runner's per-command preflight and checksums
        doc["speedup_step_alone"] = {
            s: round(by[(w1, s)]["step_s"] / by[(wn, s)]["step_s"], 2) for s in run_steps_
            if by[(wn, s)].get("step_s")}
    if n_tiles and prepare and "degrade" in run_steps_:
        doc["extrapolation"] = {}
        for w in workers:
            # per 5000-px tile of one flight: prepare (per MP of flight) and degrade (per tile)
            prep_per_mp = prepare[w] / (3 * size * size / 1e6)
            degrade_per_mp = by[(w, "degrade")]["seconds"] / (n_tiles * tile_px ** 2 / 1e6)
            hours = PAPER_TILES * 25.0 * (prep_per_mp + degrade_per_mp) / 3600
            doc["extrapolation"][w] = {
                "paper_tiles": PAPER_TILES, "tile_px": 5000,
                "prepare_s_per_mp": round(prep_per_mp, 4),
                "degrade_s_per_mp": round(degrade_per_mp, 4),
                "hours_prepare_plus_degrade": round(hours, 2)}
        doc["extrapolation_assumes"] = (
            "cost proportional to megapixels; the paper's 1869 tiles counted as 1869 × 25 MP "
            "of flight imagery to prepare and degrade; this machine, this load")
    return doc


def speedup_rounds(first: list[dict], later: list[dict], workers: list[str]) -> dict:
    """Per step: the speed-up of the last worker setting over the first in every round
    (wall time of the same round's runs), and their median and range."""
    w1, wn = workers[0], workers[-1]
    rows = [{**r, "round": 0} for r in first] + later
    by = {(r["round"], r["workers"], r["step"]): r["seconds"] for r in rows}
    out: dict = {"of": f"{wn} workers vs {w1}, each round's own pair"}
    for step in dict.fromkeys(r["step"] for r in rows):
        ratios = [round(by[(k, w1, step)] / by[(k, wn, step)], 2)
                  for k in sorted({r["round"] for r in rows})
                  if (k, w1, step) in by and (k, wn, step) in by]
        out[step] = {"per_round": ratios, "median": round(float(np.median(ratios)), 2),
                     "min": min(ratios), "max": max(ratios)}
    return out


def against_ceiling(doc: dict, ceiling: dict) -> dict:
    """Each step's speed-up beside the machine's ceiling for the workload it is shaped
    like (``machine_ceiling.STEP_SHAPE``): the wall-time ceiling measured in this run and
    the two estimates of what two whole cores give (``machine_ceiling``'s docstring)."""
    out = {}
    for name, key in (("speedup", "speedup"), ("speedup_vs_one_thread", "speedup_vs_one_thread")):
        for step, x in (doc.get(key) or {}).items():
            shape = ceiling["step_shape"].get(step)
            if shape not in ceiling["ceilings"]:
                continue
            rec = out.setdefault(step, {
                "shape": shape, "ceiling": ceiling["ceilings"][shape],
                "ceiling_quiet": ceiling.get("quiet", {}).get(shape, False),
                "ceiling_corun": ceiling.get("ceilings_corun", {}).get(shape),
                "ceiling_two_cores": ceiling["ceilings_two_cores"][shape]})
            rec[name] = x
            rec[f"{name}_of_ceiling"] = round(x / ceiling["ceilings"][shape], 3)
    return out


def markdown(doc: dict) -> str:
    lines = [f"{doc['flights']} flights of {doc['flight_px']}² px ({doc['imagery']}), tiles of "
             f"{doc['tile_px']} px, {doc['machine']['cpus']} CPUs", "",
             "| step | workers | time (s) | step alone (s) | MP/s | CPU-s | driver CPU-s | "
             "workers busy | load (start→end) | peak RSS driver (MB) | peak RSS per worker "
             "(MB) | written (MB) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["steps"]:
        rss_w = ", ".join(f"{m:.0f}" for m in r.get("worker_peak_rss_mb", [])) or "–"
        load = "→".join(f"{v:.1f}" for v in r["load_average_1min"])
        busy = r.get("worker_busy_fraction")
        lines.append(f"| {r['step']} | {r['workers']} | {r['seconds']} | {r.get('step_s', '–')} | "
                     f"{r['mp_per_s']} | {r['cpu_s']} | {r.get('driver_cpu_s', '–')} | "
                     f"{'–' if busy is None else f'{busy:.0%}'} | {load} | "
                     f"{r['peak_rss_mb']:.0f} | {rss_w} | {r['bytes_written'] / 1e6:.0f} |")
    gw = doc["gdalwarp"]
    lines.append("")
    if "speedup" in doc:
        lines.append(f"Speed-up ({doc['speedup_of']}): "
                     + ", ".join(f"{k} {v}×" for k, v in doc["speedup"].items())
                     + "; the step alone: "
                     + ", ".join(f"{k} {v}×" for k, v in doc["speedup_step_alone"].items())
                     + ("" if "speedup_vs_one_thread" not in doc else
                        f"; {doc['workers'][-1]} workers vs 1 thread in-process: "
                        + ", ".join(f"{k} {v}×" for k, v in doc["speedup_vs_one_thread"].items()))
                     + f"; tiles and degraded tiles identical: "
                     f"{doc['outputs_identical_across_workers']}.")
    if doc.get("speedup_vs_ceiling"):
        lines.append("Against the machine's ceiling (2 processes ÷ 1 on a plain workload of "
                     "the step's shape, measured in this run): "
                     + ", ".join(f"{s} {r['speedup']}× of a machine ceiling {r['ceiling']}× "
                                 f"({r['shape']}"
                                 f"{'' if r['ceiling_quiet'] else ', NOT quiet'}; "
                                 f"{r['ceiling_two_cores']}× per CPU second, "
                                 + ("no co-run figure)" if r["ceiling_corun"] is None else
                                    f"{r['ceiling_corun']}× from the co-run repetitions)")
                                 for s, r in doc["speedup_vs_ceiling"].items() if "speedup" in r)
                     + ".")
    if doc.get("speedup_rounds"):
        rounds = doc["speedup_rounds"]
        lines.append(f"Speed-up per round ({rounds['of']}): "
                     + ", ".join(f"{s} median {r['median']}× "
                                 f"({', '.join(map(str, r['per_round']))})"
                                 for s, r in rounds.items() if s != "of") + ".")
    if "seconds" in gw and doc.get("prepare_vs_gdalwarp"):
        lines.append(f"gdalwarp, the same reprojection of the same flights (all CPUs): "
                     f"{gw['seconds']} s ({3 * doc['flight_px'] ** 2 / 1e6 / gw['seconds']:.2f}"
                     f" MP/s), {gw['bytes_written'] / 1e6:.0f} MB written.")
        lines.append("Resample-once prepare (grid + align + tiles) ÷ gdalwarp: "
                     + ", ".join(f"{w} worker(s) {v}×"
                                 for w, v in doc["prepare_vs_gdalwarp"].items()) + ".")
    else:
        lines.append(f"gdalwarp: {gw.get('skipped')}")
    for w, e in (doc.get("extrapolation") or {}).items():
        lines.append(f"Extrapolated to the paper's {e['paper_tiles']} tiles of 5000 px, "
                     f"{w} worker(s): {e['hours_prepare_plus_degrade']} h for prepare + degrade.")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=20000, help="flight side, px (default 20000)")
    ap.add_argument("--tile-px", type=int, default=5000, help="tile side, px (default 5000)")
    ap.add_argument("--workers", default="1,2",
                    help="worker counts to compare, comma-separated (default 1,2); 1 runs "
                         "in-process on one core, N > 1 on a local Dask cluster of N "
                         "processes, 1tK in-process on K threads per task (GEOSIM_THREADS=K)")
    ap.add_argument("--out", type=Path, default=RESULT)
    ap.add_argument("--keep", action="store_true", help="keep the temporary site and run")
    ap.add_argument("--site-cache", type=Path,
                    help="folder where the generated flights are kept and reused by later "
                         "runs of the same --size (site generation: ~450 s at 20000 px)")
    ap.add_argument("--no-gdalwarp", action="store_true",
                    help="skip the gdalwarp comparison")
    ap.add_argument("--steps", default=",".join(STEPS),
                    help="steps to run, in pipeline order, comma-separated (default: all; "
                         "a step needs the ones before it, e.g. grid,footprints,align)")
    ap.add_argument("--no-ceiling", action="store_true",
                    help="skip the machine-ceiling probe (≈ 40 s before the steps)")
    ap.add_argument("--ceiling-seconds", type=float, default=2.5,
                    help="wall seconds per phase of the ceiling probe (default 2.5)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds of every worker setting, alternated (default 1): the JSON "
                         "gets the speed-up per round and its median (speedup_rounds)")
    ap.add_argument("--child")
    ap.add_argument("--site")
    ap.add_argument("--run")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child_step(args.child, args.site, args.run, int(args.workers))))
        return
    workers = [w.strip() for w in str(args.workers).split(",")]
    if not all(w.isdigit() or (w.startswith("1t") and (w[2:] == "" or w[2:].isdigit()))
               for w in workers):
        ap.error("--workers: give counts such as 1,2 (and 1tK for K threads in-process)")
    steps = tuple(s.strip() for s in args.steps.split(","))
    if not set(steps) <= set(STEPS):
        ap.error(f"--steps: choose among {', '.join(STEPS)}")
    if args.repeat < 1:
        ap.error("--repeat: give a whole number ≥ 1")
    doc = run(args.size, args.tile_px, workers, args.keep, args.site_cache,
              not args.no_gdalwarp, steps, None if args.no_ceiling else args.ceiling_seconds,
              args.repeat)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(doc, indent=2) + "\n")
    print(markdown(doc))


if __name__ == "__main__":
    main()
