"""Cloud-Optimized GeoTIFFs: every raster geosim writes ends up in this layout.

Rasters are written window by window into a scratch GeoTIFF beside the target and
then copied once with GDAL's COG driver, which builds internal overviews (of the
pixels and of the mask), orders the file as the COG layout asks (IFDs first,
overviews before full resolution) and keeps tags, band descriptions, colour
interpretation, nodata and the internal mask. The copy is lossless (deflate), so
the decoded full-resolution pixels are exactly those written.

References
----------
GDAL COG driver: https://gdal.org/drivers/raster/cog.html
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import rasterio
import rasterio.shutil

from geosim.io.atomic import atomic_path

#: Internal tile size (pixels) of every COG geosim writes; overviews are built down to it.
COG_BLOCK_PX = 256


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
    return {"COMPRESS": "DEFLATE", "PREDICTOR": "YES", "BLOCKSIZE": int(blocksize_px),
            "OVERVIEWS": "AUTO", "OVERVIEW_RESAMPLING": resampling.upper(),
            "BIGTIFF": "IF_SAFER", "NUM_THREADS": "1"}


def copy_as_cog(src: str | os.PathLike[str], dst: str | os.PathLike[str], **options: Any
                ) -> Path:
    """Copy any GDAL-readable raster to ``dst`` as a COG (not atomic; see :func:`cog_writer`)."""
    opts = {**cog_options(), **{k.upper(): v for k, v in options.items()}}
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True):
        rasterio.shutil.copy(str(src), str(dst), driver="COG", **opts)
    return Path(dst)


@contextlib.contextmanager
def cog_writer(path: str | os.PathLike[str], profile: Mapping[str, Any], *,
               internal_mask: bool = False, cog_overrides: Mapping[str, Any] | None = None,
               ) -> Iterator[rasterio.io.DatasetWriter]:
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
    """
    with atomic_path(path) as tmp:
        scratch = tmp.with_name(tmp.name.replace(".part", ".scratch"))
        try:
            env = (rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True) if internal_mask
                   else contextlib.nullcontext())
            # the scratch copy is read once: fast compression, final compression in the COG
            scratch_profile = {**dict(profile), "compress": "zstd", "zstd_level": 1,
                               "predictor": 1}
            with env, rasterio.open(scratch, "w", **scratch_profile) as dst:
                yield dst
            copy_as_cog(scratch, tmp, **dict(cog_overrides or {}))
        finally:
            for leftover in (scratch, scratch.with_name(scratch.name + ".aux.xml")):
                with contextlib.suppress(FileNotFoundError):
                    leftover.unlink()

