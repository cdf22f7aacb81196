"""Where per-window, per-tile and per-flight tasks run.

A step is a plan (which outputs, from which inputs) plus tasks; each task reads its
inputs, computes and writes its own output atomically, and returns a small record.
Steps hand their tasks to :func:`parallel_map`, which runs them on the active engine:
in this process by default, or on a Dask cluster when one is active (see
:func:`using` and :func:`open_engine`). The driver only gathers the small records, in
task order, so the outputs are the same whatever ran them.

Task functions must be importable top-level functions and their arguments and results
picklable, so that they can be sent to worker processes.

Engines
-------
:class:`InProcess`
    Every task in this process, one after the other, on one thread (``--workers 1``).
:class:`LocalCluster`
    A ``dask.distributed`` cluster of N single-threaded worker processes on this
    machine, bound to 127.0.0.1 with no dashboard (``--workers N``).
:class:`SchedulerCluster`
    An existing Dask cluster reached through its scheduler's address
    (``--scheduler tcp://HOST:8786``); its workers must share the run folder's
    filesystem and import the same geosim.
"""

from __future__ import annotations

import functools
import logging
import os
import pickle
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, Protocol, TypeVar

from tqdm import tqdm

from geosim.errors import ConfigError, EngineError
from geosim.heap import keep_freed_heap

T = TypeVar("T")
R = TypeVar("R")

#: GDAL block cache per worker process (MB): bounded, so N workers stay within memory.
WORKER_GDAL_CACHEMAX_MB = 256
#: Environment every worker process gets: GDAL's cache bounded, one thread per
#: numerical library (the worker itself is the unit of parallelism).
WORKER_ENV: dict[str, str] = {
    "GDAL_CACHEMAX": str(WORKER_GDAL_CACHEMAX_MB),
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
}
#: Seconds to wait for a scheduler or a local cluster to answer.
CONNECT_TIMEOUT_S = 30


class Engine(Protocol):
    """Runs independent tasks and returns their results in task order."""

    def map(self, fn: Callable[[T], R], items: Iterable[T], *,
            desc: str | None = None) -> list[R]:
        """``[fn(item) for item in items]``, possibly in parallel (``desc`` labels progress)."""
        ...

    def describe(self) -> dict[str, Any]:
        """What ran the tasks, for ``run.json`` (kind, number of workers, address)."""
        ...


class InProcess:
    """Runs every task in this process, one after the other."""

    def map(self, fn: Callable[[T], R], items: Iterable[T], *,
            desc: str | None = None) -> list[R]:
        items = list(items)
        out = []
        threads = task_budget()
        keep_freed_heap()
        for item in tqdm(items, desc=desc, unit="task", disable=None, leave=False):
            with task_limits(threads):
                out.append(fn(item))
        return out

    def describe(self) -> dict[str, Any]:
        return {"kind": "in-process", "workers": 1}

    def close(self) -> None:
        """Nothing to release."""


# --------------------------------------------------------------------------- Dask

def _geosim_identity() -> dict[str, str]:
    """Where this process imports geosim from, and its version (checked on every worker)."""
    import geosim

    return {"file": str(Path(geosim.__file__).resolve()), "version": geosim.__version__}


def _setup_worker(quiet: bool = False) -> dict[str, str]:
    """Bound GDAL's cache and numerical threads in a worker; return its geosim identity.

    ``quiet`` (workers this process started) mutes the worker's own report of a failed
    task: the driver reports it, as one line.
    """
    if quiet:
        logging.getLogger("distributed.worker").setLevel(logging.CRITICAL)
    for key, value in WORKER_ENV.items():
        os.environ.setdefault(key, value)
    keep_freed_heap()  # Dask's nanny starts workers with MALLOC_TRIM_THRESHOLD_=65536
    import cv2

    cv2.setNumThreads(1)
    return _geosim_identity()


def _threads_from_env(default: int) -> int:
    """``GEOSIM_THREADS`` when set to a whole number ≥ 1, else ``default``."""
    env = os.environ.get("GEOSIM_THREADS", "").strip()
    return int(env) if env.isdigit() and int(env) > 0 else default


_TASK_THREADS: ContextVar[int | None] = ContextVar("geosim_task_threads", default=None)


