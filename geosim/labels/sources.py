"""Reading label sources into one GeoDataFrame in the site CRS (the I/O layer).

A flight's labels (``labels`` in the site file) are one of

- a **YOLO folder** in LabelImg layout: ``classes.txt`` (one class name per
  line; line index = class id) and one ``<image stem>.txt`` per labelled image.
  ``<flight image stem>.txt`` labels the whole flight image; any other
  ``<stem>.txt`` labels a georeferenced patch image ``<stem>.tif`` (or
  ``.tiff``) found in the label folder or beside the flight image. Each file is
  georeferenced through its image's own transform, size and CRS.
- a **GeoJSON or GeoPackage** file in any CRS: one box polygon per cow, an
  optional class column (``class_name``, ``class`` or ``label``; default
  ``cattle``). A GeoPackage with several layers must have one named ``cattle``.

Either way the geometries are in the frame of the flight's *stated*
georeference (what a person labelling in QGIS sees); the pipeline step moves
them into the aligned frame afterwards. Every label is checked: a box outside
its image is an error, as is a vector label whose centre lies outside the
flight image or that is not a polygon.

Output columns (see :data:`LABEL_COLUMNS`): ``flight``, ``acquired`` (ISO 8601
text), ``class_name``, ``source_file``, ``source_line`` (line in a YOLO file,
1-based feature number in a vector file), ``width_m``, ``height_m`` (box sides
in site-CRS metres; width along image columns for YOLO boxes, the more
east-west side for polygons), ``source_kind``; geometry = the box polygon.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import geopandas as gpd
import numpy as np
import pyogrio
import shapely
from pyproj import CRS

from geosim.config import FlightConfig
from geosim.errors import CRSError, InputFileError, LabelError
from geosim.io.georef import Georef
from geosim.io.paths import relative_if_inside
from geosim.io.raster import open_raster
from geosim.labels.georef import (
    boxes_to_polygons,
    linear_unit_m,
    polygon_sides,
    reproject_geometries,
)
from geosim.labels.yolo import CLASS_NAMES, read_classes_file, read_yolo_file

#: Columns of a labels GeoDataFrame, besides ``geometry``.
LABEL_COLUMNS: tuple[str, ...] = ("flight", "acquired", "class_name", "source_file",
                                  "source_line", "source_kind", "width_m", "height_m")

VECTOR_SUFFIXES = (".geojson", ".json", ".gpkg")
PATCH_IMAGE_SUFFIXES = (".tif", ".tiff", ".TIF", ".TIFF")
CLASS_COLUMNS = ("class_name", "class", "label")


def read_image_georef(path: str | os.PathLike[str], *, what: str) -> Georef:
    """Read only the header of a raster: transform, size and CRS."""
    with open_raster(path, what=what) as ds:
        return Georef.of_dataset(ds, path=path)


def _frame(flight: FlightConfig, geoms: np.ndarray, *, class_names: Sequence[str],
           source_file: Sequence[str], source_line: Sequence[int], source_kind: str,
           sides_m: np.ndarray, crs: CRS) -> gpd.GeoDataFrame:
    n = len(geoms)
    return gpd.GeoDataFrame(
        {
            "flight": [flight.id] * n,
            "acquired": [flight.acquired.isoformat()] * n,
            "class_name": list(class_names),
            "source_file": list(source_file),
            "source_line": np.asarray(source_line, dtype=np.int64),
            "source_kind": [source_kind] * n,
            "width_m": sides_m[:, 0] if n else np.zeros(0),
            "height_m": sides_m[:, 1] if n else np.zeros(0),
        },
        geometry=gpd.GeoSeries(list(geoms), crs=crs),
        crs=crs,
    )


def empty_labels(crs: CRS | str) -> gpd.GeoDataFrame:
    """An empty labels GeoDataFrame with the standard columns."""
    cols = {c: [] for c in LABEL_COLUMNS}
    return gpd.GeoDataFrame(cols, geometry=gpd.GeoSeries([], crs=crs), crs=crs)


def _corner_sides(geoms: np.ndarray) -> np.ndarray:
    """Side lengths (CRS units) of 4-corner polygons: edge 0-1 (width) and 1-2 (height)."""
    if len(geoms) == 0:
        return np.zeros((0, 2))
    xy = shapely.get_coordinates(geoms).reshape(len(geoms), 5, 2)
    return np.column_stack([np.hypot(*(xy[:, 1] - xy[:, 0]).T),
                            np.hypot(*(xy[:, 2] - xy[:, 1]).T)])


def yolo_file_to_frame(label_file: Path, image: Georef, class_list: Sequence[str],
                       flight: FlightConfig, site_crs: CRS, *,
                       base_dir: Path | None = None,
                       known_classes: Sequence[str] = CLASS_NAMES) -> gpd.GeoDataFrame:
    """One YOLO file of one image -> labels in the site CRS (stated frame).

    Raises
    ------
    LabelError
        Malformed line or box outside its image (file and line named).
    """
    yolo = read_yolo_file(label_file, class_list=class_list, known_classes=known_classes)
    polys = boxes_to_polygons(yolo.boxes, image.transform, image.width_px, image.height_px)
    polys = reproject_geometries(polys, image.crs, site_crs)
    sides_m = _corner_sides(polys) * linear_unit_m(site_crs)
    name = relative_if_inside(label_file, base_dir)
    return _frame(flight, polys, class_names=yolo.class_names, source_file=[name] * len(yolo),
                  source_line=yolo.lines, source_kind="yolo", sides_m=sides_m, crs=site_crs)


def _patch_image(stem: str, folder: Path, flight: FlightConfig) -> Path | None:
    for where in (folder, flight.image.parent):
        for suffix in PATCH_IMAGE_SUFFIXES:
            candidate = where / f"{stem}{suffix}"
            if candidate.is_file():
                return candidate
    return None


def read_yolo_folder(folder: Path, flight: FlightConfig, site_crs: CRS, *,
                     base_dir: Path | None = None,
                     known_classes: Sequence[str] = CLASS_NAMES) -> gpd.GeoDataFrame:
    """Read a LabelImg YOLO folder of one flight (see module docstring)."""
    class_list = read_classes_file(folder / "classes.txt")
    label_files = sorted(p for p in folder.glob("*.txt") if p.name != "classes.txt")
    if not label_files:
        raise LabelError(f"{folder}: no YOLO label files; expected {flight.image.stem}.txt "
                         f"(labels of {flight.image.name}) beside classes.txt")
    flight_image = read_image_georef(flight.image, what=f"flight {flight.id} image")
    frames = []
    for label_file in label_files:
        if label_file.stem == flight.image.stem:
            image = flight_image
        else:
            found = _patch_image(label_file.stem, folder, flight)
            if found is None:
                raise LabelError(
                    f"{label_file}: no image for this label file: it is not named after the "
                    f"flight image ({flight.image.stem}.txt) and there is no georeferenced "
                    f"{label_file.stem}.tif in {folder} or {flight.image.parent}; rename it "
                    "or put its patch image there")
            image = read_image_georef(found, what=f"patch image of {label_file}")
        frames.append(yolo_file_to_frame(label_file, image, class_list, flight, site_crs,
                                         base_dir=base_dir, known_classes=known_classes))
    return _concat(frames, site_crs)


def _vector_layer(path: Path) -> str | None:
    try:
        layers = pyogrio.list_layers(path)
    except Exception as exc:  # pyogrio raises DataSourceError and friends
        raise LabelError(f"{path}: cannot be read as GeoJSON/GeoPackage ({exc}); give a "
                         "valid vector file") from exc
    names = [str(name) for name, _ in layers]
    if len(names) <= 1:
        return names[0] if names else None
    if "cattle" in names:
        return "cattle"
    raise LabelError(f"{path}: has layers {', '.join(names)}; name the cattle layer 'cattle'")


def _class_values(gdf: gpd.GeoDataFrame, path: Path, known: Sequence[str]) -> list[str]:
    column = next((c for c in CLASS_COLUMNS if c in gdf.columns), None)
    if column is None:
        return [known[0]] * len(gdf)
    values = []
    for i, v in enumerate(gdf[column], start=1):
        name = str(v).strip() if v is not None else ""
        if name not in known:
            raise LabelError(f"{path}: feature {i}: {column} = {v!r} is not a known class "
                             f"(known: {', '.join(known)}); fix the attribute or drop the "
                             "feature")
        values.append(name)
    return values


def read_vector_labels(path: Path, flight: FlightConfig, site_crs: CRS, *,
                       base_dir: Path | None = None,
                       known_classes: Sequence[str] = CLASS_NAMES) -> gpd.GeoDataFrame:
    """Read GeoJSON / GeoPackage label polygons (any CRS) of one flight.

    Raises
    ------
    LabelError
        No CRS, a geometry that is not a non-empty valid polygon, an unknown class,
        or a label whose centre lies outside the flight image (feature named).
    """
    layer = _vector_layer(path)
    try:
        gdf = gpd.read_file(path, layer=layer, engine="pyogrio")
    except Exception as exc:
        raise LabelError(f"{path}: cannot be read ({exc}); give a valid GeoJSON/GeoPackage"
                         ) from exc
    if gdf.crs is None:
        raise LabelError(f"{path}: has no CRS; assign the CRS it was digitised in "
                         "(GeoJSON without a crs member is read as EPSG:4326)")
    classes = _class_values(gdf, path, known_classes)
    geoms = np.asarray(gdf.geometry.values, dtype=object)
    for i, g in enumerate(geoms, start=1):
        if g is None or g.is_empty:
            raise LabelError(f"{path}: feature {i} has no geometry; delete it or draw its box")
        if g.geom_type == "MultiPolygon" and len(g.geoms) == 1:
            geoms[i - 1] = g = g.geoms[0]
        if g.geom_type != "Polygon":
            raise LabelError(f"{path}: feature {i} is a {g.geom_type}; cattle labels must be "
                             "box polygons (one per cow)")
        if not g.is_valid or g.area <= 0:
            raise LabelError(f"{path}: feature {i} is not a valid polygon of positive area "
                             f"({shapely.is_valid_reason(g)}); redraw the box")
    try:
        geoms = reproject_geometries(geoms, CRS.from_user_input(gdf.crs), site_crs)
    except CRSError as exc:
        raise LabelError(f"{path}: {exc}") from exc
    image = read_image_georef(flight.image, what=f"flight {flight.id} image")
    outline = reproject_geometries(np.array([image.outline], dtype=object), image.crs,
                                   site_crs)[0]
    inside = shapely.contains_xy(outline, *shapely.get_coordinates(
        shapely.centroid(geoms)).T) if len(geoms) else np.zeros(0, bool)
    if not np.all(inside):
        i = int(np.flatnonzero(~inside)[0]) + 1
        raise LabelError(f"{path}: feature {i} lies outside the image of flight {flight.id} "
                         f"({flight.image.name}); check the file's CRS and that it labels "
                         "this flight")
    sides_m = polygon_sides(geoms) * linear_unit_m(site_crs)
    kind = "gpkg" if path.suffix.lower() == ".gpkg" else "geojson"
    name = relative_if_inside(path, base_dir)
    return _frame(flight, geoms, class_names=classes, source_file=[name] * len(geoms),
                  source_line=np.arange(1, len(geoms) + 1), source_kind=kind,
                  sides_m=sides_m, crs=site_crs)


def read_flight_labels(flight: FlightConfig, site_crs: CRS | str, *,
                       base_dir: Path | None = None,
                       known_classes: Sequence[str] = CLASS_NAMES) -> gpd.GeoDataFrame:
    """Read one flight's labels (YOLO folder or vector file) into the site CRS.

    Parameters
    ----------
    flight
        The flight; ``flight.labels`` must be set.
    site_crs
        The projected site CRS (metres); output geometries are in it, in the
        flight's stated frame.
    base_dir
        Folder that ``source_file`` is written relative to (the site file's folder).

    Returns
    -------
    geopandas.GeoDataFrame
        Columns :data:`LABEL_COLUMNS` and the box polygons.
    """
    crs = CRS.from_user_input(site_crs)
    path = flight.labels
    if path is None:
        return empty_labels(crs)
    path = Path(path)
    if path.is_dir():
        return read_yolo_folder(path, flight, crs, base_dir=base_dir,
                                known_classes=known_classes)
    if not path.exists():
        raise InputFileError(f"flight {flight.id}: labels {path} do not exist; fix the path")
    if path.suffix.lower() in VECTOR_SUFFIXES:
        return read_vector_labels(path, flight, crs, base_dir=base_dir,
                                  known_classes=known_classes)
    raise LabelError(f"flight {flight.id}: labels {path} are neither a YOLO folder nor a "
                     f"{'/'.join(VECTOR_SUFFIXES)} file; give one of those")


def _concat(frames: Sequence[gpd.GeoDataFrame], crs: CRS) -> gpd.GeoDataFrame:
    frames = [f for f in frames if len(f)]
    if not frames:
        return empty_labels(crs)
    import pandas as pd

    return gpd.GeoDataFrame(pd.concat(frames, ignore_index=True), crs=crs)


def read_site_labels(flights: Sequence[FlightConfig], site_crs: CRS | str, *,
                     base_dir: Path | None = None) -> gpd.GeoDataFrame:
    """Read every labelled flight; all files are validated before anything is returned."""
    crs = CRS.from_user_input(site_crs)
    return _concat([read_flight_labels(f, crs, base_dir=base_dir)
                    for f in flights if f.labels is not None], crs)


# ---------------------------------------------------------------- outputs read back


def read_cattle(path: str | os.PathLike[str]) -> gpd.GeoDataFrame:
    """Read cattle features written by the labels step (GPKG layer ``cattle`` or GeoJSON).

    Any polygon or point file with a ``flight`` column works (e.g. edited in QGIS).
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: cattle labels not found; give labels/cattle.gpkg (or "
                             "cattle.geojson) from 'geosim labels'")
    layer = _vector_layer(p)
    gdf = gpd.read_file(p, layer=layer, engine="pyogrio")
    if gdf.crs is None:
        raise LabelError(f"{p}: has no CRS; assign one")
    if "flight" not in gdf.columns:
        raise LabelError(f"{p}: has no 'flight' column; give the cattle layer written by "
                         "'geosim labels'")
    return gdf


def read_paddocks(path: str | os.PathLike[str], *, name_column: str = "name",
                  ) -> gpd.GeoDataFrame:
    """Read paddock polygons (any CRS) with a name column.

    A missing name column is a :class:`~geosim.errors.LabelError` listing the columns.
    """
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: paddocks file not found; give a GeoJSON/GPKG of paddock "
                             "polygons")
    try:
        gdf = gpd.read_file(p, engine="pyogrio")
    except Exception as exc:
        raise InputFileError(f"{p}: cannot be read as a vector file ({exc})") from exc
    if gdf.crs is None:
        raise CRSError(f"{p}: paddocks have no CRS; assign the CRS they were drawn in")
    if name_column not in gdf.columns:
        columns = [c for c in gdf.columns if c != gdf.geometry.name]
        raise LabelError(f"{p}: paddocks have no '{name_column}' column; columns there are: "
                         f"{', '.join(map(str, columns)) or '(none)'}; give the one holding "
                         "paddock names with --name-column")
    return gdf
