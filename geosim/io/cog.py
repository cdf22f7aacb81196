"""Cloud-Optimized GeoTIFFs: every raster geosim writes ends up in this layout.

Rasters are written window by window into a scratch GeoTIFF beside the target and
then copied once with GDAL's COG driver, which builds internal overviews (of the
pixels and of the mask), orders the file as the COG layout asks (IFDs first,
overviews before full resolution) and keeps tags, band descriptions, colour
interpretation, nodata and the internal mask. The copy is lossless (deflate), so
the decoded full-resolution pixels are exactly those written.

Cost (CPU, one 5000 x 5000 RGB tile with its mask; benchmarks/bench_cog_write.py): the
copy's deflate at GDAL's default level 6 was the largest part, so geosim writes
deflate level :data:`DEFLATE_LEVEL` (same decoded pixels, an 8 % larger file),
and a scratch file small enough is written uncompressed (it is read once, right away).
GDAL compresses with one thread (``NUM_THREADS=1``): its multi-threaded writer lays the
blocks out in another order (files must be the same bytes whatever engine ran them), and
geosim runs one single-threaded task per core (docs/scale.md), so more threads would only
compete for the same cores without lowering the CPU per file.
A writer holding the whole raster (:class:`WholeRaster`) gets its overviews computed in
memory instead (:mod:`geosim.io.overviews`): GDAL's masked averaging and mask overviews were
about a third of a 5000 px tile's write (docs/delivery.md).

References
----------
GDAL COG driver: https://gdal.org/drivers/raster/cog.html
"""

from __future__ import annotations

import contextlib
import glob
import os
import warnings
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np
import rasterio
import rasterio.shutil
from rasterio.errors import NotGeoreferencedWarning

from geosim.io.atomic import atomic_path
from geosim.io.overviews import (
    LEVEL1_BINOMIAL,
    LEVEL1_TAG,
    average_overviews,
    binomial_level1_applies,
)

#: Internal tile size (pixels) of every COG geosim writes; overviews are built down to it.
COG_BLOCK_PX = 256

#: libdeflate level of every COG geosim writes (GDAL's default is 6, which cost about
#: twice the CPU of the whole write at level 1 on a 5000 px tile, for a file 8 %
#: smaller; any level decodes with any DEFLATE reader; degraded tiles already used 1).
DEFLATE_LEVEL = 1

#: Scratch GeoTIFFs up to this many bytes of raw pixels are written uncompressed (a 5000 px
#: RGB tile is 75 MB); larger ones (whole orthomosaics) with ZSTD level 1 to bound the
#: scratch disk.
SCRATCH_RAW_MAX_BYTES = 256 * 2**20


#: COG options replacing :func:`cog_options` per ``parameters.tile_compression``
#: (:data:`geosim.config.TILE_COMPRESSIONS`): DEFLATE as every COG, or uncompressed.
#: Measured on a 5000 px RGB tile with its mask (benchmarks/bench_tile_codec.py): 45.2 MB,
#: 2.3 CPU-s to write, 0.16-0.19 CPU-s to read (DEFLATE) against 106.0 MB, 1.4 and 0.045
#: (uncompressed); OpenCV and Pillow read both.
TILE_COMPRESSION_OPTIONS: dict[str, dict[str, Any]] = {
    "deflate": {},
    "none": {"COMPRESS": "NONE", "PREDICTOR": "NO"},
}


def cog_options(*, blocksize_px: int = COG_BLOCK_PX, resampling: str = "average"
                ) -> dict[str, Any]:
    """Creation options of GDAL's COG driver used for every geosim raster.

    Parameters
    ----------
    blocksize_px
        Internal tile size in pixels (overviews stop once they fit in one tile).
    resampling
        Overview resampling (``average`` keeps grey levels of imagery and masks honest).
    """
    return {"COMPRESS": "DEFLATE", "LEVEL": DEFLATE_LEVEL, "PREDICTOR": "YES",
            "BLOCKSIZE": int(blocksize_px),
            "OVERVIEWS": "AUTO", "OVERVIEW_RESAMPLING": resampling.upper(),
            "BIGTIFF": "IF_SAFER", "NUM_THREADS": "1"}


def copy_as_cog(src: str | os.PathLike[str], dst: str | os.PathLike[str], **options: Any
                ) -> Path:
    """Copy any GDAL-readable raster to ``dst`` as a COG (not atomic; see :func:`cog_writer`)."""
    opts = {**cog_options(), **{k.upper(): v for k, v in options.items()}}
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        rasterio.shutil.copy(str(src), str(dst), driver="COG", **opts)
    return Path(dst)


@dataclass(frozen=True)
class WholeRaster:
    """The whole raster a writer holds in memory, from which :func:`cog_writer` computes the
    overviews itself (:mod:`geosim.io.overviews`) instead of GDAL reading the file back.

    Attributes
    ----------
    array
        ``(bands, rows, cols)`` pixels, exactly as written to the file.
    valid
        ``(rows, cols)`` bool mask (True = valid) written as the internal mask.
    fill
        Value of overview pixels with no valid pixel under them (the nodata value, or 0).
    binomial_level1
        Make the first overview level the binomial one where it applies (an all-valid 8-bit
        raster of even sides: :mod:`geosim.io.overviews`), and tag the raster so
        (:data:`~geosim.io.overviews.LEVEL1_TAG`): the UAV tiles, which ``geosim degrade``
        then reads at that level.
    """

    array: np.ndarray
    valid: np.ndarray
    fill: float = 0
    binomial_level1: bool = False

    def binomial_level1_written(self, block_px: int) -> bool:
        """Whether the first overview level written for ``block_px`` blocks is binomial."""
        return self.binomial_level1 and binomial_level1_applies(self.array, self.valid,
                                                                block_px)