def task_threads() -> int:
    """Threads the running task may use for FFTs, OpenCV and GDAL (warps, block decoding).

    Inside a task: what its engine gave it (one, on a Dask worker and in this process).
    Outside any task: the driver's own work under an active in-process engine
    (``--workers 1``) gets one thread, like its tasks, so that ``--workers 1`` uses one
    core; under a Dask engine (whose workers wait while the driver works) and in a
    library call with no engine, every core. ``GEOSIM_THREADS`` overrides all of these.
    """
    threads = _TASK_THREADS.get()
    if threads is not None:
        return threads
    in_process_driver = isinstance(_ACTIVE.get(), InProcess)
    return _threads_from_env(1 if in_process_driver else os.cpu_count() or 1)


@contextmanager
def task_limits(threads: int) -> Iterator[None]:
    """The thread budget of one task: ``threads`` for FFTs, OpenCV and GDAL, one for BLAS.

    * BLAS and OpenMP: one thread on every engine. A multi-threaded BLAS sums in an order
      that depends on its thread count, which changes the last bits of floating-point
      results (seen in calibration.json); one thread everywhere keeps outputs identical.
    * ``scipy.fft``: ``threads`` workers (``scipy.fft.set_workers``), which every geosim
      kernel uses by default (``workers=None``): on a worker of a multi-process engine
      every core is already busy with another worker, and N processes × N FFT threads on
      N cores only adds contention. (pocketfft splits independent 1-D transforms over its
      threads, so the results do not depend on the count.)
    * OpenCV: ``threads`` (its parallel loops split rows; results do not depend on it).
    * GDAL: :func:`task_threads` returns ``threads``; the warp and decode calls ask it.
    """
    import cv2
    import scipy.fft
    from threadpoolctl import threadpool_limits

    threads = max(1, int(threads))
    cv2_threads = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    token = _TASK_THREADS.set(threads)
    try:
        with threadpool_limits(limits=1), scipy.fft.set_workers(threads):
            yield
    finally:
        _TASK_THREADS.reset(token)
        cv2.setNumThreads(cv2_threads)


def task_budget() -> int:
    """Threads a task gets on every engine, in this process (``--workers 1``) as on a Dask
    worker: one, since the process is the unit of parallelism (so ``--workers N`` means
    N cores whatever N is), or this process's ``GEOSIM_THREADS``."""
    return _threads_from_env(1)


def _run_task(fn: Callable[[T], R], item: T) -> tuple[str, R]:
    """Run one task on a worker; return the worker's address with the result."""
    from distributed import get_worker

    from geosim.errors import GeosimError

    try:
        with task_limits(task_budget()):
            return get_worker().address, fn(item)
    except GeosimError as exc:
        # The message is the error; its cause or context (often a GDAL exception that does
        # not pickle) would make Dask send a generic Exception instead of this class, so
        # the copy is raised outside the handler, with neither.
        error = _portable(exc)
    raise error


def _task_keys(fn: Callable[..., Any], desc: str | None, n: int) -> list[str]:
    """Unique Dask keys naming the step's tasks (``local_check-<token>-000000`` …) rather
    than Dask's default, the wrapper's name, so a task stream or the dashboard says what ran.

    The index is zero-padded so that the keys sort in task order: Dask breaks ties between
    independent tasks by key, and with unpadded indices it started task 1 before 0, 3
    before 2 (seen on 2 workers); padded, they start in the order given, as with Dask's
    default keys.
    """
    import uuid

    name = (desc or getattr(fn, "__name__", "task")).strip().replace(" ", "_") or "task"
    token = uuid.uuid4().hex[:12]
    return [f"{name}-{token}-{i:06d}" for i in range(n)]


def _portable(exc: BaseException) -> BaseException:
    """``exc`` without cause or context, as the same class when it can be rebuilt."""
    try:
        clean = type(exc)(*exc.args)
        pickle.loads(pickle.dumps(clean))
    except Exception:
        from geosim.errors import GeosimError

        clean = GeosimError(str(exc))
    return clean


