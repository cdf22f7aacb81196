"""How file paths are recorded in outputs (provenance tags, JSON, label attributes)."""

from __future__ import annotations

import os
import re
from pathlib import Path


def relative_if_inside(path: str | os.PathLike[str],
                       base_dir: str | os.PathLike[str] | None) -> str:
    """``path`` relative to ``base_dir`` (POSIX) when it lies inside it, else as given.

    Recording paths inside a run or site folder relative to it keeps them true when the
    folder is moved or opened on another machine.
    """
    p = Path(path)
    if base_dir is not None:
        try:
            return p.resolve().relative_to(Path(base_dir).resolve()).as_posix()
        except ValueError:
            pass  # outside base_dir
    return str(p)


def safe_name(text: str, *, default: str = "item") -> str:
    """``text`` as a file or folder name: runs of characters other than ``A-Z a-z 0-9 . _ -``
    become ``_``, leading and trailing dots go (no hidden files, no ``..``); ``default``
    when nothing is left. The one id sanitiser of geosim (flight ids, pair ids, folders).
    """
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip(".") or default


def unique_name(base: str, taken: set[str]) -> str:
    """``base``, or ``base_2``, ``base_3``, ... : the first not in ``taken`` (which it joins)."""
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    taken.add(name)
    return name
