"""How file paths are recorded in outputs (provenance tags, JSON, label attributes)."""

from __future__ import annotations

import os
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
