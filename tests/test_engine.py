"""The engines: a local Dask cluster and an existing scheduler give the same outputs as one
process, errors in workers come back as the same one-line errors, and a rerun resumes.

The truth compared against is an in-process run of the same steps on the sample site,
read back with GDAL / pyogrio / PIL (tests/engine_outputs.py), not the engine's own records.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio
from click.testing import CliRunner

from geosim.cli.main import cli
from geosim.engine import (
    WORKER_GDAL_CACHEMAX_MB,
    InProcess,
    LocalCluster,
    SchedulerCluster,
    _check_identities,
    _geosim_identity,
    _task_keys,
    make_engine,
    open_engine,
    parallel_map,
)
from geosim.errors import ConfigError, EngineError, InputFileError
from tests.engine_outputs import differing, output_digests

PROJECT = Path(__file__).resolve().parents[1]
#: Every step but diagnose (tested for equality by hand; 30-100 s on the sample site).
STEPS = ("grid", "footprints", "align", "tiles", "pairs", "labels", "calibrate", "degrade")
LATE = ("tiles", "pairs", "labels", "calibrate", "degrade")
#: What the late steps write (compared after a run of LATE only).
LATE_OUTPUTS = ("tiles/", "pairs.csv", "labels/", "calibration.", "degraded/")


def _only(steps: tuple[str, ...]) -> list[str]:
    return [a for s in steps for a in ("--only", s)]


def _run(site: Path, out: Path, *extra: str) -> dict:
    res = CliRunner().invoke(cli, ["run", str(site), "--out", str(out), *extra],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return json.loads((out / "run.json").read_text())


def _square(x: int) -> int:
    if x < 0:
        raise InputFileError(f"tile {x}.tif not found; run 'geosim tile' first")
    return x * x


@pytest.fixture(scope="module")
def base(samples_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The steps run in this process (--workers 1) on two threads per task
    (``GEOSIM_THREADS=2``): the reference outputs, which single-threaded workers must
    reproduce whatever the thread count."""
    out = tmp_path_factory.mktemp("engine") / "base"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("GEOSIM_THREADS", "2")
        record = _run(samples_dir / "site.toml", out, "--workers", "1", *_only(STEPS))
    assert record["engine"] == {"kind": "in-process", "workers": 1}
    return out


def _late_digests(run: Path) -> dict[str, str]:
    return {k: v for k, v in output_digests(run).items() if k.startswith(LATE_OUTPUTS)}


def _copy_early(base: Path, dst: Path) -> Path:
    """The run folder as it is after grid, footprints and align (no late outputs)."""
    shutil.copytree(base, dst, ignore=shutil.ignore_patterns(
        "tiles", "pairs.csv", "labels", "calibration.*", "degraded", ".geosim", "run.json"))
    return dst


# ----------------------------------------------------------------------------- units


def test_make_engine_choices() -> None:
    assert isinstance(make_engine(1), InProcess)
    assert isinstance(make_engine(2), LocalCluster)
    assert isinstance(make_engine(1, "tcp://127.0.0.1:8786"), SchedulerCluster)
    with pytest.raises(ConfigError, match="--workers 0"):
        make_engine(0)
    with pytest.raises(ConfigError, match="tcp://HOST:PORT"):
        make_engine(None, "somehost")