class DaskEngine:
    """Tasks on a ``dask.distributed`` cluster; subclasses say how the client is made.

    The client is made on the first :meth:`map` with at least one task, so a command
    with nothing to distribute starts no cluster.
    """

    def __init__(self) -> None:
        self._client: Any | None = None
        self.workers_used: set[str] = set()
        self.n_workers: int | None = None
        #: Mute the workers' own task-failure logs (only for workers we started).
        self.quiet_workers = False

    # subclasses -------------------------------------------------------------------
    def _connect(self) -> Any:  # pragma: no cover - abstract
        raise NotImplementedError

    def _base_description(self) -> dict[str, Any]:  # pragma: no cover - abstract
        raise NotImplementedError

    # engine -----------------------------------------------------------------------
    @property
    def client(self) -> Any:
        """The ``distributed.Client``, connected (and workers checked) on first use."""
        if self._client is None:
            client = self._connect()
            try:
                identities = client.run(_setup_worker, self.quiet_workers)
            except Exception as exc:
                client.close()
                raise EngineError(f"{self.label}: could not set up the Dask workers "
                                  f"({type(exc).__name__}: {exc})") from None
            try:
                _check_identities(identities, self.label)
            except EngineError:
                client.close()
                raise
            self.n_workers = len(identities)
            self._client = client
        return self._client

    @property
    def label(self) -> str:
        return str(self._base_description().get("address") or self._base_description()["kind"])

    def map(self, fn: Callable[[T], R], items: Iterable[T], *,
            desc: str | None = None) -> list[R]:
        from distributed import as_completed

        items = list(items)
        if not items:
            return []
        client = self.client
        futures = client.map(functools.partial(_run_task, fn), items, pure=False,
                             key=_task_keys(fn, desc, len(items)))
        try:
            with tqdm(total=len(futures), desc=desc, unit="task", disable=None,
                      leave=False) as bar:
                for _ in as_completed(futures):
                    bar.update()
            done = client.gather(futures, errors="raise")
        except Exception as exc:
            for f in futures:
                f.cancel()
            raise _as_geosim_error(exc, self.label) from None
        self.workers_used.update(address for address, _ in done)
        return [result for _, result in done]

    def describe(self) -> dict[str, Any]:
        out = self._base_description()
        if self.n_workers is not None:
            out["workers_connected"] = self.n_workers
        out["workers_used"] = sorted(self.workers_used)
        return out

    def close(self) -> None:
        """Close the client (and, for a local cluster, the cluster)."""
        if self._client is not None:
            self._client.close()
            self._client = None


class LocalCluster(DaskEngine):
    """A local ``dask.distributed`` cluster of ``workers`` single-threaded processes.

    Bound to 127.0.0.1 with no dashboard; each worker gets :data:`WORKER_ENV` and this
    process's ``sys.path`` first on ``PYTHONPATH`` (so it imports the same geosim).
    """

    def __init__(self, workers: int) -> None:
        super().__init__()
        if workers < 2:
            raise ConfigError(f"a local cluster needs at least 2 workers (got {workers}); "
                              "use --workers 1 to run in this process")
        self.workers = workers
        self.quiet_workers = True
        self._cluster: Any | None = None

    def _connect(self) -> Any:
        import dask
        from distributed import Client
        from distributed import LocalCluster as DaskLocalCluster

        geosim_root = str(Path(_geosim_identity()["file"]).parents[1])
        python_path = os.pathsep.join(
            [geosim_root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                             if p and p != geosim_root])
        env = {**WORKER_ENV, "PYTHONPATH": python_path}
        try:
            with dask.config.set({"distributed.worker.daemon": False,
                                  "distributed.logging.distributed": "error",
                                  # the statistical profiler samples every thread's stack
                                  # 100 times a second: 2-3 % of a busy worker's CPU
                                  "distributed.worker.profile.enabled": False}):
                self._cluster = DaskLocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    host="127.0.0.1", dashboard_address=None, env=env,
                    # the scheduler's HTTP server (health, metrics) would otherwise take
                    # port 8787 (and warn when that is busy): a free port on 127.0.0.1
                    scheduler_kwargs={"dashboard": False,
                                      "dashboard_address": "127.0.0.1:0"},
                    silence_logs=logging.ERROR, timeout=CONNECT_TIMEOUT_S)
            return Client(self._cluster, timeout=CONNECT_TIMEOUT_S)
        except Exception as exc:
            self.close()
            raise EngineError(f"could not start a local Dask cluster of {self.workers} "
                              f"workers ({type(exc).__name__}: {exc}); try --workers 1"
                              ) from None

    def _base_description(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": "local-cluster", "workers": self.workers,
                               "threads_per_worker": 1}
        if self._cluster is not None:
            out["scheduler"] = self._cluster.scheduler_address
        return out

    def close(self) -> None:
        super().close()
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None


