"""Tiles of the aligned grid: the same tile id is the same ground in every flight.

Tile ``r{row:03d}_c{col:03d}`` covers aligned-grid pixels
``[row·tile_px, (row+1)·tile_px) × [col·tile_px, (col+1)·tile_px)``; its transform is
the aligned grid transform offset by whole tiles
(``aligned_transform @ Affine.translation(col·tile_px, row·tile_px)``), and the aligned
grid transform is the site grid transform offset by whole satellite pixels, so tiles
stay nested in the satellite grid. A tile is kept when every flight's valid data
covers all of it; with ``keep_partial_tiles`` every tile that some flight covers
at least in part is kept, with its mask (pixels outside the data are masked).
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from affine import Affine
from rasterio.windows import Window
from rasterio.windows import bounds as window_bounds

from geosim.io.cog import TILE_COMPRESSION_OPTIONS, WholeRaster
from geosim.io.raster import create_geotiff, naming_read_failures


def tile_id(row: int, col: int) -> str:
    """Tile id ``r{row:03d}_c{col:03d}`` of tile row/column indexes on the aligned grid."""
    return f"r{row:03d}_c{col:03d}"


def tile_transform(aligned_transform: Affine, row: int, col: int, tile_px: int) -> Affine:
    """Transform of a tile: the aligned grid transform offset by whole tiles."""
    return aligned_transform @ Affine.translation(col * tile_px, row * tile_px)


@dataclass(frozen=True)
class TileSpec:
    """One tile of the aligned grid."""

    row: int
    col: int
    window: Window       # on the aligned grid; may extend beyond it (partial tiles)
    transform: Affine

    @property
    def id(self) -> str:
        """``r{row:03d}_c{col:03d}``."""
        return tile_id(self.row, self.col)

    def bounds(self) -> tuple[float, float, float, float]:
        """``(minx, miny, maxx, maxy)`` in the site CRS, metres."""
        return window_bounds(Window(0, 0, self.window.width, self.window.height), self.transform)


def iter_tiles(shape: tuple[int, int], aligned_transform: Affine, tile_px: int
               ) -> Iterator[TileSpec]:
    """Every tile touching an aligned grid of ``shape = (rows, cols)``, row-major."""
    rows, cols = shape
    for r in range(math.ceil(rows / tile_px)):
        for c in range(math.ceil(cols / tile_px)):
            yield TileSpec(r, c, Window(c * tile_px, r * tile_px, tile_px, tile_px),
                           tile_transform(aligned_transform, r, c, tile_px))


def select_tiles(tiles: Sequence[TileSpec], coverage: Mapping[str, Sequence[float]], *,
                 keep_partial: bool) -> list[tuple[TileSpec, dict[str, float]]]:
    """Tiles to cut, with each flight's coverage fraction.

    Parameters
    ----------
    tiles
        All tiles of the aligned grid.
    coverage
        ``{flight: [valid fraction of each tile]}`` in the order of ``tiles``.
    keep_partial
        False: keep a tile only if every flight covers it fully (fraction 1).
        True: keep it if any flight covers any of it.
    """
    out = []
    for i, t in enumerate(tiles):
        cov = {f: float(v[i]) for f, v in coverage.items()}
        full = all(v >= 1.0 for v in cov.values())
        if full or (keep_partial and any(v > 0 for v in cov.values())):
            out.append((t, cov))
    return out


@dataclass(frozen=True)
class WarpTileTask:
    """One tile of one flight, resampled once from the original flight (an engine task).

    The tile's pixels are those of the flight on the aligned grid
    (:class:`geosim.prepare.aligned.AlignedFlight`) over ``tile.window``; parts of the
    window outside the aligned grid (partial tiles) are 0 and masked.
    """

    flight: Any                       # geosim.prepare.aligned.AlignedFlight
    dst_path: str
    tile: TileSpec
    tags: Mapping[str, str]
    block_px: int = 2048
    #: ``parameters.tile_compression`` (:data:`geosim.config.TILE_COMPRESSIONS`).
    compression: str = "deflate"


def warp_tile_task(task: WarpTileTask) -> str:
    """Run a :class:`WarpTileTask`; returns the tile path.

    Memory: the tile (bands × tile_px²) plus one ``block_px``² block's coordinates and
    source window.
    """
    with naming_read_failures(task.flight.warp.src_path if task.flight.warp is not None
                               else str(task.flight.path)), task.flight.open() as reader:
        img, valid = read_tile(reader, task.tile.window, task.block_px)
        write_tile(reader, task, task.dst_path, img, valid)
    return str(task.dst_path)


def read_tile(reader: Any, window: Window, block_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The tile ``window`` of an open flight reader, read ``block_px``² blocks at a time:
    the ``(bands, rows, cols)`` image and its boolean valid mask."""
    from geosim.io.raster import iter_windows

    width, height = int(window.width), int(window.height)
    img = np.zeros((reader.count, height, width), dtype=reader.dtype)
    valid = np.zeros((height, width), dtype=bool)
    for blk in iter_windows(width, height, block_px=block_px):
        r0, c0 = int(blk.row_off), int(blk.col_off)
        r1, c1 = r0 + int(blk.height), c0 + int(blk.width)
        img[:, r0:r1, c0:c1], valid[r0:r1, c0:c1] = reader.read(Window(
            int(window.col_off) + c0, int(window.row_off) + r0, c1 - c0, r1 - r0))
    return img, valid


