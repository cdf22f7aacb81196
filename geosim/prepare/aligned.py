"""A flight on the aligned grid, read on demand through its composed warp.

The align step no longer stores every flight resampled onto the aligned grid
(``aligned/<flight>.tif`` is written only with ``keep_intermediates = true``): the tiles,
the calibration and the diagnosis read the windows they need straight from the original
flight file through the flight's composed warp (:mod:`geosim.prepare.onewarp`: source
CRS → site grid → alignment correction [→ local field], one bicubic interpolation). The
pixels are the ones the aligned raster would hold, bit for bit: the warp maps every
destination pixel from its global grid index alone, whatever window it is read in.

:func:`aligned_flights` rebuilds each flight's :class:`AlignedFlight` from the run folder
(``grid/grid.json``, ``alignment.json`` and, with ``align_model = "local"``,
``alignment_field/<flight>.tif``). An :class:`AlignedFlight` is picklable (it holds paths
and numbers), so it travels to engine workers; :meth:`AlignedFlight.open` gives a reader
with the few dataset-like attributes the readers need.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.windows import Window

from geosim.errors import AlignmentError
from geosim.io.raster import (
    band_descriptions,
    image_band_indexes,
    iter_windows,
    read_valid_mask,
)
from geosim.prepare.onewarp import ComposedWarp, read_warped, read_warped_valid
from geosim.rundir import RunDir, RunPath


@dataclass(frozen=True)
class AlignedFlight:
    """One flight on the aligned grid (picklable).

    Parameters
    ----------
    flight
        Flight id.
    warp
        Its composed warp (original file → aligned grid), or None when ``path`` is read.
    transform
        Affine of the aligned grid (6 numbers; the site grid offset by whole pixels).
    shape
        ``(rows, cols)`` of the aligned grid, pixels.
    path
        A stored raster on the aligned grid to read instead of warping (``aligned/`` with
        ``keep_intermediates``, or a raster handed in by a caller).
    sources
        The files the pixels come from (for provenance tags and resume manifests).
    """

    flight: str
    warp: ComposedWarp | None
    transform: tuple[float, ...]
    shape: tuple[int, int]
    path: str | None = None
    sources: tuple[str, ...] = ()

    @classmethod
    def from_raster(cls, flight: str, path: str | os.PathLike[str]) -> AlignedFlight:
        """A flight already stored on the aligned grid (read as it is)."""
        with rasterio.open(path) as ds:
            return cls(flight, None, tuple(ds.transform)[:6], (ds.height, ds.width),
                       str(path), (str(path),))

    @contextlib.contextmanager
    def open(self) -> Iterator[AlignedReader]:
        """A reader of windows of this flight (the source file opened once)."""
        src_path = self.path if self.path is not None else self.warp.src_path
        with rasterio.open(src_path) as src:
            yield AlignedReader(self, src)


class AlignedReader:
    """Windows of an :class:`AlignedFlight`; dataset-like ``crs``, ``transform``, ``width``,
    ``height``, ``count``, ``dtype`` and ``name`` (the file read). Pixels outside the
    aligned grid are 0 and invalid."""

    def __init__(self, flight: AlignedFlight, src: rasterio.DatasetReader) -> None:
        self.flight = flight
        self.name = flight.path if flight.path is not None else flight.warp.src_path
        self._src = src
        self._bands = image_band_indexes(src)
        self.transform = Affine(*flight.transform)
        self.height, self.width = (int(v) for v in flight.shape)
        self.count = len(self._bands)
        self.dtype = src.dtypes[self._bands[0] - 1] if self._bands else "uint8"
        self.crs = (src.crs if flight.warp is None
                    else CRS.from_wkt(flight.warp.site_crs_wkt))
        self.descriptions = (band_descriptions(src, self._bands) if flight.warp is not None
                             else [d or f"band {i}" for i, d in enumerate(
                                 (src.descriptions[b - 1] for b in self._bands), 1)])
        self.colorinterp = [src.colorinterp[b - 1] for b in self._bands]

    def _inner(self, window: Window) -> tuple[Window, slice, slice] | None:
        """The part of ``window`` inside the aligned grid and where it sits in ``window``."""
        r0, c0 = int(window.row_off), int(window.col_off)
        a0, b0 = max(r0, 0), max(c0, 0)
        a1 = min(r0 + int(window.height), self.height)
        b1 = min(c0 + int(window.width), self.width)
        if a1 <= a0 or b1 <= b0:
            return None
        return (Window(b0, a0, b1 - b0, a1 - a0), slice(a0 - r0, a1 - r0),
                slice(b0 - c0, b1 - c0))

    def read_valid(self, window: Window) -> np.ndarray:
        """The valid mask of a window (as :meth:`read` gives it), without the image."""
        valid = np.zeros((int(window.height), int(window.width)), dtype=bool)
        found = self._inner(window)
        if found is None:
            return valid
        inner, rs, cs = found
        if self.flight.warp is None:
            valid[rs, cs] = read_valid_mask(self._src, window=inner)
        else:
            t = self.transform @ Affine.translation(int(inner.col_off), int(inner.row_off))
            valid[rs, cs] = read_warped_valid(self.flight.warp, t,
                                              (int(inner.height), int(inner.width)),
                                              src=self._src)
        return valid

    def valid_fraction(self, window: Window, block_px: int = 2048) -> float:
        """Fraction of ``window`` (may extend past the grid) that is valid, block by block."""
        n = 0
        for blk in iter_windows(int(window.width), int(window.height), block_px=block_px):
            n += int(np.count_nonzero(self.read_valid(Window(
                int(window.col_off) + int(blk.col_off), int(window.row_off) + int(blk.row_off),
                int(blk.width), int(blk.height)))))
        return n / (int(window.width) * int(window.height))

    def read(self, window: Window, n_bands: int | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
        """``(image (bands, rows, cols), valid (rows, cols))`` of a window of the aligned grid.

        ``n_bands``: the first ``n_bands`` image bands (default all; alpha never).
        """
        bands = self._bands[:n_bands] if n_bands else self._bands
        h, w = int(window.height), int(window.width)
        image = np.zeros((len(bands), h, w), dtype=self.dtype)
        valid = np.zeros((h, w), dtype=bool)
        found = self._inner(window)
        if found is None:
            return image, valid
        inner, rs, cs = found
        if self.flight.warp is None:
            img = self._src.read(list(bands), window=inner)
            ok = read_valid_mask(self._src, window=inner)
            img[:, ~ok] = 0
        else:
            t = self.transform @ Affine.translation(int(inner.col_off), int(inner.row_off))
            img, ok = read_warped(self.flight.warp, t, (int(inner.height), int(inner.width)),
                                  src=self._src, bands=list(bands))
        image[:, rs, cs] = img
        valid[rs, cs] = ok
        return image, valid


def read_alignment_doc(run: RunDir) -> dict[str, Any]:
    """``alignment.json`` (InputFileError if absent)."""
    return json.loads(run.require_alignment().read_text())


def aligned_flights(site: Any, out: RunPath) -> dict[str, AlignedFlight]:
    """Every flight of ``site`` on the aligned grid of the run folder ``out``.

    Built from ``grid/grid.json`` and ``alignment.json`` (each flight's ``aligned_to_stated``
    and, with the local model, its field file) and the site's flight files. An
    ``alignment.json`` written before the warps were recorded (no ``aligned_to_stated``)
    falls back to the stored ``aligned/<flight>.tif``.

    A run folder without ``alignment.json`` whose ``aligned/`` holds every flight is read
    from those rasters.

    Raises
    ------
    InputFileError
        ``grid/grid.json`` or ``alignment.json`` is missing (run the earlier steps).
    AlignmentError
        A flight has neither a recorded warp nor a stored aligned raster.
    """
    from geosim.prepare.grid import SiteGrid
    from geosim.prepare.local_align import read_field_geotiff

    run = RunDir.of(out)
    if not run.alignment_json.is_file() and all(run.aligned(f.id).is_file()
                                                for f in site.flights):
        # rasters already on the aligned grid, without the alignment that made them
        return {f.id: AlignedFlight.from_raster(f.id, run.aligned(f.id)) for f in site.flights}
    doc = read_alignment_doc(run)
    grid = SiteGrid.from_dict(json.loads(run.require_grid().read_text()))
    ag = doc["aligned_grid"]
    transform = tuple(float(v) for v in ag["transform"][:6])
    shape = (int(ag["shape"][0]), int(ag["shape"][1]))
    out_flights: dict[str, AlignedFlight] = {}
    for f in site.flights:
        entry = (doc.get("flights") or {}).get(f.id)
        if not isinstance(entry, dict) or "aligned_to_stated" not in entry:
            # an alignment.json that does not record the warps (another geosim version, or
            # written by hand): the stored aligned raster, when there is one
            if run.aligned(f.id).is_file():
                out_flights[f.id] = AlignedFlight.from_raster(f.id, run.aligned(f.id))
                continue
            raise AlignmentError(f"{run.alignment_json}: no warp recorded for flight {f.id} "
                                 f"and no {run.rel(run.aligned(f.id))}; re-run 'geosim align'")
        sources = [str(f.image)]
        field = None
        if entry.get("local_field"):
            field_path = run.alignment_field(f.id)
            field = read_field_geotiff(field_path).apply
            sources.append(str(field_path))
        warp = ComposedWarp.for_flight(f.image, grid.crs, grid.uav_transform,
                                       aligned_to_stated=Affine(*entry["aligned_to_stated"]),
                                       field=field)
        out_flights[f.id] = AlignedFlight(f.id, warp, transform, shape, None, tuple(sources))
    return out_flights


def flight_inputs(flight: AlignedFlight) -> tuple[str, ...]:
    """The files an aligned flight's pixels depend on, for resume manifests (the warp
    itself — grid, correction, field values — is part of the task's parameters)."""
    return tuple(str(p) for p in flight.sources)


__all__ = ["AlignedFlight", "AlignedReader", "aligned_flights", "flight_inputs"]