class SchedulerCluster(DaskEngine):
    """An existing Dask cluster, reached at ``address`` (e.g. ``tcp://host:8786``)."""

    def __init__(self, address: str) -> None:
        super().__init__()
        if "://" not in address and ":" not in address:
            raise ConfigError(f"--scheduler {address!r} is not a scheduler address; give "
                              "it as tcp://HOST:PORT (dask scheduler prints it)")
        self.address = address

    def _connect(self) -> Any:
        from distributed import Client

        try:
            client = Client(self.address, timeout=CONNECT_TIMEOUT_S)
        except Exception as exc:
            raise EngineError(f"cannot reach the Dask scheduler at {self.address} "
                              f"({type(exc).__name__}: {exc}); start it with 'dask scheduler' "
                              "and its workers with 'dask worker ADDRESS', or check the "
                              "address") from None
        if not client.scheduler_info().get("workers"):
            try:
                client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
            except Exception:
                client.close()
                raise EngineError(f"the Dask scheduler at {self.address} has no workers; "
                                  f"start some with 'dask worker {self.address}'") from None
        return client

    def _base_description(self) -> dict[str, Any]:
        return {"kind": "scheduler", "address": self.address}


def _check_identities(identities: dict[str, dict[str, str]], label: str) -> None:
    """EngineError unless every worker imports the same geosim (file and version) as us."""
    mine = _geosim_identity()
    for address, theirs in sorted(identities.items()):
        if theirs != mine:
            raise EngineError(
                f"{label}: worker {address} imports geosim {theirs['version']} from "
                f"{theirs['file']}, this process geosim {mine['version']} from {mine['file']}; "
                "start the workers in the same environment (same virtualenv and PYTHONPATH)")


def _as_geosim_error(exc: BaseException, label: str) -> BaseException:
    """A worker's GeosimError as is; a lost worker or a cancelled task as an EngineError."""
    from geosim.errors import GeosimError

    if isinstance(exc, GeosimError):
        return exc
    kind = type(exc).__name__
    if kind in {"KilledWorker", "CancelledError", "CommClosedError", "FutureCancelledError"}:
        return EngineError(f"{label}: a Dask worker died or the task was lost ({kind}: "
                           f"{exc}); check the workers' memory and logs, then rerun (finished "
                           "outputs are kept)")
    return exc


# --------------------------------------------------------------------------- choosing

def default_workers() -> int:
    """The machine's cores (what ``--workers`` defaults to)."""
    return max(1, os.cpu_count() or 1)


def make_engine(workers: int | None = None, scheduler: str | None = None
                ) -> InProcess | DaskEngine:
    """The engine for ``--workers`` / ``--scheduler``.

    Parameters
    ----------
    workers
        Worker processes of a local cluster; 1 runs in this process; None = the cores.
    scheduler
        Address of an existing Dask scheduler; overrides ``workers``.
    """
    if scheduler:
        return SchedulerCluster(scheduler)
    n = default_workers() if workers is None else workers
    if n < 1:
        raise ConfigError(f"--workers {n}: give a whole number of worker processes ≥ 1")
    return InProcess() if n == 1 else LocalCluster(n)


_ACTIVE: ContextVar[Engine | None] = ContextVar("geosim_engine", default=None)


def active() -> Engine:
    """The engine tasks run on now (in-process unless :func:`using` set another)."""
    return _ACTIVE.get() or InProcess()


@contextmanager
def using(engine: Engine) -> Iterator[Engine]:
    """Make ``engine`` the active engine inside the ``with`` block."""
    token = _ACTIVE.set(engine)
    try:
        yield engine
    finally:
        _ACTIVE.reset(token)


@contextmanager
def open_engine(workers: int | None = None, scheduler: str | None = None
                ) -> Iterator[InProcess | DaskEngine]:
    """Make the engine of ``--workers`` / ``--scheduler`` active; close it on exit.

    In-process (``--workers 1``), the command's own OpenCV calls between tasks also get
    the tasks' budget (:func:`task_budget`), so that the whole command uses one
    core; GDAL's asks :func:`task_threads`, which knows the engine.
    """
    import cv2

    engine = make_engine(workers, scheduler)
    cv2_threads = cv2.getNumThreads()
    if isinstance(engine, InProcess):
        cv2.setNumThreads(task_budget())
    try:
        with using(engine):
            yield engine
    finally:
        cv2.setNumThreads(cv2_threads)
        engine.close()


def parallel_map(fn: Callable[[T], R], items: Iterable[T], *,
                 desc: str | None = None) -> list[R]:
    """Run ``fn`` on every item on the active engine; results in item order.

    ``fn`` must be a top-level function and items and results picklable; a task's
    :class:`~geosim.errors.GeosimError` reaches the caller unchanged.
    """
    return active().map(fn, items, desc=desc)


__all__: Sequence[str] = (
    "Engine", "InProcess", "DaskEngine", "LocalCluster", "SchedulerCluster", "make_engine",
    "open_engine", "using", "active", "parallel_map", "default_workers",
    "task_threads", "task_limits",
)