def write_tile(reader: Any, task: WarpTileTask, dst_path: str, img: np.ndarray,
               valid: np.ndarray) -> None:
    """Write a read tile as the task's COG at ``dst_path`` (the reader gives band count,
    type, CRS, descriptions and colour interpretation)."""
    write_tile_array(dst_path, img, valid, transform=task.tile.transform, crs=reader.crs,
                     band_descriptions=reader.descriptions, tags=task.tags,
                     cog_overrides=TILE_COMPRESSION_OPTIONS[task.compression],
                     colorinterp=reader.colorinterp)


def write_tile_array(dst_path: str | os.PathLike[str], img: np.ndarray, valid: np.ndarray, *,
                     transform: Affine, crs: Any,
                     band_descriptions: Sequence[str | None] | None = None,
                     tags: Mapping[str, str] | None = None,
                     cog_overrides: Mapping[str, Any] | None = None,
                     colorinterp: Sequence[Any] | None = None) -> None:
    """Write a UAV tile ``(bands, rows, cols)`` with its valid mask as ``geosim tile`` does.

    A COG with an internal mask whose overviews are computed in memory, the first of them
    the binomial level the degradation reads (:mod:`geosim.io.overviews`) where the tile is
    whole and 8-bit; ``cog_overrides``: the codec
    (:data:`~geosim.io.cog.TILE_COMPRESSION_OPTIONS`).
    """
    height, width = valid.shape
    with create_geotiff(dst_path, width=width, height=height, count=img.shape[0],
                        dtype=img.dtype, crs=crs, transform=transform,
                        band_descriptions=band_descriptions, tags=tags,
                        internal_mask=True, whole=WholeRaster(img, valid, binomial_level1=True),
                        cog_overrides=cog_overrides) as dst:
        if colorinterp is not None:
            dst.colorinterp = colorinterp
        dst.write(img)
        dst.write_mask(np.where(valid, 255, 0).astype(np.uint8))


@dataclass(frozen=True)
class AlignedCoverageTask:
    """Valid fractions of tile windows of one flight on the aligned grid (an engine task)."""

    flight: Any                       # geosim.prepare.aligned.AlignedFlight
    windows: tuple[Window, ...]
    block_px: int = 2048


def aligned_coverage_task(task: AlignedCoverageTask) -> list[float]:
    """Run an :class:`AlignedCoverageTask`: one fraction per window (masks only: the
    conservative mask of the warp, no image resampled)."""
    with task.flight.open() as reader:
        return [reader.valid_fraction(w, task.block_px) for w in task.windows]


def index_records(selected: Sequence[tuple[TileSpec, Mapping[str, float]]], crs_name: str,
                  tile_px: int, *, reference: str | None = None) -> list[dict[str, Any]]:
    """Rows of ``tiles/index.geojson`` (geometry added by the caller).

    ``location`` is the path of the tile's file, relative to the index's folder, as
    ``gdaltindex`` writes it (so GDAL's GTI driver, MapServer and QGIS can open the tiles
    from the index): the ``reference`` flight's file when it covers the tile, else the first
    flight that does; ``location_<flight>`` gives every flight's file ("" where absent).
    """
    rows = []
    for t, cov in selected:
        minx, miny, maxx, maxy = t.bounds()
        have = [f for f, v in cov.items() if v > 0]
        first = reference if reference in have else (have[0] if have else None)
        rows.append({
            "location": f"{first}/{t.id}.tif" if first else "",
            **{f"location_{f}": (f"{f}/{t.id}.tif" if f in have else "") for f in cov},
            "tile_id": t.id, "row": t.row, "col": t.col, "tile_px": tile_px,
            "minx": minx, "miny": miny, "maxx": maxx, "maxy": maxy, "crs": crs_name,
            "flights": ",".join(f for f, v in cov.items() if v > 0),
            "min_coverage": min(cov.values()) if cov else 0.0,
            "partial": not all(v >= 1.0 for v in cov.values()),
            "transform": ",".join(repr(v) for v in list(t.transform)[:6]),
        })
    return rows
