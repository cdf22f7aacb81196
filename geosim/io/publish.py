"""Put a staged output folder in place without touching files geosim did not write.

A step that writes a whole folder (``labels/``) builds it under a hidden temporary name
and calls :func:`publish_folder`. The folder's list of files is kept in it
(:data:`MANIFEST`), so a rerun knows which files are its own:

- no folder yet, or one holding only geosim's files: the staged folder replaces it with
  two renames (readers see the old or the new folder, never a mix);
- a folder that also holds other files (a user's notes, another tool's output): only
  geosim's files are replaced or removed, file by file; the others stay untouched. A
  foreign file at the path of a new output is refused before anything changes.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from geosim.errors import OutputError

#: Name of the list of files geosim wrote, kept inside the published folder.
MANIFEST = ".geosim_files.json"


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*")
            if p.is_file() or p.is_symlink()}


def _own_files(final: Path, present: set[str], legacy_own: Callable[[str], bool]) -> set[str]:
    """The files of ``final`` that geosim wrote: from its manifest, else by name."""
    try:
        listed = json.loads((final / MANIFEST).read_text())["files"]
        return {str(r) for r in listed} & present
    except (OSError, ValueError, KeyError, TypeError):
        return {r for r in present if legacy_own(r)}  # written before manifests existed


def _swap(stage: Path, final: Path) -> None:
    old = final.with_name(f".{final.name}.old-{os.getpid()}")
    if old.exists():
        shutil.rmtree(old)
    os.replace(final, old)
    os.replace(stage, final)
    shutil.rmtree(old, ignore_errors=True)


def _prune_empty_dirs(final: Path, rel: str) -> None:
    parent = (final / rel).parent
    while parent != final and final in parent.parents:
        try:
            parent.rmdir()  # only when empty
        except OSError:
            return
        parent = parent.parent


def publish_folder(stage: Path, final: Path, *,
                   legacy_own: Callable[[str], bool] = lambda rel: False) -> dict[str, int]:
    """Replace geosim's files in ``final`` by the files of ``stage``; leave others alone.

    Parameters
    ----------
    stage
        The complete new folder (consumed: moved or emptied).
    final
        Where it goes.
    legacy_own
        For a ``final`` without a manifest: whether a relative POSIX path is a file geosim
        writes (by name).

    Returns
    -------
    dict
        ``written``, ``removed`` (geosim's stale files) and ``kept`` (foreign files).

    Raises
    ------
    OutputError
        A file geosim did not write sits where a new output goes.
    """
    new = _files(stage) - {MANIFEST}
    (stage / MANIFEST).write_text(json.dumps({"files": sorted(new)}, indent=1) + "\n")
    if not final.exists():
        os.replace(stage, final)
        return {"written": len(new), "removed": 0, "kept": 0}
    if not final.is_dir():
        raise OutputError(f"{final} is a file, not geosim's output folder; move it away")
    present = _files(final) - {MANIFEST}
    own = _own_files(final, present, legacy_own)
    foreign = present - own
    if not foreign:
        _swap(stage, final)
        return {"written": len(new), "removed": len(own - new), "kept": 0}
    clash = sorted(foreign & new)
    if clash:
        raise OutputError(f"{final / clash[0]} exists and was not written by geosim; move it "
                          "away or choose another --out (geosim never overwrites files it "
                          "did not write)")
    for rel in sorted(new):
        (final / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage / rel, final / rel)
    stale = sorted(own - new)
    for rel in stale:
        (final / rel).unlink(missing_ok=True)
        _prune_empty_dirs(final, rel)
    os.replace(stage / MANIFEST, final / MANIFEST)  # last: lists what is now there
    shutil.rmtree(stage, ignore_errors=True)
    return {"written": len(new), "removed": len(stale), "kept": len(foreign)}
