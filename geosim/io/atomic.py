"""Write to a temporary name beside the target, rename on success.

A killed or failed run therefore never leaves a half-written output under the
final name, and an existing output is replaced in one step.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from geosim.errors import GeosimError, OutputError


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
        tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")
    return Path(path)


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` atomically. Returns the final path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
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
