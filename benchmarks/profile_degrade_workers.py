"""Where the degrade step's CPU goes in-process on one thread and on 2 Dask workers.

A run folder of ``--tiles`` 5000 × 5000 RGB tiles of real imagery (written as ``geosim
tile`` writes them, as bench_degrade_command.py does), half of them partial (an invalid
edge strip, as the tiles at a flight's edge: the no-data fill runs on them).
``run_degrade`` runs on it ``--reps`` times per setting, each in its own process: ``1t``
(in-process, one thread, ``GEOSIM_THREADS=1``) and ``2`` (a local cluster of 2
single-threaded workers, up before the clock). Reported per run: wall time, CPU seconds of
the driver and of the workers, and, summed over the tasks, the task thread's CPU inside
each part (``time.thread_time`` around the step module's reads — ``read_raster`` and, for
whole tiles, ``read_binomial_level1`` —, its kernels ``degrade_array`` / ``degrade_level1``,
``write_geotiff``, the manifest's record and check, and the whole ``degrade_tile_task``):
what the workers spent outside the tasks is ``workers_cpu - task_total`` (Dask's own
threads). ``--code DIR`` runs another checkout's geosim (e.g. main's, ``git archive main |
tar -x -C DIR``), alternated with this one.

Usage: ``python benchmarks/profile_degrade_workers.py [--tiles 8] [--reps 2] [--code DIR]
[--out FILE]``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def setup(root: Path, n_tiles: int) -> None:
    """Tiles F0.. (full) and P0.. (partial: an invalid left strip and top strip)."""
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from affine import Affine
    from bench_degrade import make_tile

    from geosim.prepare.tiles import write_tile_array

    tile, _ = make_tile(5000)
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    lines = ['[site]', 'name = "degrade workers"', 'crs = "EPSG:32756"',
             'reference_flight = "F0"', '', '[parameters]', 'tile_px = 5000', 'q = 4.34', '']
    for i in range(n_tiles):
        fid = f"{'FP'[i % 2]}{i // 2}"
        img = np.roll(tile, 97 * i, axis=2).copy()
        valid = np.ones(img.shape[1:], bool)
        if fid.startswith("P"):
            valid[:, : 400 + 300 * i] = False
            valid[: 100 * i] = False
            img[:, ~valid] = 0
        path = root / "run" / "tiles" / fid / "r000_c000.tif"
        # as `geosim tile` writes it: whole tiles get their binomial first overview
        write_tile_array(path, img, valid, transform=t, crs="EPSG:32756")
        lines += ['[[flights]]', f'id = "{fid}"', f'image = "{path}"',
                  f'acquired = "2021-07-15T{10 + i:02d}:00:00+10:00"', '']
    (root / "site.toml").write_text("\n".join(lines))


def _cpu() -> float:
    t = os.times()
    return t.user + t.system


def install() -> None:
    """Time the parts of the degrade task (thread CPU), in this process."""
    import geosim.degrade.steps as st
    import geosim.manifest as mf

    if getattr(st, "_bench_phase", None) is not None:
        return
    st._bench_phase = {}

    def wrap(mod, name: str, key: str) -> None:
        f = getattr(mod, name)

        def timed(*a, **k):
            c = time.thread_time()
            try:
                return f(*a, **k)
            finally:
                st._bench_phase[key] = st._bench_phase.get(key, 0.0) + time.thread_time() - c

        setattr(mod, name, timed)

    wrap(st, "read_raster", "read")
    wrap(st, "degrade_array", "kernel")
    if hasattr(st, "read_binomial_level1"):  # whole tiles read at their first overview
        wrap(st, "read_binomial_level1", "read")
        wrap(st, "degrade_level1", "kernel")
    wrap(st, "write_geotiff", "write")
    wrap(st, "degrade_tile_task", "task_total")
    wrap(mf, "record_output", "manifest_record")
    wrap(mf, "is_current", "manifest_check")


def phases() -> dict:
    import geosim.degrade.steps as st

    out = dict(st._bench_phase)
    st._bench_phase.clear()
    return out


def child(root: Path, mode: str, reps: int) -> list[dict]:
    if mode == "1t":
        os.environ["GEOSIM_THREADS"] = "1"
    from geosim import engine
    from geosim.config import load_site
    from geosim.degrade.steps import run_degrade

    site = load_site(root / "site.toml")
    n = int(mode.rstrip("t"))
    rows = []
    with engine.open_engine(n) as eng:
        client = eng.client if n > 1 else None
        if client is not None:
            client.run(install)
        install()
        for _ in range(reps):
            for sub in ("degraded", ".geosim"):
                shutil.rmtree(root / "run" / sub, ignore_errors=True)
            d0, w0 = _cpu(), sum(client.run(_cpu).values()) if client else 0.0
            if client is not None:
                client.run(phases)
            load0 = os.getloadavg()[0]
            t0 = time.perf_counter()
            run_degrade(site, root / "run")
            wall = time.perf_counter() - t0
            d1, w1 = _cpu(), sum(client.run(_cpu).values()) if client else 0.0
            parts: dict[str, float] = {}
            for p in (client.run(phases).values() if client else [phases()]):
                for k, v in p.items():
                    parts[k] = round(parts.get(k, 0.0) + v, 3)
            rows.append({"mode": mode, "wall_s": round(wall, 2),
                         "driver_cpu_s": round(d1 - d0, 2), "workers_cpu_s": round(w1 - w0, 2),
                         "total_cpu_s": round(d1 - d0 + w1 - w0, 2),
                         "load_1min": [round(load0, 1), round(os.getloadavg()[0], 1)],
                         "task_cpu_s": parts})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tiles", type=int, default=8)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--code", type=Path, help="another geosim checkout, alternated with this")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--child")
    ap.add_argument("--root", type=Path)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(args.root, args.child, args.reps)))
        return
    codes = {"this": ROOT, **({"other": args.code.resolve()} if args.code else {})}
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        setup(root, args.tiles)
        for mode in ("1t", "2"):
            for label, code in codes.items():
                env = {**os.environ, "PYTHONPATH": os.pathsep.join(
                    [str(code), str(Path(__file__).parent)])}
                proc = subprocess.run([sys.executable, __file__, "--child", mode, "--root",
                                       str(root), "--reps", str(args.reps)],
                                      capture_output=True, text=True, env=env, check=True)
                rows = json.loads(proc.stdout.strip().splitlines()[-1])
                for r in rows:
                    r["code"] = str(code) if label == "other" else "this checkout"
                    print(json.dumps(r), flush=True)
                results += rows
    doc = {"benchmark": "profile_degrade_workers", "tiles": args.tiles,
           "partial_tiles": args.tiles // 2, "tile_px": 5000, "reps": args.reps,
           "cpus": os.cpu_count(), "runs": results}
    if args.out is not None:
        args.out.write_text(json.dumps(doc, indent=2) + "\n")


if __name__ == "__main__":
    main()
