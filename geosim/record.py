"""run.json for commands that do not run pipeline steps (augment, cattle-per-paddock,
movement, overlay-check).

:func:`command_record` runs a command's body inside the pipeline's bounded GDAL
environment and records it with the same top-level schema as
:func:`geosim.pipeline.run_pipeline` (docs/outputs.md, "run.json"): ``status``
``running`` → ``ok`` / ``failed`` / ``interrupted``, the inputs with their SHA-256, the
command's options, the engine, and one ``steps.<command>`` record with its summary text
and the files it wrote (relative to the record's folder).

Where the record goes: ``<out>/run.json`` when the command's output is a folder, and
``<file>.run.json`` beside it when the output is one file (``cattle-per-paddock --out
counts.csv``, ``augment --plot-warp --out warp.png``). A folder whose run.json was
written by another command (a site's run folder, for ``overlay-check SITE_FILE``) keeps
its record: this command's step record is added to its ``steps`` and the top-level
fields (status, site, inputs) stay those of the pipeline run.
"""

from __future__ import annotations

import contextlib
import platform
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geosim import __version__, engine
from geosim.io.atomic import recording_outputs, to_jsonable, write_json
from geosim.pipeline import (
    GDAL_CACHE_MB,
    _now,
    _read_record,
    _sigterm_raises,
    file_checksums,
    gdal_environment,
)


@dataclass
class CommandRun:
    """What the command body reports back: its summary line and files written elsewhere."""

    summary: str = ""
    outputs: list[Path] = field(default_factory=list)


def record_path(out: Path, *, folder: bool) -> Path:
    """Where a command writing to ``out`` records itself: ``out/run.json`` for a folder,
    ``out.run.json`` beside a single output file."""
    return out / "run.json" if folder else out.with_name(out.name + ".run.json")


@contextlib.contextmanager
def command_record(command: str, run_json: Path, *, inputs: Mapping[str, Path | None],
                   options: Mapping[str, Any]) -> Iterator[CommandRun]:
    """Run the ``with`` body as ``command`` and keep ``run_json`` current.

    Parameters
    ----------
    command
        Command name, the key of its step record (``steps.<command>``).
    run_json
        The record to write (:func:`record_path`); its folder is created.
    inputs
        Input files (or folders) by name; their SHA-256 is recorded before the body runs.
    options
        The command's options, recorded as given.

    Yields
    ------
    CommandRun
        Set ``summary`` (one line) in the body; files written atomically
        (:mod:`geosim.io.atomic`) inside the body are recorded as outputs.
    """
    root = run_json.parent
    root.mkdir(parents=True, exist_ok=True)
    previous = _read_record(run_json)
    host = previous if previous and previous.get("command") != command else None
    opts = to_jsonable(dict(options))
    record: dict[str, Any] = host if host is not None else {
        "geosim_version": __version__, "started": _now(), "python": platform.python_version(),
        "status": "running", "command": command, "options": opts,
        "inputs": file_checksums(inputs), "steps": {}, "gdal_cache_mb": GDAL_CACHE_MB,
        "engine": engine.active().describe()}
    steps = record.setdefault("steps", {})
    steps[command] = {"status": "running", "options": opts, "outputs": []}
    if host is not None:
        steps[command]["inputs"] = file_checksums(inputs)
    write_json(run_json, record)
    run = CommandRun()
    start = time.perf_counter()
    status, error = "ok", None
    with recording_outputs() as written:
        try:
            with gdal_environment(), _sigterm_raises():
                yield run
        except BaseException as exc:
            status = "failed" if isinstance(exc, Exception) else "interrupted"
            error = str(exc) or type(exc).__name__
            raise
        finally:
            _finish(record, command, run_json, run, written, status, error, start,
                    top=host is None)


def _finish(record: dict[str, Any], command: str, run_json: Path, run: CommandRun,
            written: list[Path], status: str, error: str | None, start: float, *,
            top: bool) -> None:
    """Write the final step record (and top-level status unless hosted)."""
    seconds = round(time.perf_counter() - start, 3)
    root = run_json.parent.resolve()
    outputs = set()
    for p in [*written, *run.outputs]:
        p = Path(p).resolve()
        if p.is_file() and p != run_json.resolve():
            outputs.add(str(p.relative_to(root)) if p.is_relative_to(root) else str(p))
    step = {**record["steps"][command], "status": status, "seconds": seconds,
            "outputs": sorted(outputs)}
    if error is not None:
        step["error"] = error
    else:
        step["summary"] = {"text": run.summary}
    record["steps"][command] = step
    if top:
        record.update(status=status, engine=engine.active().describe(), seconds=seconds,
                      finished=_now())
    write_json(run_json, record)