def _overview_source(scratch: Path, whole: WholeRaster, block_px: int) -> Path | None:
    """Write the overview levels of ``whole`` beside ``scratch`` (uncompressed GeoTIFFs with
    their internal masks) and a VRT of ``scratch`` listing them as its overviews (its mask's
    too); return the VRT, or None when the raster needs no overviews.

    The VRT is GDAL's own copy of the scratch (georeference, tags, descriptions, colour
    interpretation, nodata and mask band as GDAL reads them), with ``<Overview>`` elements
    added, so the COG copy (``OVERVIEWS=FORCE_USE_EXISTING``) keeps everything it would have
    kept from the scratch.
    """
    levels = average_overviews(whole.array, whole.valid, block_px, fill=whole.fill,
                               binomial_level1=whole.binomial_level1)
    if not levels:
        return None
    names = []
    for i, level in enumerate(levels):
        path = scratch.with_name(f"{scratch.name}.ovr{i + 1}.tif")
        bands, rows, cols = level.array.shape
        # the VRT places the level; the file itself needs no georeference
        with warnings.catch_warnings(category=NotGeoreferencedWarning, action="ignore"), \
                rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(
                path, "w", driver="GTiff", width=cols, height=rows, count=bands,
                dtype=level.array.dtype, compress="none") as dst:
            dst.write(level.array)
            dst.write_mask(level.valid.view(np.uint8) * np.uint8(255))
        names.append(path.name)
    vrt = scratch.with_name(scratch.name + ".vrt")
    rasterio.shutil.copy(str(scratch), str(vrt), driver="VRT")
    tree = ElementTree.parse(vrt)
    root = tree.getroot()
    targets = [(band, band.get("band")) for band in root.findall("VRTRasterBand")]
    targets += [(band, "mask,1") for band in root.findall("MaskBand/VRTRasterBand")]
    for band, source_band in targets:
        for name in names:
            ovr = ElementTree.SubElement(band, "Overview")
            ElementTree.SubElement(ovr, "SourceFilename", relativeToVRT="1").text = name
            ElementTree.SubElement(ovr, "SourceBand").text = source_band
    tree.write(vrt)
    return vrt


@contextlib.contextmanager
def cog_writer(path: str | os.PathLike[str], profile: Mapping[str, Any], *,
               internal_mask: bool = False, cog_overrides: Mapping[str, Any] | None = None,
               whole: WholeRaster | None = None) -> Iterator[rasterio.io.DatasetWriter]:
    """Open a scratch GeoTIFF for (windowed) writing; on success it becomes ``path`` as a COG.

    Parameters
    ----------
    path
        Final raster path. Written under a temporary name and renamed, so a failure
        leaves no half-written file.
    profile
        rasterio creation profile of the scratch GeoTIFF (``driver`` must be GTiff).
    internal_mask
        Store the mask written with ``dst.write_mask`` as an internal mask band.
    cog_overrides
        COG creation options that replace those of :func:`cog_options` (e.g. ``LEVEL``).
    whole
        The whole raster as written, with the mask written as the internal mask: the
        overviews (and the mask's) are then computed from it in memory
        (:mod:`geosim.io.overviews`) instead of by GDAL reading the file back (0.6-0.7 CPU-s
        less for a 5000 px RGB tile; same sizes and mask, pixels within rounding of GDAL's).
    """
    with atomic_path(path) as tmp:
        scratch = tmp.with_name(tmp.name.replace(".part", ".scratch"))
        try:
            env = (rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True) if internal_mask
                   else contextlib.nullcontext())
            scratch_profile = {**dict(profile), **scratch_options(profile)}
            overrides = {k.upper(): v for k, v in (cog_overrides or {}).items()}
            block_px = int(overrides.get("BLOCKSIZE", COG_BLOCK_PX))
            with env, rasterio.open(scratch, "w", **scratch_profile) as dst:
                yield dst
                if whole is not None and whole.binomial_level1_written(block_px):
                    dst.update_tags(**{LEVEL1_TAG: LEVEL1_BINOMIAL})
            vrt = None if whole is None else _overview_source(scratch, whole, block_px)
            if vrt is None:
                copy_as_cog(scratch, tmp, **overrides)
            else:
                copy_as_cog(vrt, tmp, **{**overrides, "OVERVIEWS": "FORCE_USE_EXISTING"})
        finally:
            for leftover in scratch.parent.glob(glob.escape(scratch.name) + "*"):
                with contextlib.suppress(FileNotFoundError):
                    leftover.unlink()


def scratch_options(profile: Mapping[str, Any]) -> dict[str, Any]:
    """Compression of the scratch GeoTIFF, which is read once right after being written.

    Uncompressed up to :data:`SCRATCH_RAW_MAX_BYTES` of raw pixels (no encode, no decode),
    ZSTD level 1 above (bounded scratch disk); the final compression is the COG copy's.
    """
    itemsize = np.dtype(profile["dtype"]).itemsize
    raw_bytes = int(profile["width"]) * int(profile["height"]) * int(profile["count"]) * itemsize
    if raw_bytes <= SCRATCH_RAW_MAX_BYTES:
        return {"compress": "none", "predictor": 1}
    return {"compress": "zstd", "zstd_level": 1, "predictor": 1}
