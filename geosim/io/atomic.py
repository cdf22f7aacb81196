"""Write to a temporary name beside the target, rename on success.

A killed or failed run therefore never leaves a half-written output under the
final name, and an existing output is replaced in one step.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from geosim.errors import GeosimError, OutputError

#: While :func:`recording_outputs` is active: the list of final paths written by
#: :func:`atomic_path`, the journal file they are also appended to, and its tag.
_JOURNAL: ContextVar[tuple[list[Path], Path | None, str] | None] = ContextVar(
    "geosim_written", default=None)


@contextlib.contextmanager
def recording_outputs(journal: Path | None = None, *, tag: str = "") -> Iterator[list[Path]]:
    """Collect the final path of every file written atomically inside the block.

    The pipeline runner uses it so that a step interrupted half-way still records the
    outputs it completed (run.json), and a rerun can remove them if they are stale.
    With ``journal``, each path is also appended to that file at once (a line
    ``<tag>\t<path>``), so that even a run killed with SIGKILL leaves a list of what it
    wrote. Writes made in other processes (Dask workers) are not seen.
    """
    written: list[Path] = []
    token = _JOURNAL.set((written, journal, tag))
    try:
        yield written
    finally:
        _JOURNAL.reset(token)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it to ``path`` on success.

    Parameters
    ----------
    path
        Final output path. Its parent folder is created if needed.

    Yields
    ------
    pathlib.Path
        A temporary path with the same suffix (drivers pick formats by suffix).
        It is removed if the ``with`` body raises.
    """
    final = Path(path)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(
            f"{final.parent}: cannot create the output folder ({exc.strerror}); "
            "choose a writable --out folder"
        ) from exc
    fd, tmp_name = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".part{final.suffix}",
                                    dir=final.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()  # drivers (GDAL, GPKG) want to create the file themselves
    try:
        yield tmp
        os.replace(tmp, final)
        active = _JOURNAL.get()
        if active is not None:
            written, journal, tag = active
            written.append(final)
            if journal is not None:
                with open(journal, "a", encoding="utf-8") as fh:
                    fh.write(f"{tag}\t{final}\n")
    except Exception as exc:
        failure = write_failure(exc, final)
        if failure is None:
            raise
        raise failure from exc
    finally:
        for leftover in (tmp, tmp.with_name(tmp.name + ".aux.xml")):
            with contextlib.suppress(FileNotFoundError):
                leftover.unlink()


def write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Write ``obj`` as indented JSON, atomically. Returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, default=json_default) + "\n")
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` atomically. Returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def json_default(obj: Any) -> Any:
    """The one JSON converter of geosim (``json.dumps(..., default=json_default)``).

    numpy scalars and arrays, paths, dates and times, and dataclasses become plain JSON.
    """
    import dataclasses
    import datetime as dt

    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, (dt.datetime, dt.date, dt.time)):
        return obj.isoformat()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    if isinstance(obj, (set, frozenset)):
        return sorted(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


#: errno values that mean "this output cannot be written here".
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM,
                          errno.EROFS, errno.EIO, errno.ENOTDIR, errno.EISDIR})
#: Words in GDAL/OGR messages (rasterio, pyogrio) that mean a write failed.
_WRITE_WORDS = ("write failed", "write or read failed", "failed to create", "attempt to create",
                "permission denied", "no space", "file too large", "read-only file system",
                "disk full", "could not add feature", "failed to write")


def write_failure(exc: BaseException, path: str | os.PathLike[str]) -> OutputError | None:
    """One-line :class:`OutputError` for a failed write of ``path``, or None if not one.

    Recognises OS errors (disk full, quota, file too large, permission, read-only) and
    GDAL/OGR write failures as rasterio and pyogrio report them; a read error or a bug in
    the code writing the file is not translated.
    """
    if isinstance(exc, GeosimError):
        return None
    text = " ".join(str(exc).split())
    is_write = (isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS) or \
        any(word in text.lower() for word in _WRITE_WORDS)
    if not is_write:
        return None
    final = Path(path)
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else text
    reason = reason.replace(" See previous exception for details.", "").rstrip(".")[:160]
    try:
        free = f"; {shutil.disk_usage(final.parent).free / 1e9:.2f} GB free there"
    except OSError:
        free = ""
    return OutputError(f"{final}: cannot be written ({reason}{free}); free disk space or "
                       "choose a writable --out, then rerun (nothing was half-written)")


def to_jsonable(obj: Any, *, nan_to_null: bool = False) -> Any:
    """``obj`` as plain JSON types (what reading back its JSON text would give).

    With ``nan_to_null``, non-finite floats (NaN, ±inf: not JSON, RFC 8259) become
    ``None``, so that strict readers accept the file.
    """
    out = json.loads(json.dumps(obj, default=json_default))
    return _finite(out) if nan_to_null else out


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    return obj