def _thread_budget(_: int) -> tuple[int, int, int, int]:
    """What a task sees: geosim's budget, scipy.fft's default workers (what geosim's FFT
    kernels use), OpenCV's threads, the BLAS threads (threadpoolctl)."""
    import cv2
    import scipy.fft
    from threadpoolctl import threadpool_info

    from geosim.engine import task_threads

    blas = max((p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"),
               default=1)
    return task_threads(), scipy.fft.get_workers(), cv2.getNumThreads(), blas


def test_thread_budget_one_thread_per_worker_in_process_too(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A task uses one thread for FFTs, OpenCV and GDAL on a worker of a multi-process
    engine and in this process (``--workers N`` = N cores); BLAS one thread everywhere
    (bit-identical sums); ``GEOSIM_THREADS`` raises the budget. Restored after the task.
    The command's own work between tasks: one thread under ``--workers 1`` (GDAL and
    OpenCV), every core under a cluster and in a library call. geosim's FFT kernels take
    scipy's default workers (the budget) unless told otherwise."""
    import inspect

    import cv2
    import scipy.fft

    from geosim.degrade.core import SpectralDegrader, blur
    from geosim.engine import task_threads
    from geosim.physics.otf import apply_transfer

    for kernel in (blur, SpectralDegrader, apply_transfer):
        assert inspect.signature(kernel).parameters["workers"].default is None, kernel
    monkeypatch.delenv("GEOSIM_THREADS", raising=False)
    cores = os.cpu_count() or 1
    cv2_before, fft_before = cv2.getNumThreads(), scipy.fft.get_workers()
    assert parallel_map(_thread_budget, [0]) == [(1, 1, 1, 1)]
    assert (cv2.getNumThreads(), scipy.fft.get_workers()) == (cv2_before, fft_before)
    assert task_threads() == cores  # a library call: no engine
    with open_engine(1):
        assert (task_threads(), cv2.getNumThreads()) == (1, 1)
        assert parallel_map(_thread_budget, [0]) == [(1, 1, 1, 1)]
    assert cv2.getNumThreads() == cv2_before
    with open_engine(2):
        assert task_threads() == cores
        assert parallel_map(_thread_budget, [0, 1, 2]) == [(1, 1, 1, 1)] * 3
    monkeypatch.setenv("GEOSIM_THREADS", "2")
    assert parallel_map(_thread_budget, [0]) == [(2, 2, 2, 1)]
    with open_engine(1):
        assert (task_threads(), cv2.getNumThreads()) == (2, 2)


def test_in_process_map_keeps_order_and_errors() -> None:
    assert parallel_map(_square, [3, 1, 2]) == [9, 1, 4]
    with pytest.raises(InputFileError, match="tile -1.tif"):
        parallel_map(_square, [1, -1])


def test_workers_must_import_the_same_geosim() -> None:
    mine = _geosim_identity()
    _check_identities({"tcp://127.0.0.1:1": dict(mine)}, "cluster")
    with pytest.raises(EngineError, match="imports geosim .* from /elsewhere/geosim"):
        _check_identities({"tcp://127.0.0.1:1": {**mine, "file": "/elsewhere/geosim/__init__.py"}},
                          "cluster")


def test_unreachable_scheduler_is_one_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("geosim.engine.CONNECT_TIMEOUT_S", 2)
    with pytest.raises(EngineError, match="cannot reach the Dask scheduler"), \
            open_engine(scheduler=f"tcp://127.0.0.1:{_free_port()}"):
        parallel_map(_square, [1, 2])


def test_local_cluster_order_workers_and_worker_errors(recwarn: pytest.WarningsRecorder
                                                       ) -> None:
    # Dask's dashboard port busy (another cluster on this machine) must not matter: the
    # scheduler's HTTP server takes a free port instead of warning about 8787
    busy = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        busy.bind(("127.0.0.1", 8787))
        busy.listen()
    except OSError:
        pass  # already taken by another program: the same case
    try:
        with open_engine(2) as engine:
            from distributed import get_task_stream

            with get_task_stream(engine.client) as stream:
                assert parallel_map(_square, list(range(8)), desc="a square") == [
                    i * i for i in range(8)]
            with pytest.raises(InputFileError, match="tile -1.tif not found"):
                parallel_map(_square, [2, -1, 3])
            info = engine.describe()
            worker_state = engine.client.run(_worker_state)
    finally:
        busy.close()
    assert not [w for w in recwarn if "already in use" in str(w.message)]
    assert info["kind"] == "local-cluster" and info["workers"] == 2
    assert info["workers_connected"] == 2
    assert info["scheduler"].startswith("tcp://127.0.0.1:")
    assert 1 <= len(info["workers_used"]) <= 2
    assert all(w.startswith("tcp://127.0.0.1:") for w in info["workers_used"])
    # Dask's statistical profiler is off on the workers geosim starts, and glibc was told
    # to keep freed heap despite the nanny's MALLOC_TRIM_THRESHOLD_=65536
    assert len(worker_state) == 2
    # ... and GDAL (asked itself) has the 256 MB block cache of WORKER_ENV
    for state in worker_state.values():
        assert state == {"profile": False, "trim_env": "65536", "heap_kept": True,
                         "gdal_cache_bytes": WORKER_GDAL_CACHEMAX_MB * 2**20}
    # the tasks are named by the step's label in Dask's task stream
    keys = sorted(str(t["key"]) for t in stream.data)
    assert len(keys) == 8 and all(k.startswith("a_square-") for k in keys)


def test_task_keys_are_unique_named_and_sort_in_task_order() -> None:
    keys = _task_keys(_square, None, 12)
    assert len(set(keys)) == 12 and all(k.startswith("_square-") for k in keys)
    assert sorted(keys) == keys  # Dask breaks ties by key: tasks start in this order
    again = _task_keys(_square, "local check", 3)
    assert all(k.startswith("local_check-") for k in again) and not set(again) & set(keys)


def _worker_state() -> dict:
    import os

    import dask

    from geosim.heap import keep_freed_heap
    from tests.helpers import gdal_cache_bytes

    return {"gdal_cache_bytes": gdal_cache_bytes(),
            "profile": dask.config.get("distributed.worker.profile.enabled"),
            "trim_env": os.environ.get("MALLOC_TRIM_THRESHOLD_"),
            "heap_kept": keep_freed_heap()}


def test_worker_error_reaches_the_cli_as_one_line(samples_dir: Path, tmp_path: Path) -> None:
    tiles = tmp_path / "run" / "tiles" / "PA1"
    tiles.mkdir(parents=True)
    (tiles / "r001_c001.tif").write_bytes(b"not a GeoTIFF")
    res = CliRunner().invoke(cli, ["degrade", str(samples_dir / "site.toml"), "--out",
                                   str(tmp_path / "run"), "--q", "2", "--workers", "2"])
    assert res.exit_code == 2, res.output
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("geosim: error:")]
    assert len(errors) == 1, res.stderr  # (progress lines like "[1/1] degrade: ..." may precede)
    assert "r001_c001.tif" in errors[0] and "Traceback" not in res.output
    assert not (tmp_path / "run" / "degraded" / "PA1" / "r001_c001.tif").exists()


