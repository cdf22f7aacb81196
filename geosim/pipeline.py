"""The pipeline runner: every command runs its steps here and records them in run.json.

Each step is a library function ``run_<step>(site, out, **options) -> StepResult``
(:class:`geosim.result.StepResult`) that reads earlier steps' outputs through a
:class:`geosim.rundir.RunDir` and writes its own atomically. :func:`run_pipeline`
runs the selected steps inside one bounded GDAL environment and keeps ``run.json``
honest (docs/outputs.md, "run.json"):

* written at the start (``"status": "running"``, the parameters and the inputs with
  their SHA-256 checksums) and again after every step;
* a step that raises is recorded ``failed``; Ctrl-C or SIGTERM is recorded
  ``interrupted``, never ``ok``;
* temporary files a killed run left (:data:`geosim.rundir.TEMP_NAME`) are removed at
  the start;
* when the site (parameters, flights, satellite, anchor) differs from the one
  recorded, the outputs the earlier run recorded for the steps from the first step
  run now onwards are removed before work starts, so the folder never mixes the two;
  after each step, outputs it recorded last time but did not write this time are
  removed. Only files listed as outputs in run.json are ever removed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import importlib
import json
import platform
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rasterio

from geosim import __version__, engine
from geosim.config import SiteConfig
from geosim.errors import ConfigError
from geosim.io.atomic import recording_outputs, to_jsonable, write_json
from geosim.io.raster import sha256_file
from geosim.log import get_logger
from geosim.log import info as log_info
from geosim.manifest import file_stat
from geosim.result import StepResult
from geosim.rundir import RunDir
from geosim.validate import check_out_dir, preflight

#: GDAL block cache of every run, MB (GDAL's default is 5 % of RAM): bounds memory; the
#: same cache in the driver as in a worker (:data:`geosim.engine.WORKER_GDAL_CACHEMAX_MB`).
GDAL_CACHE_MB = engine.WORKER_GDAL_CACHEMAX_MB


def gdal_environment() -> rasterio.Env:
    """The bounded GDAL environment every command runs in: a :data:`GDAL_CACHE_MB` block cache.

    ``rasterio.Env`` hands an integer ``GDAL_CACHEMAX`` to ``GDALSetCacheMax64``, which
    takes **bytes** (the environment variable of the same name means MB below 100 000):
    ``GDAL_CACHEMAX=256`` left GDAL a 256-byte cache, so every in-process task (``--workers
    1``) ran without one, and the tiles step's tasks cost ≈ 45 % more CPU than on a Dask
    worker, whose environment variable gives 256 MB (docs/scale.md). The special case is
    rasterio's (rasterio/rasterio#1042; the same trap: rasterio/rasterio#2336).
    """
    return rasterio.Env(GDAL_CACHEMAX=GDAL_CACHE_MB * 2**20)


StepFunction = Callable[..., StepResult]


@dataclass(frozen=True)
class Step:
    """One pipeline step: its name, where its function lives, what it needs."""

    name: str
    module: str
    function: str
    needs_satellite: bool = False
    description: str = ""

    def load(self) -> StepFunction:
        """Import the step function."""
        return getattr(importlib.import_module(self.module), self.function)


STEPS: tuple[Step, ...] = (
    Step("grid", "geosim.prepare.steps", "run_grid",
         description="reproject flights and satellite onto the shared grid"),
    Step("footprints", "geosim.prepare.steps", "run_footprints",
         description="trace valid-data footprints and the common extent"),
    Step("align", "geosim.prepare.steps", "run_align",
         description="register flights to the reference (Fourier–Mellin)"),
    Step("tiles", "geosim.prepare.steps", "run_tiles", description="cut aligned tiles"),
    Step("pairs", "geosim.prepare.steps", "run_pairs", description="list patch pairs"),
    Step("labels", "geosim.labels.steps", "run_labels",
         description="cattle labels in map coordinates and per tile"),
    Step("calibrate", "geosim.degrade.steps", "run_calibrate", needs_satellite=True,
         description="calibrate Q by Laplacian variance against the satellite"),
    Step("degrade", "geosim.degrade.steps", "run_degrade",
         description="degrade tiles to the 0.5 m satellite grid"),
    Step("diagnose", "geosim.diagnose.steps", "run_diagnose", needs_satellite=True,
         description="locate and explain the simulation–satellite mismatch"),
    Step("deliver", "geosim.deliver.steps", "run_deliver",
         description="VRT mosaics, STAC catalogue, YOLO datasets, QGIS project"),
)
STEP_NAMES: tuple[str, ...] = tuple(s.name for s in STEPS)
#: Steps of commands that work on images rather than a site's run folder (not part of
#: ``geosim run``), run and recorded the same way.
STANDALONE_STEPS: tuple[Step, ...] = (
    Step("diagnose_images", "geosim.diagnose.steps", "run_diagnose_images",
         needs_satellite=True,
         description="diagnose UAV images against a satellite scene (standalone)"),
)


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived during a run (raised so that run.json records the interruption)."""


