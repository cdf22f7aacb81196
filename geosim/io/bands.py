"""Which band layouts and data types the pipeline reads (checked when a site is loaded)."""

from __future__ import annotations

import rasterio

from geosim.errors import RasterError

__all__ = ["check_raster_bands"]


def check_raster_bands(ds: rasterio.DatasetReader, what: str) -> None:
    """Refuse a band layout or data type the pipeline cannot use.

    Supported: 1 image band (grey; luma) or 3 or more (R, G, B first), each optionally
    with an alpha band; all image bands of one supported data type.
    """
    from geosim.io.raster import image_band_indexes
    from geosim.prepare.reproject import SUPPORTED_DTYPES

    bands = image_band_indexes(ds)
    if not bands:
        raise RasterError(f"{what}: {ds.name} has no image band (only alpha); give an "
                          "RGB(A) or grey raster")
    if len(bands) == 2:
        raise RasterError(
            f"{what}: {ds.name} has 2 image bands and no band tagged alpha; give grey (1 "
            "band), grey+alpha (tag band 2: gdal_edit.py -colorinterp_2 alpha) or RGB(A)")
    dtypes = sorted({ds.dtypes[b - 1] for b in bands})
    if len(dtypes) != 1 or dtypes[0] not in SUPPORTED_DTYPES:
        raise RasterError(f"{what}: {ds.name} has data type(s) {dtypes}; use one of "
                          f"{', '.join(SUPPORTED_DTYPES)} for all bands")
