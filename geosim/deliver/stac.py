"""A STAC catalogue of the run (pystac): one collection for the site, an item per flight
tile and one for the satellite scene, with relative hrefs so the folder can move.

Each item carries ``datetime`` (the acquisition), the projection extension
(``proj:epsg``, ``proj:transform``, ``proj:shape`` of the raster in the site CRS), a
bbox and geometry in EPSG:4326 (RFC 7946), and assets for the files a user or trainer
needs (UAV tile, degraded tile, YOLO label files, GeoJSON labels).

References
----------
STAC specification 1.x and the projection extension v1.1.0 (``proj:epsg``).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rasterio
from rasterio.warp import transform_geom
from shapely.geometry import box, mapping, shape

PROJECTION_V1 = "https://stac-extensions.github.io/projection/v1.1.0/schema.json"
COG_TYPE = "image/tiff; application=geotiff; profile=cloud-optimized"


@dataclass(frozen=True)
class RasterItem:
    """One raster to catalogue, with its acquisition time and extra assets."""

    id: str
    path: Path
    acquired: dt.datetime
    assets: dict[str, tuple[Path, str, str]]   # key -> (path, media type, role)
    properties: dict[str, Any]


def _item(spec: RasterItem) -> Any:
    import pystac

    with rasterio.open(spec.path) as ds:
        epsg = ds.crs.to_epsg()
        geom_site = mapping(box(*ds.bounds))
        geom = transform_geom(ds.crs, "EPSG:4326", geom_site, antimeridian_cutting=True,
                              precision=9)
        t, shape_rc = ds.transform, [ds.height, ds.width]
    item = pystac.Item(id=spec.id, geometry=geom, bbox=list(shape(geom).bounds),
                       datetime=spec.acquired.astimezone(dt.UTC), properties={
                           **spec.properties, "proj:epsg": epsg,
                           "proj:transform": [t.a, t.b, t.c, t.d, t.e, t.f],
                           "proj:shape": shape_rc},
                       stac_extensions=[PROJECTION_V1])
    for key, (path, media, role) in spec.assets.items():
        item.add_asset(key, pystac.Asset(href=str(path.resolve()), media_type=media,
                                         roles=[role]))
    return item


def write_stac(out_dir: Path, site_name: str, items: Sequence[RasterItem], *,
               description: str) -> Path:
    """Write ``out_dir/stac/`` (catalog.json, a collection, items); replaces an earlier one.

    Returns
    -------
    pathlib.Path
        ``out_dir/stac/catalog.json``.
    """
    import pystac

    stac_items = [_item(s) for s in items]
    bboxes = [i.bbox for i in stac_items]
    times = [i.datetime for i in stac_items]
    extent = pystac.Extent(
        pystac.SpatialExtent([[min(b[0] for b in bboxes), min(b[1] for b in bboxes),
                               max(b[2] for b in bboxes), max(b[3] for b in bboxes)]]),
        pystac.TemporalExtent([[min(times), max(times)]]))
    catalog = pystac.Catalog(id="geosim", description=description)
    collection = pystac.Collection(id=site_name, description=f"geosim run of site {site_name}",
                                   extent=extent, license="other")
    collection.add_items(stac_items)
    catalog.add_child(collection)
    final = out_dir / "stac"
    tmp = Path(tempfile.mkdtemp(prefix=".stac.", dir=out_dir))
    try:
        # hrefs are computed for the final location, then the folder is written aside
        catalog.normalize_hrefs(str(final.resolve()))
        catalog.make_all_asset_hrefs_relative()
        catalog.save(catalog_type=pystac.CatalogType.SELF_CONTAINED, dest_href=str(tmp))
        old = out_dir / f".stac.old.{os.getpid()}"
        if final.exists():
            final.rename(old)
        tmp.rename(final)
        shutil.rmtree(old, ignore_errors=True)
    finally:
        with contextlib.suppress(FileNotFoundError):
            shutil.rmtree(tmp)
    return final / "catalog.json"


__all__ = ["COG_TYPE", "PROJECTION_V1", "RasterItem", "write_stac"]
