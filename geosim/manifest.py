"""What each output was made from, so that a rerun skips what is still current.

Every task that finishes an output records, beside the run folder's outputs in
``DIR/.geosim/manifest/<output>.json``, a fingerprint of each input (size, mtime and
SHA-256 — or, for an input that an entry of the same run folder vouches for, the digest
of what made it, :func:`made_by`, so that a tile just written by ``geosim tile`` is not
read again only to be hashed), a digest of the parameters that determine the output (the
geosim version included) and the output's own size and mtime. On a rerun the task first
asks :func:`is_current`: the output is current when its entry exists, the output is still
the file that was recorded, every input is unchanged (same size and mtime, or, when
only the mtime moved, the same SHA-256, or the same ``made_by``: an input rewritten with
the same bytes does not invalidate its outputs; for a ``made_by`` input that means
rewritten by its own task from the same inputs and parameters, while one edited or touched
by hand counts as changed) and the parameters digest is the same.

One small file per output: tasks on different workers (or machines sharing the run
folder) record their outputs without a shared file to lock. Entries are written
atomically after their output has been renamed into place, so a run killed between the
two leaves an output without an entry, which the next run simply makes again.

Outputs that are records rather than files (e.g. one flight's calibration) use
:func:`cached` / :func:`record` with a key and keep the record in the entry.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geosim.io.atomic import write_json
from geosim.io.raster import sha256_file

#: Folder of the entries inside a run folder.
MANIFEST_DIR = Path(".geosim") / "manifest"
#: Version of the entry layout; entries of another version are not current.
FORMAT = 1

PathLike = str | os.PathLike[str]


def params_digest(params: Mapping[str, Any]) -> str:
    """SHA-256 of the parameters as canonical JSON, with the geosim version mixed in."""
    from geosim import __version__

    text = json.dumps({"geosim_version": __version__, **dict(params)}, sort_keys=True,
                      default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def _name(path: Path, out: Path) -> str:
    """``path`` relative to the run folder (POSIX) when inside it, else absolute."""
    try:
        return path.resolve().relative_to(out.resolve()).as_posix()
    except ValueError:
        return str(path.resolve())


def file_stat(path: Path) -> dict[str, int]:
    """``{"size", "mtime_ns"}`` of a file: with its path, what calls an input unchanged
    without hashing it again (here and in run.json's ``inputs``)."""
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _entry_path(out: Path, key: str) -> Path:
    if key.startswith("/") or ".." in Path(key).parts:
        key = "_abs/" + hashlib.sha256(key.encode()).hexdigest()
    return out / MANIFEST_DIR / f"{key}.json"


#: SHA-256 already computed in this process, by (path, size, mtime_ns): many outputs share
#: one large input (every tile of a flight is cut from the same aligned raster).
_SHA_MEMO: dict[tuple[str, int, int], str] = {}


def _sha256(path: Path) -> str:
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _SHA_MEMO:
        if len(_SHA_MEMO) > 4096:
            _SHA_MEMO.clear()
        _SHA_MEMO[key] = sha256_file(path)
    return _SHA_MEMO[key]


def made_by(out: Path, name: str, stat: Mapping[str, int]) -> str | None:
    """Digest of what made the run folder's file ``name``, if its own entry vouches for it.

    A file that a geosim task wrote into the run folder has an entry (under its own
    name) recording its size and mtime, the parameters digest and its inputs'
    fingerprints. While the file still has the recorded size and mtime (``stat``), the
    digest of the parameters and of the inputs' content fingerprints (size and SHA-256,
    or their own ``made_by``; not their mtimes) identifies its content: geosim's outputs
    are the same bytes for the same inputs and parameters (the version is in the
    parameters). None for a file outside the run folder, without an entry, or changed
    since it was recorded.
    """
    if name.startswith("/"):
        return None
    try:
        entry = json.loads(_entry_path(out, name).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(entry, dict) or entry.get("format") != FORMAT \
            or (entry.get("outputs") or {}).get(name) != dict(stat):
        return None
    inputs = entry.get("inputs") or {}
    ident = {"params_sha256": entry.get("params_sha256"),
             "inputs": {k: {f: v.get(f) for f in ("size", "sha256", "made_by") if f in v}
                        for k, v in inputs.items() if isinstance(v, dict)}}
    return hashlib.sha256(json.dumps(ident, sort_keys=True).encode()).hexdigest()


def vouched_for(out_dir: PathLike, path: PathLike) -> bool:
    """Whether ``path`` is still the file a geosim task of run folder ``out_dir`` wrote
    (its entry records its present size and mtime: :func:`made_by`). A file edited in place
    since, e.g. a tile whose pixels were rewritten while its overviews were not, is not."""
    out, file = Path(out_dir), Path(path)
    try:
        return made_by(out, _name(file, out), file_stat(file)) is not None
    except OSError:
        return False


def _fingerprint(path: Path, out: Path) -> dict[str, Any]:
    """Size, mtime and what identifies the content of an input: ``made_by`` for a file
    an entry of this run folder vouches for (no need to read it), else its SHA-256."""
    stat = file_stat(path)
    recipe = made_by(out, _name(path, out), stat)
    return {**stat, "made_by": recipe} if recipe is not None \
        else {**stat, "sha256": _sha256(path)}


def _input_unchanged(path: Path, recorded: Mapping[str, Any], out: Path) -> bool:
    try:
        now = file_stat(path)
    except OSError:
        return False
    if now["size"] != recorded.get("size"):
        return False
    if now["mtime_ns"] == recorded.get("mtime_ns"):
        return True
    if "made_by" in recorded:  # rewritten by its task from the same inputs and parameters
        return made_by(out, _name(path, out), now) == recorded["made_by"]
    return _sha256(path) == recorded.get("sha256")


def cached(out_dir: PathLike, key: str, inputs: Iterable[PathLike],
           params: Mapping[str, Any], outputs: Iterable[PathLike] = ()) -> dict[str, Any] | None:
    """The entry recorded under ``key`` if it is still current, else None.

    Parameters
    ----------
    out_dir
        Run folder.
    key
        Name of the output (for a file: its path relative to ``out_dir``).
    inputs
        Files the output is made from.
    params
        Everything else that determines the output (JSON-serialisable).
    outputs
        Files the task wrote; each must still be the file that was recorded.

    Returns
    -------
    dict or None
        The entry (its ``"result"`` holds what :func:`record` was given).
    """
    out = Path(out_dir)
    try:
        entry = json.loads(_entry_path(out, key).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(entry, dict) or entry.get("format") != FORMAT \
            or entry.get("params_sha256") != params_digest(params):
        return None
    inputs, outputs = [Path(p) for p in inputs], [Path(p) for p in outputs]
    recorded_in = entry.get("inputs") or {}
    recorded_out = entry.get("outputs") or {}
    if {_name(p, out) for p in inputs} != set(recorded_in) \
            or {_name(p, out) for p in outputs} != set(recorded_out):
        return None
    for p in outputs:
        try:
            if file_stat(p) != recorded_out[_name(p, out)]:
                return None
        except OSError:
            return None
    if not all(_input_unchanged(p, recorded_in[_name(p, out)], out) for p in inputs):
        return None
    return entry


def record(out_dir: PathLike, key: str, inputs: Iterable[PathLike], params: Mapping[str, Any],
           outputs: Iterable[PathLike] = (), result: Any = None) -> None:
    """Record that ``key`` was made from ``inputs`` with ``params`` (after writing it).

    ``result`` (JSON-serialisable) is kept in the entry for outputs that are records.
    """
    out = Path(out_dir)
    entry = {
        "format": FORMAT,
        "key": key,
        "params_sha256": params_digest(params),
        "inputs": {_name(Path(p), out): _fingerprint(Path(p), out) for p in inputs},
        "outputs": {_name(Path(p), out): file_stat(Path(p)) for p in outputs},
        "result": result,
    }
    write_json(_entry_path(out, key), entry)


def is_current(out_dir: PathLike, output: PathLike, inputs: Iterable[PathLike],
               params: Mapping[str, Any]) -> bool:
    """Whether the file ``output`` was made from these unchanged ``inputs`` and ``params``."""
    output = Path(output)
    return cached(out_dir, _name(output, Path(out_dir)), inputs, params,
                  outputs=[output]) is not None


def record_output(out_dir: PathLike, output: PathLike, inputs: Iterable[PathLike],
                  params: Mapping[str, Any]) -> None:
    """:func:`record` for the file ``output`` (call it once the file is in place)."""
    output = Path(output)
    record(out_dir, _name(output, Path(out_dir)), inputs, params, outputs=[output])


def skip_text(skipped: int, total: int) -> str:
    """``"; 3 of 12 current, skipped"`` for a step summary (empty when none was skipped)."""
    return f"; {skipped} of {total} already current, skipped" if skipped else ""


@dataclass(frozen=True)
class ResumableTask:
    """An engine task made resumable: ``fn(task)`` writes ``output`` from ``inputs``.

    The parameters are the task itself: a digest of its pickle (every field: paths, grids,
    warps, tags), so any change to what the task would do makes the output not current.
    ``fn`` must be a top-level function and ``task`` picklable (as for any engine task).
    """

    run_dir: str
    fn: Callable[[Any], Any]
    task: Any
    output: str
    inputs: tuple[str, ...]


def run_resumable(job: ResumableTask) -> bool:
    """Run ``job.fn(job.task)`` unless its output is current; True when it was skipped."""
    params = {"task": getattr(job.fn, "__qualname__", str(job.fn)),
              "task_pickle_sha256": hashlib.sha256(pickle.dumps(job.task, protocol=4)).hexdigest()}
    if is_current(job.run_dir, job.output, job.inputs, params):
        return True
    job.fn(job.task)
    record_output(job.run_dir, job.output, job.inputs, params)
    return False