def input_checksums(site: SiteConfig, known: Mapping[str, Any] | None = None
                    ) -> dict[str, dict[str, Any]]:
    """SHA-256 of every input file (for a folder of labels: of each file in it); ``known``:
    an earlier record's entries, reused for files whose path, size and mtime are the same
    (:func:`file_checksums`)."""
    paths: dict[str, Path | None] = {"site": site.path}
    for f in site.flights:
        paths[f"flights.{f.id}.image"] = f.image
        paths[f"flights.{f.id}.labels"] = f.labels
    paths["satellite.image"] = site.satellite.image if site.satellite is not None else None
    paths["paddocks"] = site.paddocks
    return file_checksums(paths, known)


def file_checksums(paths: Mapping[str, Path | None], known: Mapping[str, Any] | None = None
                   ) -> dict[str, dict[str, Any]]:
    """``{key: {"path", "sha256", "size", "mtime_ns"}}`` of each given input file; a folder
    gives one entry per file directly in it (``key.<name>``); ``None`` and missing paths are
    left out.

    ``known`` (the ``inputs`` of an earlier run.json) saves hashing again a file whose
    entry there has the same path, size and modification time (ns), the rule the manifest
    uses to call an input unchanged (:mod:`geosim.manifest`): a 20000² px flight takes
    about a second to hash, on every command that names it.
    """
    files: dict[str, Path] = {}
    for key, p in paths.items():
        if p is None:
            continue
        if p.is_dir():
            files.update({f"{key}.{f.name}": f for f in sorted(p.iterdir()) if f.is_file()})
        elif p.is_file():
            files[key] = p
    out: dict[str, dict[str, Any]] = {}
    for k, p in files.items():
        entry: dict[str, Any] = {"path": str(p), **file_stat(p)}
        old = (known or {}).get(k)
        if (isinstance(old, dict) and isinstance(old.get("sha256"), str)
                and all(old.get(f) == v for f, v in entry.items())):
            out[k] = {**entry, "sha256": old["sha256"]}
        else:
            out[k] = {**entry, "sha256": sha256_file(p)}
    return out


def select_steps(only: Sequence[str] | None = None) -> list[Step]:
    """The steps to run, in pipeline order; ConfigError for an unknown step name."""
    if not only:
        return list(STEPS)
    known = (*STEPS, *STANDALONE_STEPS)
    unknown = [s for s in only if s not in {k.name for k in known}]
    if unknown:
        raise ConfigError(f"unknown step {unknown[0]!r}; steps are: {', '.join(STEP_NAMES)}")
    return [s for s in known if s.name in only]


def run_pipeline(site: SiteConfig, out_dir: str | Path | RunDir, *,
                 only: Sequence[str] | None = None,
                 options: Mapping[str, Mapping[str, Any]] | None = None,
                 echo: Callable[[str], None] = log_info) -> dict[str, Any]:
    """Run pipeline steps on a site and keep ``out_dir/run.json`` current.

    Parameters
    ----------
    site
        A validated site (:func:`geosim.config.load_site`).
    out_dir
        Run folder (created if needed).
    only
        Names of the steps to run (default: all, in order). Records of the other
        steps from an earlier run in the folder are kept (``"from_earlier_run": true``).
    options
        Keyword options per step name (e.g. ``{"degrade": {"q": 4.34}}``), passed to
        the step function and recorded in its step record.
    echo
        Where progress lines and warnings go (default: INFO messages of the ``geosim``
        logger).

    Returns
    -------
    dict
        The content of run.json. A failing or interrupted step is recorded there
        (status ``failed`` / ``interrupted``) before its exception propagates.
    """
    run = RunDir.of(out_dir)
    steps = select_steps(only)
    options = {k: dict(v) for k, v in (options or {}).items()}
    _preflight(site, run, steps, options)  # refuses before anything is written
    run.root.mkdir(parents=True, exist_ok=True)
    previous = _merge_journal(run, _read_record(run.run_json))
    site_doc = to_jsonable(site.to_dict())
    record: dict[str, Any] = {
        "geosim_version": __version__,
        "started": _now(),
        "python": platform.python_version(),
        "status": "running",
        "site": site_doc,
        "inputs": input_checksums(site, previous.get("inputs")),
        "steps": _earlier_steps(previous) if only else {},
        "gdal_cache_mb": GDAL_CACHE_MB,
    }
    record["engine"] = engine.active().describe()
    record["cleaned"] = _clean_before(run, previous, site_doc, steps, record)
    write_json(run.run_json, record)
    earlier = {name: [p for p in paths if (run.root / p).is_file()]
               for name, paths in _outputs_by_step(previous).items()}
    start = time.perf_counter()
    try:
        with gdal_environment(), _sigterm_raises():
            for i, step in enumerate(steps, start=1):
                if step.needs_satellite and site.satellite is None:
                    record["steps"][step.name] = {"status": "skipped",
                                                  "reason": "no satellite scene"}
                    echo(f"[{i}/{len(steps)}] {step.name}: skipped (the site has no "
                         "satellite scene)")
                    continue
                echo(f"[{i}/{len(steps)}] {step.name}: {step.description}")
                step_record = _run_step(step, site, run, to_jsonable(options.get(step.name, {})),
                                        record, earlier.get(step.name, []))
                for warning in step_record["warnings"]:
                    get_logger().warning(f"      warning: {warning}")
                echo(f"      done in {step_record['seconds']:.1f} s")
    except BaseException as exc:
        _finish(run, record, "failed" if isinstance(exc, Exception) else "interrupted", start)
        raise
    _finish(run, record, "ok", start)
    return record


