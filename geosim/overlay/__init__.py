"""Overlay check: local shifts between two rasters (or a run's satellite and degraded
mosaics) by windowed phase correlation; see :mod:`.check` and :mod:`.outputs`."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from geosim.errors import InputFileError
from geosim.overlay.check import OverlayResult, overlay_check
from geosim.rundir import RunDir

__all__ = ["OverlayResult", "overlay_check", "run_pairs"]


def run_pairs(out_dir: str | os.PathLike[str], flights: Sequence[str]
              ) -> list[tuple[str, Path, Path]]:
    """``(name, a, b)`` for a run folder: each flight's degraded mosaic (a) vs the satellite
    on the shared grid (b), so shifts say where the satellite sees the simulated ground."""
    run = RunDir.of(out_dir)
    sat = run.satellite_grid
    if not sat.is_file():
        raise InputFileError(f"{sat} not found; the overlay check of a run needs the "
                             "satellite scene on the grid ('geosim run' with a satellite)")
    pairs = []
    for fid in flights:
        vrt = run.degraded_dir / f"{fid}.vrt"
        if not vrt.is_file():
            raise InputFileError(f"{vrt} not found; run 'geosim degrade' and "
                                 "'geosim deliver' (or 'geosim run') first")
        pairs.append((f"degraded {fid} -> satellite", vrt, sat))
    return pairs
