"""Benchmark: the degrade and calibrate steps at 1 worker (in-process) and 2 worker processes.

Degrade runs on a synthetic run folder of 3 flights × ``--tiles`` UAV tiles of ``--size`` px
(real drone imagery from ../shared/realdata mirrored out, or synthetic texture; see
bench_degrade.make_tile), calibrate on the sample site after grid, footprints and align.
The 2-worker engine is a local Dask cluster (:class:`geosim.engine.LocalCluster`); its
start-up is timed apart and the step times are taken with the cluster already up, as in a
``geosim run`` where the cluster serves every step. Runs alternate (1, 2, 1, 2, ...) so
that a change in the machine's load hits both; the load average is recorded around each.
The outputs of the two engines are compared (decoded pixels, JSON without timings).

Usage::

    python benchmarks/bench_engine.py                 # writes results/bench_engine.json
    python benchmarks/bench_engine.py --size 2000 --tiles 2 --repeats 1   # quicker
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from bench_degrade import make_tile  # noqa: E402

from geosim.config import load_site  # noqa: E402
from geosim.engine import InProcess, LocalCluster, using  # noqa: E402
from geosim.io.raster import write_geotiff  # noqa: E402
from tests.engine_outputs import differing, output_digests  # noqa: E402

RESULT = ROOT / "benchmarks" / "results" / "bench_engine.json"
SITE = ROOT / "data" / "samples" / "site.toml"


def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def make_tiles(out: Path, flights: list[str], n: int, size: int) -> str:
    """``n`` tiles of ``size`` px per flight under ``out/tiles/`` (0.05 m, EPSG:32756)."""
    base, source = make_tile(size)
    for i, fid in enumerate(flights):
        for k in range(n):
            img = np.roll(base, shift=(i * 997 + k * 331) % size, axis=2)
            t = Affine(0.05, 0, 300000 + 25.0 * k, 0, -0.05, 6200000 - 25.0 * i)
            write_geotiff(out / "tiles" / fid / f"r{i:03d}_c{k:03d}.tif", img, transform=t,
                          crs="EPSG:32756", band_descriptions=["red", "green", "blue"])
    return source


def cpu_seconds() -> float:
    """User + system CPU time of this process so far (all its threads), seconds."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _cpu_total(engine: Any) -> float:
    """CPU seconds of this process plus, on a cluster, of every worker process."""
    total = cpu_seconds()
    if isinstance(engine, LocalCluster):
        total += sum(engine.client.run(cpu_seconds).values())
    return total


def _timed(engine: Any, fn: Any) -> dict[str, Any]:
    """Wall and CPU seconds of ``fn`` on ``engine``; CPU / wall says how busy the cores were
    for it (2.0 = both cores all the time; much less = waiting for a core, i.e. other load)."""
    before = _load()
    cpu0 = _cpu_total(engine)
    start = time.perf_counter()
    with using(engine):
        fn()
    wall = time.perf_counter() - start
    cpu = _cpu_total(engine) - cpu0
    return {"seconds": round(wall, 3), "cpu_seconds": round(cpu, 3),
            "cpu_per_wall": round(cpu / wall, 3), "load_before": before, "load_after": _load()}


def bench(step: str, run: Path, fn: Any, clear: Any, cluster: LocalCluster,
          repeats: int, digest_prefix: str) -> dict[str, Any]:
    """Alternate in-process and 2-worker runs of ``fn``; compare the outputs."""
    times: dict[str, list[dict[str, Any]]] = {"1": [], "2": []}
    digests: dict[str, dict[str, str]] = {}
    for _ in range(repeats):
        for key, engine in (("1", InProcess()), ("2", cluster)):
            clear()
            times[key].append(_timed(engine, fn))
            digests[key] = {k: v for k, v in output_digests(run).items()
                            if k.startswith(digest_prefix)}
            print(f"{step} workers={key}: {times[key][-1]}", flush=True)
    best = {k: min(t["seconds"] for t in v) for k, v in times.items()}
    return {"runs": times, "best_seconds": best,
            "speedup_2_over_1": round(best["1"] / best["2"], 3),
            "outputs_compared": len(digests["1"]),
            "outputs_identical": differing(digests["1"], digests["2"]) == []}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=3000, help="tile side, px")
    ap.add_argument("--tiles", type=int, default=4, help="tiles per flight (3 flights)")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULT)
    args = ap.parse_args()

    from geosim.degrade.steps import run_calibrate, run_degrade
    from geosim.pipeline import run_pipeline

    site = load_site(SITE)
    result: dict[str, Any] = {"machine": {"cpus": os.cpu_count(), "python":
                                          platform.python_version(),
                                          "load_at_start": _load()},
                              "note": "the machine's 2 cores are shared with other users; "
                                      "load averages above 2 mean other work competed"}
    with tempfile.TemporaryDirectory(prefix="bench_engine_") as tmp:
        tmp = Path(tmp)
        cluster = LocalCluster(2)
        try:
            start = time.perf_counter()
            _ = cluster.client  # start the cluster and check its workers
            result["cluster_start_seconds"] = round(time.perf_counter() - start, 3)

            # ---------------------------------------------------------------- degrade
            run = tmp / "degrade"
            source = make_tiles(run, list(site.flight_ids), args.tiles, args.size)

            def clear_degrade() -> None:
                shutil.rmtree(run / "degraded", ignore_errors=True)
                shutil.rmtree(run / ".geosim", ignore_errors=True)

            res = bench("degrade", run, lambda: run_degrade(site, run, q=2.0), clear_degrade,
                        cluster, args.repeats, "degraded/")
            mp = 3 * args.tiles * args.size ** 2 / 1e6
            res.update({"tiles": 3 * args.tiles, "tile_px": args.size, "source": source,
                        "megapixels": mp,
                        "mp_per_s": {k: round(mp / v, 2) for k, v in res["best_seconds"].items()}})
            result["degrade"] = res

            # ---------------------------------------------------------------- calibrate
            run = tmp / "sample"
            run_pipeline(site, run, only=["grid", "footprints", "align"], echo=lambda s: None)

            def clear_calibrate() -> None:
                shutil.rmtree(run / ".geosim", ignore_errors=True)
                for name in ("calibration.json", "calibration.png"):
                    (run / name).unlink(missing_ok=True)

            res = bench("calibrate", run, lambda: run_calibrate(site, run), clear_calibrate,
                        cluster, args.repeats, "calibration.")
            res.update({"flights": len(site.flights), "site": "data/samples (3 flights, "
                        "aligned grid 1870×1880 px at 0.05 m)"})
            result["calibrate"] = res
        finally:
            cluster.close()
    result["machine"]["load_at_end"] = _load()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: result[k] for k in ("cluster_start_seconds",)}, indent=2))
    for step in ("degrade", "calibrate"):
        r = result[step]
        print(f"{step}: best 1 worker {r['best_seconds']['1']} s, 2 workers "
              f"{r['best_seconds']['2']} s, speedup {r['speedup_2_over_1']}, identical "
              f"{r['outputs_identical']}")


if __name__ == "__main__":
    main()
