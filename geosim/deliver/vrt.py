"""GDAL VRT mosaics of tiles that sit on one pixel grid (no resampling, relative paths).

The tiles of a flight share the aligned grid, so each tile is placed in the mosaic
at a whole-pixel offset: the VRT only points at the tiles (``relativeToVRT``), with a
mask band built from the tiles' internal masks, and GDAL reads the tiles' own
overviews through it.

References
----------
GDAL VRT format: https://gdal.org/drivers/raster/vrt.html
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

import rasterio
from affine import Affine

from geosim.errors import RasterError
from geosim.io.atomic import write_text

#: GDAL data type names of numpy dtypes.
_GDAL_TYPES = {"uint8": "Byte", "uint16": "UInt16", "int16": "Int16", "uint32": "UInt32",
               "int32": "Int32", "float32": "Float32", "float64": "Float64"}


@dataclass(frozen=True)
class TileInfo:
    """What the VRT needs to know of one tile."""

    path: Path
    width: int
    height: int
    transform: Affine
    block: tuple[int, int]


@dataclass(frozen=True)
class Mosaic:
    """Georeference of a mosaic of tiles: its size in pixels, transform and each tile's offset."""

    width: int
    height: int
    transform: Affine
    offsets_px: tuple[tuple[int, int], ...]   # (col, row) of each tile's first pixel


def mosaic_layout(transforms: Sequence[Affine], sizes: Sequence[tuple[int, int]], *,
                  tol_px: float = 1e-6) -> Mosaic:
    """Place tiles of one north-up pixel grid in a mosaic.

    Parameters
    ----------
    transforms
        Each tile's transform (same pixel size, north-up).
    sizes
        Each tile's ``(width, height)`` in pixels.
    tol_px
        Largest departure of a tile's origin from a whole-pixel offset, in pixels.

    Raises
    ------
    RasterError
        Tiles with different pixel sizes, rotation, or origins off the common grid.
    """
    t0 = transforms[0]
    if t0.b != 0 or t0.d != 0:
        raise RasterError("mosaic: tiles must be north-up (no rotation terms)")
    minx = min(t.c for t in transforms)
    maxy = max(t.f for t in transforms)
    offsets = []
    for t in transforms:
        if (t.a, t.b, t.d, t.e) != (t0.a, t0.b, t0.d, t0.e):
            raise RasterError(f"mosaic: pixel size {t.a, t.e} differs from {t0.a, t0.e}; "
                              "tiles of one mosaic must share one grid")
        col, row = (t.c - minx) / t0.a, (t.f - maxy) / t0.e
        if abs(col - round(col)) > tol_px or abs(row - round(row)) > tol_px:
            raise RasterError(f"mosaic: a tile's origin ({t.c}, {t.f}) is off the grid of the "
                              "others by a fraction of a pixel; tiles must share one grid")
        offsets.append((round(col), round(row)))
    width = max(c + w for (c, _), (w, _) in zip(offsets, sizes, strict=True))
    height = max(r + h for (_, r), (_, h) in zip(offsets, sizes, strict=True))
    return Mosaic(width, height, Affine(t0.a, 0.0, minx, 0.0, t0.e, maxy), tuple(offsets))


def _source(rel: str, band: str, tile: TileInfo, dtype: str, offset: tuple[int, int]) -> str:
    bx, by = tile.block
    return (f"      <SimpleSource>\n"
            f"        <SourceFilename relativeToVRT=\"1\">{escape(rel)}</SourceFilename>\n"
            f"        <SourceBand>{band}</SourceBand>\n"
            f"        <SourceProperties RasterXSize=\"{tile.width}\" "
            f"RasterYSize=\"{tile.height}\" DataType=\"{dtype}\" BlockXSize=\"{bx}\" "
            f"BlockYSize=\"{by}\" />\n"
            f"        <SrcRect xOff=\"0\" yOff=\"0\" xSize=\"{tile.width}\" "
            f"ySize=\"{tile.height}\" />\n"
            f"        <DstRect xOff=\"{offset[0]}\" yOff=\"{offset[1]}\" xSize=\"{tile.width}\" "
            f"ySize=\"{tile.height}\" />\n"
            f"      </SimpleSource>\n")