# ----------------------------------------------------------------------------- same outputs


def test_two_worker_cluster_gives_the_same_outputs_and_reruns_skip(
        base: Path, samples_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "two"
    record = _run(samples_dir / "site.toml", out, "--workers", "2", *_only(STEPS))
    engine = record["engine"]
    assert engine["kind"] == "local-cluster" and engine["workers"] == 2
    assert len(engine["workers_used"]) == 2  # 12 tiles, 3 calibrations: both got work
    want = output_digests(base)
    assert len(want) > 40
    assert differing(want, output_digests(out)) == []

    # Nothing changed: the rerun skips every per-output task and says so.
    again = _run(samples_dir / "site.toml", out, "--workers", "2", *_only(STEPS))
    steps = again["steps"]
    assert steps["align"]["summary"]["skipped_current"] == 0  # no aligned/ rasters to skip
    assert steps["tiles"]["summary"]["skipped_current"] == 12
    assert steps["labels"]["summary"]["skipped_current"] == 1
    assert steps["calibrate"]["summary"]["skipped_current"] == 3
    assert steps["degrade"]["summary"]["skipped_current"] == 12
    assert "12 of 12 already current, skipped" in steps["degrade"]["summary"]["text"]
    assert differing(want, output_digests(out)) == []

    # One UAV tile changes: only its degraded tile is made again.
    tile = out / "tiles" / "PA2" / "r001_c001.tif"
    with rasterio.open(tile, "r+", IGNORE_COG_LAYOUT_BREAK="YES") as ds:  # tiles are COGs
        band = ds.read(1)
        band[:50, :50] = 255 - band[:50, :50]
        ds.write(band, 1)
    once = _run(samples_dir / "site.toml", out, "--workers", "1", "--only", "degrade")
    assert once["steps"]["degrade"]["summary"]["skipped_current"] == 11
    changed = differing(want, output_digests(out))
    assert changed == ["degraded/PA2/r001_c001.tif", "tiles/PA2/r001_c001.tif"]


#: Manifest folder of each step's per-output entries (.geosim/manifest/<folder>/...).
_ENTRY_STEP = {"aligned": "align", "tiles": "tiles", "calibration": "calibrate",
               "degraded": "degrade"}


def _finished_entries(out: Path) -> dict[str, int]:
    """Completed manifest entries per step.

    Entries are written atomically (a hidden ``.<name>.XXXX.part.json`` renamed into place),
    and ``Path.glob("*.json")`` matches hidden files too: a temp file must not count as a
    finished output, nor one that a SIGKILL left behind half-written.
    """
    counts = dict.fromkeys(_ENTRY_STEP.values(), 0)
    for folder, step in _ENTRY_STEP.items():
        root = out / ".geosim" / "manifest" / folder
        if root.is_dir():
            counts[step] = sum(1 for p in root.rglob("*.json") if not p.name.startswith("."))
    return counts


def _wait_group_gone(pgid: int, timeout_s: float = 60) -> None:
    """Wait until no live process of the group is left (the cluster's workers die with the
    driver, but a process is only gone once the kernel has delivered the signal)."""
    import psutil  # a dependency of dask.distributed

    def alive() -> list[int]:
        pids = []
        for p in psutil.process_iter(["status"]):
            try:
                if os.getpgid(p.pid) == pgid and p.info["status"] != psutil.STATUS_ZOMBIE:
                    pids.append(p.pid)
            except (ProcessLookupError, psutil.Error):
                pass
        return pids

    deadline = time.monotonic() + timeout_s
    while left := alive():
        assert time.monotonic() < deadline, f"processes {left} still alive after kill -9"
        time.sleep(0.05)


def test_kill_9_mid_run_then_rerun_equals_uninterrupted(
        base: Path, samples_dir: Path, tmp_path: Path) -> None:
    """Whatever moment the kill lands after the first finished output (the test process may
    notice it late on a loaded machine), the rerun skips every output the killed run
    finished and ends with the uninterrupted run's outputs."""
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "geosim", "run", str(samples_dir / "site.toml"), "--out",
           str(out), "--workers", "2", *_only(STEPS)]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PROJECT),
                                                        os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        deadline = time.monotonic() + 600  # generous: a loaded 2-core machine is slow
        while proc.poll() is None and not any(_finished_entries(out).values()):
            assert time.monotonic() < deadline, "no output finished within 600 s"
            time.sleep(0.05)
        assert proc.poll() is None, "the run finished before it could be killed"
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and its cluster, as kill -9 would
        proc.wait(timeout=60)
        _wait_group_gone(proc.pid)
    finally:
        _kill_group(proc)
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    # SIGKILL cannot be caught: the record still says running, never ok
    assert json.loads((out / "run.json").read_text())["status"] == "running"
    finished = _finished_entries(out)  # counted once every process of the run is gone
    assert sum(finished.values()) >= 1
    record = _run(samples_dir / "site.toml", out, "--workers", "2", *_only(STEPS))
    assert record["status"] == "ok"
    for step, n in finished.items():
        assert record["steps"][step]["summary"]["skipped_current"] >= n, (step, finished)
    assert differing(output_digests(base), output_digests(out)) == []


