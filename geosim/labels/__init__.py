"""Cattle labels in map coordinates.

YOLO boxes (``class cx cy w h``, normalised to the image they label) and
GeoJSON/GeoPackage features in any CRS are read into one GeoDataFrame in the
site CRS, moved into the aligned frame, de-duplicated, and written back out as
RFC 7946 GeoJSON, a GeoPackage and YOLO files for every UAV tile and every
0.5 m tile. Paddock counts and movement between flights are queries on that
GeoDataFrame.

Modules
-------
yolo
    Parse, validate and format YOLO text (pure; one thin file reader).
georef
    Boxes <-> map polygons through an affine transform (pure).
sources
    Read a site's label sources into a GeoDataFrame (I/O).
tiles
    Map polygons -> clipped YOLO boxes for a tile (pure kernel).
dedupe
    One cow, one feature (pure on GeoDataFrames).
paddocks
    Cattle per paddock, counts and density per hectare.
movement
    One-to-one matching of cattle between two flights.
steps
    ``run_labels(site, out_dir)``: the pipeline step.
"""

from geosim.labels.yolo import CLASS_NAMES

__all__ = ["CLASS_NAMES"]
