"""Overlay check: local shifts between two rasters (or a run's satellite and degraded
mosaics) by windowed phase correlation; see :mod:`.check` and :mod:`.outputs`."""

from geosim.overlay.check import OverlayResult, overlay_check

__all__ = ["OverlayResult", "overlay_check", "run_pairs"]


def run_pairs(out_dir, flights):  # type: ignore[no-untyped-def]
    """``(name, a, b)`` for a run folder: each flight's degraded mosaic (a) vs the satellite
    on the shared grid (b), so shifts say where the satellite sees the simulated ground."""
    from pathlib import Path

    from geosim.errors import InputFileError

    out = Path(out_dir)
    sat = out / "grid" / "satellite.tif"
    if not sat.is_file():
        raise InputFileError(f"{sat} not found; the overlay check of a run needs the "
                             "satellite scene on the grid ('geosim run' with a satellite)")
    pairs = []
    for fid in flights:
        vrt = out / "degraded" / f"{fid}.vrt"
        if not vrt.is_file():
            raise InputFileError(f"{vrt} not found; run 'geosim degrade' and "
                                 "'geosim deliver' (or 'geosim run') first")
        pairs.append((f"degraded {fid} -> satellite", vrt, sat))
    return pairs