def _preflight(site: SiteConfig, run: RunDir, steps: list[Step],
               options: dict[str, dict[str, Any]]) -> None:
    """:func:`geosim.validate.preflight` for these steps (with a ``degrade --q`` counted as
    the site's Q); for standalone steps only the run-folder check (their images need not
    overlap each other)."""
    if all(s in STANDALONE_STEPS for s in steps):
        check_out_dir(site, run.root)
        return
    q = options.get("degrade", {}).get("q")
    if q is not None and site.parameters.q is None:
        site = dataclasses.replace(site, parameters=dataclasses.replace(site.parameters, q=q))
    preflight(site, run.root, [s.name for s in steps])


def _run_step(step: Step, site: SiteConfig, run: RunDir, opts: dict[str, Any],
              record: dict[str, Any], earlier: list[str]) -> dict[str, Any]:
    """Run one step, record it in ``record["steps"]`` and run.json; returns its record.

    On an exception the step is recorded ``failed`` (``interrupted`` for Ctrl-C or
    SIGTERM) with the outputs it completed, and the exception propagates.
    """
    # until it ends, the step's outputs are those an earlier run recorded (still there)
    record["steps"][step.name] = {"status": "running", "options": opts, "outputs": earlier}
    write_json(run.run_json, _ordered(record))
    start = time.perf_counter()
    with recording_outputs(run.output_journal, tag=step.name) as written:
        try:
            result = step.load()(site, run, **opts)
            if not isinstance(result, StepResult):
                raise TypeError(f"step {step.name} returned {type(result).__name__}, "
                                "not a StepResult")
        except BaseException as exc:
            # keep what it completed and what an earlier run recorded, so that a later
            # run can still find (and remove) them
            done = _relative_existing(run, written)
            record["steps"][step.name] = {
                "status": "failed" if isinstance(exc, Exception) else "interrupted",
                "error": str(exc) or type(exc).__name__,
                "seconds": round(time.perf_counter() - start, 3), "options": opts,
                "outputs": sorted(set(done) | set(earlier))}
            raise
    outputs = sorted(set(result.outputs) | set(_relative_existing(run, written)))
    step_record: dict[str, Any] = {
        "status": "ok", "seconds": round(time.perf_counter() - start, 3),
        "summary": to_jsonable(result.summary_record()), "warnings": list(result.warnings),
        "outputs": outputs, "options": opts}
    removed = run.remove_outputs(sorted(set(earlier) - set(outputs)))
    if removed:
        step_record["removed_stale_outputs"] = removed
    record["steps"][step.name] = step_record
    write_json(run.run_json, _ordered(record))
    return step_record


def _relative_existing(run: RunDir, paths: list[Path]) -> list[str]:
    """Those of ``paths`` that exist inside the run folder, relative to it."""
    rel = (run.rel(p) for p in paths if p.is_file())
    return [r for r in rel if not Path(r).is_absolute()]


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def _ordered(record: dict[str, Any]) -> dict[str, Any]:
    """Step records in pipeline order (standalone steps after)."""
    steps = record["steps"]
    order = [n for n in STEP_NAMES if n in steps] + [n for n in steps if n not in STEP_NAMES]
    record["steps"] = {name: steps[name] for name in order}
    return record