def write_mosaic_vrt(tile_paths: Sequence[str | os.PathLike[str]],
                     vrt_path: str | os.PathLike[str]) -> Path:
    """Write a VRT mosaic of GeoTIFF tiles on one grid, with paths relative to the VRT.

    Parameters
    ----------
    tile_paths
        Tiles of one flight (same CRS, bands, dtype and pixel grid).
    vrt_path
        The ``.vrt`` to write (atomically); tile paths are stored relative to its folder.

    Returns
    -------
    pathlib.Path
        ``vrt_path``.
    """
    vrt = Path(vrt_path)
    if not tile_paths:
        raise RasterError(f"{vrt}: no tiles to mosaic")
    tiles, first = [], None
    for p in tile_paths:
        with rasterio.open(p) as ds:
            if first is None:
                first = {"crs": ds.crs, "count": ds.count, "dtype": ds.dtypes[0],
                         "nodata": ds.nodata, "colorinterp": [c.name for c in ds.colorinterp],
                         "descriptions": ds.descriptions}
            elif (ds.crs, ds.count, ds.dtypes[0]) != (first["crs"], first["count"],
                                                        first["dtype"]):
                raise RasterError(f"{p}: CRS, band count or data type differs from "
                                  f"{tile_paths[0]}; a mosaic needs tiles of one kind")
            tiles.append(TileInfo(Path(p), ds.width, ds.height, ds.transform,
                                  tuple(ds.block_shapes[0][::-1])))
    assert first is not None
    layout = mosaic_layout([t.transform for t in tiles], [(t.width, t.height) for t in tiles])
    dtype = _GDAL_TYPES[first["dtype"]]
    rels = [Path(os.path.relpath(t.path.resolve(), vrt.resolve().parent)).as_posix()
            for t in tiles]
    g = layout.transform
    lines = [f"<VRTDataset rasterXSize=\"{layout.width}\" rasterYSize=\"{layout.height}\">\n",
             f"  <SRS dataAxisToSRSAxisMapping=\"1,2\">{escape(first['crs'].to_wkt())}</SRS>\n",
             f"  <GeoTransform>{g.c!r}, {g.a!r}, {g.b!r}, {g.f!r}, {g.d!r}, {g.e!r}"
             "</GeoTransform>\n"]
    for band in range(1, first["count"] + 1):
        lines.append(f"  <VRTRasterBand dataType=\"{dtype}\" band=\"{band}\">\n")
        desc = first["descriptions"][band - 1]
        if desc:
            lines.append(f"    <Description>{escape(desc)}</Description>\n")
        if first["nodata"] is not None:
            nd = first["nodata"]
            lines.append(f"    <NoDataValue>{'nan' if math.isnan(nd) else repr(nd)}"
                         "</NoDataValue>\n")
        ci = first["colorinterp"][band - 1]
        lines.append(f"    <ColorInterp>{ci.capitalize()}</ColorInterp>\n")
        lines += [_source(r, str(band), t, dtype, o)
                  for r, t, o in zip(rels, tiles, layout.offsets_px, strict=True)]
        lines.append("  </VRTRasterBand>\n")
    lines.append("  <MaskBand>\n    <VRTRasterBand dataType=\"Byte\">\n")
    lines += [_source(r, "mask,1", t, "Byte", o).replace("      <", "        <")
              for r, t, o in zip(rels, tiles, layout.offsets_px, strict=True)]
    lines.append("    </VRTRasterBand>\n  </MaskBand>\n</VRTDataset>\n")
    return write_text(vrt, "".join(lines))


__all__ = ["Mosaic", "TileInfo", "mosaic_layout", "write_mosaic_vrt"]
