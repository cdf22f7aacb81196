"""The whole pipeline: runs each step in order and records what it did in run.json.

Each step is a library function ``run_<step>(site, out_dir) -> dict`` that reads
earlier steps' outputs from ``out_dir`` and writes its own atomically; the
summary dicts it returns go into ``run.json`` together with the geosim version,
the parameters, the inputs with their SHA-256 checksums and each step's timing.
"""

from __future__ import annotations

import datetime as dt
import importlib
import json
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geosim import __version__
from geosim.config import SiteConfig
from geosim.errors import ConfigError
from geosim.io.atomic import write_json
from geosim.io.raster import sha256_file
from geosim.log import info as log_info
from geosim.validate import preflight


@dataclass(frozen=True)
class Step:
    """One pipeline step: its name, where its function lives, what it needs."""

    name: str
    module: str
    function: str
    needs_satellite: bool = False
    description: str = ""

    def load(self) -> Callable[[SiteConfig, Path], dict[str, Any]]:
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


def input_checksums(site: SiteConfig) -> dict[str, dict[str, str]]:
    """SHA-256 of every input file (for a folder of labels: of each file in it)."""
    files: dict[str, Path] = {}
    if site.path is not None:
        files["site"] = site.path
    for f in site.flights:
        files[f"flights.{f.id}.image"] = f.image
        if f.labels is not None:
            if f.labels.is_dir():
                for p in sorted(f.labels.iterdir()):
                    if p.is_file():
                        files[f"flights.{f.id}.labels.{p.name}"] = p
            else:
                files[f"flights.{f.id}.labels"] = f.labels
    if site.satellite is not None:
        files["satellite.image"] = site.satellite.image
    if site.paddocks is not None:
        files["paddocks"] = site.paddocks
    return {k: {"path": str(p), "sha256": sha256_file(p)} for k, p in files.items()}


def select_steps(only: Sequence[str] | None = None) -> list[Step]:
    """The steps to run, in pipeline order; ConfigError for an unknown step name."""
    if not only:
        return list(STEPS)
    unknown = [s for s in only if s not in STEP_NAMES]
    if unknown:
        raise ConfigError(f"unknown step {unknown[0]!r}; steps are: {', '.join(STEP_NAMES)}")
    return [s for s in STEPS if s.name in only]


def run_pipeline(site: SiteConfig, out_dir: str | Path, *, only: Sequence[str] | None = None,
                 echo: Callable[[str], None] = log_info) -> dict[str, Any]:
    """Run the pipeline steps on a site and write ``out_dir/run.json``.

    Parameters
    ----------
    site
        A validated site (:func:`geosim.config.load_site`).
    out_dir
        Output folder (created if needed).
    only
        Names of the steps to run (default: all, in order).
    echo
        Where progress lines go (default: INFO messages of the ``geosim`` logger).

    Returns
    -------
    dict
        The content of run.json. A failing step is recorded there (status
        ``failed`` and the message) before its exception propagates.
    """
    out = Path(out_dir)
    steps = select_steps(only)
    preflight(site, out, [s.name for s in steps])  # refuses before anything is written
    out.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {
        "geosim_version": __version__,
        "started": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "site": site.to_dict(),
        "inputs": input_checksums(site),
        "steps": _earlier_steps(out / "run.json") if only else {},
        "status": "running",
    }
    total_start = time.perf_counter()
    for i, step in enumerate(steps, start=1):
        if step.needs_satellite and site.satellite is None:
            record["steps"][step.name] = {"status": "skipped", "reason": "no satellite scene"}
            echo(f"[{i}/{len(steps)}] {step.name}: skipped (the site has no satellite scene)")
            continue
        echo(f"[{i}/{len(steps)}] {step.name}: {step.description}")
        start = time.perf_counter()
        try:
            summary = step.load()(site, out)
        except Exception as exc:
            record["steps"][step.name] = {"status": "failed", "error": str(exc),
                                          "seconds": round(time.perf_counter() - start, 3)}
            record["status"] = "failed"
            record["seconds"] = round(time.perf_counter() - total_start, 3)
            write_json(out / "run.json", record)
            raise
        seconds = time.perf_counter() - start
        record["steps"][step.name] = {"status": "ok", "seconds": round(seconds, 3),
                                      "summary": summary}
        echo(f"      done in {seconds:.1f} s")
    record["steps"] = {name: record["steps"][name] for name in STEP_NAMES
                       if name in record["steps"]}
    record["status"] = "ok"
    record["seconds"] = round(time.perf_counter() - total_start, 3)
    record["finished"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    write_json(out / "run.json", record)
    return record


def _earlier_steps(run_json: Path) -> dict[str, Any]:
    """Step records of an earlier run in the same folder, kept when only some steps rerun.

    Each kept record is marked ``"from_earlier_run": true``; an unreadable file is ignored
    (the new run.json replaces it).
    """
    try:
        earlier = json.loads(run_json.read_text())
    except (OSError, ValueError):
        return {}
    steps = earlier.get("steps") if isinstance(earlier, dict) else None
    if not isinstance(steps, dict):
        return {}
    return {name: {**info, "from_earlier_run": True} for name, info in steps.items()
            if name in STEP_NAMES and isinstance(info, dict)}


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
        summary = info.get("summary") or {}
        text = summary.get("text") if isinstance(summary, dict) else None
        if not text:
            keys = [f"{k}={v}" for k, v in summary.items()
                    if isinstance(v, (int, float, str)) and len(str(v)) < 60][:6]
            text = ", ".join(keys)
        lines.append(f"  {name:<11} {info['seconds']:6.1f} s  {text}")
    return "\n".join(lines)
