"""Where a tile task's CPU goes: the same tile tasks in this process and on a Dask worker.

The 20000 px ``bench_scale.py`` run found the tiles step's tasks costing ≈ 45 % more CPU
in-process (``--workers 1``) than on the workers of a local cluster. This script takes a
run folder that has passed ``align`` (e.g. ``bench_scale.py --steps
grid,footprints,align --keep``), builds the tiles step's tasks as ``run_tiles`` does, and
runs the first ``--tasks`` of them (outputs into a scratch folder) in one setting per
child process, alternating the settings over ``--rounds``:

``main``
    this process's main thread, as the in-process engine runs tasks;
``thread``
    one executor thread of this process, as a Dask worker runs tasks;
``worker``
    a local Dask cluster of 2 workers, tasks one at a time on one worker.

Every setting runs inside the pipeline's 256 MB GDAL block cache (workers: through their
environment; ``where:heap:bug``: ``rasterio.Env(GDAL_CACHEMAX=256)``, which the pipeline
used until this was found, and which GDAL takes as 256 bytes) and
:func:`geosim.engine.task_limits` with one thread.
``--heap`` chooses what glibc's malloc is told first: ``default`` (nothing), ``keep``
(:func:`geosim.heap.keep_freed_heap`), ``nanny`` (``MALLOC_TRIM_THRESHOLD_=65536`` in the
environment, as Dask's nanny starts its workers) or ``nanny+keep``. Per task it reports
the CPU seconds (user, system) of the process and its minor page faults.

Usage::

    python benchmarks/profile_tile_tasks.py --site S/site.toml --run S/run_w1 \\
        --settings main:keep:bug,main:keep,worker:nanny+keep --tasks 2 --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class _Capture:
    """An engine that runs every task inline except the tiles', which it only records."""

    def __init__(self) -> None:
        self.jobs: list = []

    def map(self, fn, items, *, desc=None):
        items = list(items)
        if desc == "tiles":
            self.jobs = items
            return [True] * len(items)
        return [fn(i) for i in items]

    def describe(self):
        return {"kind": "capture"}


def tile_tasks(site_file: str, run: str) -> list:
    """The tiles step's :class:`WarpTileTask` list (nothing cut)."""
    from geosim import engine
    from geosim.config import load_site
    from geosim.prepare.steps import run_tiles

    cap = _Capture()
    with engine.using(cap):
        run_tiles(load_site(site_file), run)
    return [job.task for job in cap.jobs]


def measured(task, scratch: str) -> dict:
    """Run one tile task (output into ``scratch``) as :func:`warp_tile_task` does; the
    task thread's CPU seconds for the read (decode + warp) and the write, the process's
    CPU (user, system) and its minor page faults."""
    from geosim.prepare.tiles import read_tile, write_tile

    dst = str(Path(scratch) / f"{os.getpid()}_t.tif")
    r0, w0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter(), time.thread_time()
    with task.flight.open() as reader:
        img, valid = read_tile(reader, task.tile.window, task.block_px)
        t1 = time.thread_time()
        write_tile(reader, task, dst, img, valid)
    t2 = time.thread_time()
    r1, w1 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    return {"read_thread_s": round(t1 - t0, 3), "write_thread_s": round(t2 - t1, 3),
            "user_s": round(r1.ru_utime - r0.ru_utime, 3),
            "sys_s": round(r1.ru_stime - r0.ru_stime, 3),
            "minflt": r1.ru_minflt - r0.ru_minflt, "wall_s": round(w1 - w0, 3)}


def _limited(task, scratch: str) -> dict:
    """:func:`measured` inside the engines' one-thread task limits (a worker's task)."""
    from geosim.engine import task_limits

    with task_limits(1):
        return measured(task, scratch)


def child(setting: str, tasks_file: str, n: int) -> list[dict]:
    """Run the first ``n`` tile tasks of ``tasks_file`` (a pickle) in the setting
    ``where:heap`` (this is a fresh process)."""
    import pickle

    import rasterio

    from geosim import heap

    where, how, *cache = setting.split(":")
    # the pipeline's environment (geosim.pipeline.gdal_environment), or "bug": the integer
    # 256 it used to give rasterio.Env, which GDAL takes as bytes
    cache_bytes = 256 if cache == ["bug"] else 256 * 2**20
    if how in ("keep", "nanny+keep"):
        heap.keep_freed_heap()
    tasks = pickle.loads(Path(tasks_file).read_bytes())[:n]
    scratch = tempfile.mkdtemp(prefix="geosim-tileprof-")
    if where == "worker":
        from distributed import Client, LocalCluster

        env = {"GDAL_CACHEMAX": "256", "OMP_NUM_THREADS": "1",
               "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "benchmarks")])}
        if how in ("default", "keep"):  # the nanny's variable left out: default malloc
            import dask

            dask.config.set({"distributed.nanny.pre-spawn-environ": {}})
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                          host="127.0.0.1", dashboard_address=None, env=env) as cl, \
                Client(cl) as client:
            if how in ("keep", "nanny+keep"):
                client.run(heap.keep_freed_heap)
            mod = "profile_tile_tasks"
            return [client.submit(__import__(mod)._limited, t, scratch,
                                  pure=False).result() for t in tasks]
    out: list[dict] = []
    with rasterio.Env(GDAL_CACHEMAX=cache_bytes):
        if where == "main":
            out = [_limited(t, scratch) for t in tasks]
        else:
            def body() -> None:
                with rasterio.Env(GDAL_CACHEMAX=cache_bytes):
                    out.extend(_limited(t, scratch) for t in tasks)
            th = threading.Thread(target=body)
            th.start()
            th.join()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--site", required=True)
    ap.add_argument("--run", required=True)
    ap.add_argument("--settings", default="main:keep,thread:keep,worker:keep")
    ap.add_argument("--tasks", type=int, default=4)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--child")
    a = ap.parse_args()
    tasks_file = Path(a.run) / "tile_tasks.pickle"
    if a.child:
        print(json.dumps(child(a.child, str(tasks_file), a.tasks)))
        return
    import pickle

    sys.path.insert(0, str(ROOT))
    if not tasks_file.is_file():
        tasks_file.write_bytes(pickle.dumps(tile_tasks(a.site, a.run)))
    rows = []
    for rnd in range(a.rounds):
        for setting in a.settings.split(","):
            env = dict(os.environ,
                       PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "benchmarks")]))
            if setting.split(":")[1].startswith("nanny"):
                env["MALLOC_TRIM_THRESHOLD_"] = "65536"
            load = os.getloadavg()[0]
            proc = subprocess.run([sys.executable, __file__, "--child", setting, "--site",
                                   a.site, "--run", a.run, "--tasks", str(a.tasks)],
                                  capture_output=True, text=True, env=env)
            if proc.returncode:
                raise RuntimeError(proc.stderr[-3000:])
            tasks = json.loads(proc.stdout.strip().splitlines()[-1])
            row = {"round": rnd, "setting": setting, "load_1min": round(load, 2),
                   "cpu_s": round(sum(t["user_s"] + t["sys_s"] for t in tasks), 2),
                   "sys_s": round(sum(t["sys_s"] for t in tasks), 2),
                   "read_thread_s": round(sum(t["read_thread_s"] for t in tasks), 2),
                   "write_thread_s": round(sum(t["write_thread_s"] for t in tasks), 2),
                   "minflt": sum(t["minflt"] for t in tasks), "tasks": tasks}
            rows.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "tasks"}), flush=True)
    if a.out:
        a.out.write_text(json.dumps({"settings": a.settings, "tasks": a.tasks,
                                     "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