def _finish(run: RunDir, record: dict[str, Any], status: str, start: float) -> None:
    record["status"] = status
    record["engine"] = engine.active().describe()  # now with the workers that ran tasks
    record["seconds"] = round(time.perf_counter() - start, 3)
    record["finished"] = _now()
    write_json(run.run_json, _ordered(record))
    run.output_journal.unlink(missing_ok=True)  # run.json holds it all now


@contextlib.contextmanager
def _sigterm_raises() -> Iterator[None]:
    """Turn SIGTERM into :class:`Terminated` while the steps run (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: Any) -> None:
        raise Terminated(f"terminated by signal {signum}")

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def _read_record(run_json: Path) -> dict[str, Any]:
    """An earlier run.json, or {} when absent or unreadable (the new one replaces it)."""
    try:
        doc = json.loads(run_json.read_text())
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _merge_journal(run: RunDir, previous: dict[str, Any]) -> dict[str, Any]:
    """Add the outputs listed in a killed run's journal to its record's steps.

    A run killed with SIGKILL (or a power cut) leaves ``run.json`` saying ``running`` and
    the journal of the files it completed; with them in the record, this run can remove
    them like any recorded output.
    """
    journal = run.output_journal
    if not journal.is_file():
        return previous
    steps = previous.get("steps")
    if not isinstance(steps, dict):
        steps = previous["steps"] = {}
    for line in journal.read_text(encoding="utf-8", errors="replace").splitlines():
        name, _, path = line.partition("\t")
        rel = run.rel(path)
        info = steps.setdefault(name, {"status": "running"})
        if not path or Path(rel).is_absolute() or not isinstance(info, dict):
            continue
        outputs = info.setdefault("outputs", [])
        if rel not in outputs:
            outputs.append(rel)
    journal.unlink()
    return previous


def _earlier_steps(previous: dict[str, Any]) -> dict[str, Any]:
    """Step records of an earlier run in the same folder, kept when only some steps rerun.

    Each kept record is marked ``"from_earlier_run": true``.
    """
    steps = previous.get("steps")
    if not isinstance(steps, dict):
        return {}
    return {name: {**info, "from_earlier_run": True} for name, info in steps.items()
            if isinstance(info, dict)}


def _outputs_by_step(previous: dict[str, Any]) -> dict[str, list[str]]:
    steps = previous.get("steps")
    if not isinstance(steps, dict):
        return {}
    return {name: [p for p in info.get("outputs", []) if isinstance(p, str)]
            for name, info in steps.items() if isinstance(info, dict)}


def _clean_before(run: RunDir, previous: dict[str, Any], site_doc: dict[str, Any],
                  steps: list[Step], record: dict[str, Any]) -> dict[str, Any]:
    """Remove a killed run's temp files, and an earlier run's outputs the new site invalidates.

    When the site differs from the one recorded in run.json, every output recorded for
    the steps from the first one run now onwards (pipeline order) is removed and those
    steps' earlier records are dropped: they were made with the old parameters.
    """
    cleaned: dict[str, Any] = {"temp_files": run.clean_leftovers()}
    old_site = previous.get("site")
    if old_site is None or old_site == site_doc or not steps:
        return cleaned
    if steps[0].name in STEP_NAMES:
        invalid = STEP_NAMES[STEP_NAMES.index(steps[0].name):]
    else:  # a standalone step: only its own earlier outputs
        invalid = tuple(s.name for s in steps)
    by_step = _outputs_by_step(previous)
    removed: list[str] = []
    for name in invalid:
        removed += run.remove_outputs(by_step.get(name, []))
        record["steps"].pop(name, None)
    changed = sorted(k for k in set(old_site) | set(site_doc)
                     if old_site.get(k) != site_doc.get(k))
    cleaned["site_changed"] = changed
    cleaned["stale_outputs"] = removed
    return cleaned


def format_summary(record: dict[str, Any]) -> str:
    """A short human summary of a run record: what was written and the key numbers."""
    lines = [f"geosim {record['geosim_version']}: {record['status']} in "
             f"{record.get('seconds', 0):.1f} s"]
    for name, info in record["steps"].items():
        if info.get("from_earlier_run"):
            continue  # only what this invocation did
        if info["status"] != "ok":
            lines.append(f"  {name:<11} {info['status']}: "
                         f"{info.get('reason') or info.get('error', '')}")
            continue
        text = (info.get("summary") or {}).get("text", "")
        lines.append(f"  {name:<11} {info['seconds']:6.1f} s  {text}")
    return "\n".join(lines)