# ----------------------------------------------------------------------------- dask scheduler


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _kill_group(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=15)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait(timeout=15)


@pytest.fixture
def dask_cluster(tmp_path: Path) -> Iterator[tuple[str, list[subprocess.Popen]]]:
    """``dask scheduler`` and two ``dask worker`` processes on 127.0.0.1; stopped after."""
    dask_bin = Path(sys.executable).with_name("dask")
    if not dask_bin.is_file():
        pytest.skip(f"the dask command is not installed beside {sys.executable}")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PROJECT),
                                                        os.environ.get("PYTHONPATH", "")])}
    logs = tmp_path / "dask_logs"
    logs.mkdir()
    procs: list[subprocess.Popen] = []
    try:
        procs.append(subprocess.Popen(
            [str(dask_bin), "scheduler", "--host", "127.0.0.1", "--port", str(port),
             "--no-dashboard"], env=env, cwd=tmp_path, start_new_session=True,
            stdout=subprocess.DEVNULL, stderr=open(logs / "scheduler.log", "wb")))
        for i in range(2):
            procs.append(subprocess.Popen(
                [str(dask_bin), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                 "--nworkers", "1", "--no-dashboard", "--death-timeout", "60"],
                env=env, cwd=tmp_path, start_new_session=True, stdout=subprocess.DEVNULL,
                stderr=open(logs / f"worker{i}.log", "wb")))
        from distributed import Client

        # generous: the scheduler and workers start slowly on a loaded machine
        with Client(address, timeout=300) as client:
            client.wait_for_workers(2, timeout=300)
        yield address, procs
    finally:
        for p in reversed(procs):
            _kill_group(p)
        assert all(p.poll() is not None for p in procs)


def test_existing_scheduler_runs_the_steps_on_its_workers(
        base: Path, samples_dir: Path, tmp_path: Path,
        dask_cluster: tuple[str, list[subprocess.Popen]]) -> None:
    address, _ = dask_cluster
    out = _copy_early(base, tmp_path / "sched")
    from distributed import Client

    with Client(address, timeout=30) as client:
        worker_addresses = set(client.scheduler_info()["workers"])
    assert len(worker_addresses) == 2
    record = _run(samples_dir / "site.toml", out, "--scheduler", address, *_only(LATE))
    engine = record["engine"]
    assert engine["kind"] == "scheduler" and engine["address"] == address
    assert engine["workers_connected"] == 2
    assert set(engine["workers_used"]) <= worker_addresses and engine["workers_used"]
    want = _late_digests(base)
    assert len(want) >= 12 * 2 + 2
    assert differing(want, _late_digests(out)) == []
    # the tiles came from the workers: their provenance names the run folder's sources
    with rasterio.open(out / "degraded" / "PA1" / "r001_c001.tif") as ds:
        assert ds.tags()["GEOSIM_STEP"] == "degrade"
        assert np.any(ds.read(1))
