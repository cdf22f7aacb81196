"""Several flights diagnosed against one satellite scene: each on its own (an engine task,
resumable from the run's manifest) into its own folder, then the combined verdict
(:func:`~geosim.diagnose.report.write_combined`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geosim.diagnose.grids import MAX_SAT_PX, FlightPixels, diagnose_grids
from geosim.diagnose.report_figures import DEFAULT_DPI
from geosim.engine import parallel_map
from geosim.errors import DiagnosisError, ExtentError
from geosim.io.atomic import to_jsonable
from geosim.io.paths import safe_name, unique_name

__all__ = ["DiagnoseFlightTask", "diagnose_flight_task", "diagnosis_was_current",
           "diagnose_flights", "recorded_files"]


#: ``why`` of a diagnosis reused from the manifest (the dict is returned with it).
_CURRENT = "already current"


def _flight_dir(flight: str, taken: set[str]) -> str:
    """A folder name for a flight id (safe characters only, unique)."""
    name = unique_name(safe_name(flight, default="flight"), taken | {"diagnosis"})
    taken.add(name)
    return name


@dataclass(frozen=True)
class DiagnoseFlightTask:
    """One flight to diagnose: ``load()`` reads its :class:`FlightPixels` (picklable)."""

    flight: str
    load: Callable[[], FlightPixels]
    out_dir: Path
    phi: int
    seed: int
    q_min: float
    q_max: float
    dpi: int = DEFAULT_DPI
    #: Resumable when set: (run folder, the files ``load`` reads) — a rerun with the same
    #: inputs and parameters reuses the flight's diagnosis instead of making it again.
    resume: tuple[Path, tuple[Path, ...]] | None = None


def _diagnose_one(task: DiagnoseFlightTask) -> tuple[dict[str, Any] | None, str | None]:
    try:
        doc = diagnose_grids(task.load(), task.out_dir, phi=task.phi, seed=task.seed,
                             q_min=task.q_min, q_max=task.q_max,
                             extra={"flight": task.flight}, dpi=task.dpi)
    except (DiagnosisError, ExtentError) as exc:
        return None, str(exc)
    # through JSON (NaN kept), so that a fresh and a reused diagnosis are the same values
    return to_jsonable(doc), None


def diagnose_flight_task(task: DiagnoseFlightTask) -> tuple[dict[str, Any] | None, str | None]:
    """Diagnose one flight into ``task.out_dir``: (diagnosis.json dict, None), or
    (None, why) when it cannot be diagnosed (too little overlap, no usable data).

    With ``task.resume`` the flight's diagnosis is skipped when its manifest entry is
    current (same input files, parameters and output files); the dict then comes from
    the entry (``"skipped": true`` is not added: callers count skips with
    :func:`diagnosis_was_current`).
    """
    if task.resume is None:
        return _diagnose_one(task)
    from geosim import manifest

    run_dir, inputs = task.resume
    key = f"diagnosis/{task.out_dir.name}/flight"
    params = {"step": "diagnose", "flight": task.flight, "phi": task.phi, "seed": task.seed,
              "q_min": task.q_min, "q_max": task.q_max, "dpi": task.dpi,
              "dir": task.out_dir.name, "max_sat_px": MAX_SAT_PX}
    recorded = recorded_files(run_dir, key)
    entry = manifest.cached(run_dir, key, inputs, params, outputs=recorded)
    if entry is not None and recorded and isinstance(entry.get("result"), dict):
        return entry["result"], _CURRENT
    doc, why = _diagnose_one(task)
    if doc is not None:
        outputs = sorted(p for p in task.out_dir.rglob("*") if p.is_file())
        manifest.record(run_dir, key, inputs, params, outputs=outputs, result=doc)
    return doc, why


def diagnosis_was_current(result: tuple[dict[str, Any] | None, str | None]) -> bool:
    """Whether :func:`diagnose_flight_task` reused a current diagnosis."""
    return result[0] is not None and result[1] == _CURRENT


def recorded_files(run_dir: Path, key: str) -> list[Path]:
    """The output files a manifest entry lists (to check they are still those files)."""
    from geosim import manifest

    try:
        entry = json.loads((Path(run_dir) / manifest.MANIFEST_DIR / f"{key}.json").read_text())
        return [Path(run_dir) / rel for rel in entry["outputs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def diagnose_flights(loaders: list[tuple[str, Callable[[], FlightPixels]]], out_dir: Path, *,
                     reference: str | None, phi: int, seed: int = 0, q_min: float = 0.5,
                     q_max: float = 8.0, dpi: int = DEFAULT_DPI,
                     resume: dict[str, tuple[Path, tuple[Path, ...]]] | None = None,
                     counts: dict[str, int] | None = None) -> dict[str, Any]:
    """Diagnose several flights one at a time and write the combined verdict.

    Parameters
    ----------
    loaders
        (flight id, load) pairs in site order; ``load()`` returns the flight's
        :class:`FlightPixels`, or raises :class:`~geosim.errors.DiagnosisError` /
        ``ExtentError`` when the flight cannot be diagnosed (it is then skipped, with the
        reason in ``flights_skipped``).
    reference
        The flight whose GeoTIFFs, maps and plots are copied to the top level (default,
        or when it was skipped: the first diagnosed flight).
    resume
        Per flight, (run folder, the files its ``load`` reads): its diagnosis is reused
        when current (:func:`diagnose_flight_task`).
    counts
        Filled with ``skipped_current``: flights whose diagnosis was reused.

    Returns
    -------
    dict
        The combined diagnosis.json dict.
    """
    from geosim.diagnose.report import write_combined

    per: dict[str, dict[str, Any]] = {}
    dirs: dict[str, str] = {}
    skipped: dict[str, str] = {}
    taken: set[str] = set()
    tasks = [DiagnoseFlightTask(fid, load, out_dir / _flight_dir(fid, taken), phi=phi,
                                seed=seed + 1000 * i, q_min=q_min, q_max=q_max, dpi=dpi,
                                resume=(resume or {}).get(fid))
             for i, (fid, load) in enumerate(loaders)]
    results = parallel_map(diagnose_flight_task, tasks, desc="diagnose flights")
    if counts is not None:
        counts["skipped_current"] = sum(map(diagnosis_was_current, results))
    for task, (doc, why) in zip(tasks, results, strict=True):
        if doc is None:
            skipped[task.flight] = why or ""
        else:
            per[task.flight], dirs[task.flight] = doc, task.out_dir.name
    if not per:
        raise DiagnosisError(f"{out_dir}: no flight could be diagnosed against the satellite "
                             "scene (" + "; ".join(f"{k}: {v}" for k, v in skipped.items())
                             + "); give flights that overlap the satellite scene")
    ref = reference if reference in per else next(iter(per))
    return write_combined(per, out_dir, reference=ref, dirs=dirs, skipped=skipped, dpi=dpi)
