"""Files of the augmentation step: pairs.csv rows, tiles, YOLO labels and outputs.

Inputs follow the run-folder layout (:class:`geosim.rundir.RunDir`): ``DIR/pairs.csv`` lists the
pairs, ``DIR/tiles/<flight>/<tile_id>.tif`` and
``DIR/degraded/<flight>/<tile_id>.tif`` hold the UAV and 0.5 m tiles, and
``DIR/labels/yolo/<flight>/<tile_id>.txt`` / ``DIR/labels/yolo_0.5m/...`` their
YOLO labels (``class cx cy w h`` normalised to the tile).

Outputs. A geometric augmentation takes the pixels off the map grid, so such
images are written *without* a geotransform or CRS; their metadata says so
(``GEOSIM_ON_MAP_GRID=false``) and names the source tile, its georeference and
the transform chain (for affine chains also the exact output-pixel →
source-pixel matrix). Outputs changed only photometrically keep the source
tile's georeference (``GEOSIM_ON_MAP_GRID=true``).
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import rasterio
from affine import Affine

from geosim.augment import tiff_writer
from geosim.augment.geometry import Boxes
from geosim.augment.pipeline import AugImage
from geosim.errors import InputFileError, LabelError, OutputError, RasterError
from geosim.io.atomic import atomic_path, write_text
from geosim.io.georef import Georef
from geosim.io.raster import (
    BLOCK_PX,
    alpha_band_index,
    image_band_indexes,
    naming_read_failures,
    open_raster,
    read_valid_mask,
)
from geosim.prepare.pairs import COLUMNS
from geosim.rundir import YOLO_SUBDIRS, RunDir

__all__ = [
    "PAIRS_COLUMNS",
    "Georef",
    "PairRow",
    "Tile",
    "read_pairs",
    "read_preview",
    "read_tile",
    "read_yolo",
    "tile_and_label_paths",
    "write_csv",
    "write_image",
    "write_yolo",
]

#: Columns of pairs.csv (:data:`geosim.prepare.pairs.COLUMNS`).
PAIRS_COLUMNS = COLUMNS

#: Tile resolutions of a run folder (:class:`geosim.rundir.RunDir`).
RESOLUTIONS = tuple(YOLO_SUBDIRS)


@dataclass(frozen=True)
class PairRow:
    """One row of pairs.csv (paths as written: relative to the run folder)."""

    pair_id: str
    tile_id: str
    flight_a: str
    flight_b: str
    path_a: str
    path_b: str
    bounds: tuple[float, float, float, float]
    crs: str
    line: int


@dataclass(frozen=True)
class Tile:
    """A tile read for augmentation."""

    path: Path
    data: AugImage
    georef: Georef | None
    band_descriptions: tuple[str | None, ...]


def read_pairs(pairs_csv: str | os.PathLike[str]) -> list[PairRow]:
    """Read and check pairs.csv.

    Raises
    ------
    InputFileError
        The file does not exist.
    LabelError
        A column is missing or a row is malformed (message names the line).
    """
    p = Path(pairs_csv)
    if not p.is_file():
        raise InputFileError(f"pairs manifest {p} does not exist; give the pairs.csv of a run "
                             "folder (geosim run SITE.toml --out DIR writes DIR/pairs.csv)")
    with open(p, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in PAIRS_COLUMNS if c not in (reader.fieldnames or [])]
        if missing:
            raise LabelError(f"pairs manifest {p}: missing column(s) {', '.join(missing)}; "
                             f"expected {','.join(PAIRS_COLUMNS)}")
        rows = []
        for line, rec in enumerate(reader, start=2):
            try:
                bounds = tuple(float(rec[k]) for k in ("minx", "miny", "maxx", "maxy"))
            except (TypeError, ValueError):
                raise LabelError(f"pairs manifest {p}, line {line}: bounds are not numbers; "
                                 "regenerate pairs.csv") from None
            for k in ("pair_id", "tile_id", "flight_a", "flight_b", "path_a", "path_b"):
                if not rec.get(k):
                    raise LabelError(f"pairs manifest {p}, line {line}: empty {k}; "
                                     "regenerate pairs.csv")
            rows.append(PairRow(rec["pair_id"], rec["tile_id"], rec["flight_a"], rec["flight_b"],
                                rec["path_a"], rec["path_b"], bounds,  # type: ignore[arg-type]
                                rec["crs"], line))
    return rows


def tile_and_label_paths(run_dir: Path, row: PairRow, resolution: str
                         ) -> tuple[Path, Path, Path, Path]:
    """Image and label paths of both images of a pair at ``resolution`` (``uav``/``0.5m``).

    UAV images come from the pairs.csv paths; 0.5 m ones from
    ``degraded/<flight>/<tile_id>.tif``.
    """
    run = RunDir.of(run_dir)
    if resolution not in RESOLUTIONS:
        raise ValueError(f"resolution must be one of {', '.join(RESOLUTIONS)}")
    if resolution == "uav":
        img_a, img_b = run.root / row.path_a, run.root / row.path_b
    else:
        img_a = run.tile_at(resolution, row.flight_a, row.tile_id)
        img_b = run.tile_at(resolution, row.flight_b, row.tile_id)
    return (img_a, img_b, run.yolo_file(resolution, row.flight_a, row.tile_id),
            run.yolo_file(resolution, row.flight_b, row.tile_id))


def read_tile(path: Path, *, what: str) -> Tile:
    """Read a tile's image bands and valid mask (a tile is small enough to hold whole).

    The bands are read straight into a pixel-interleaved ``(rows, cols, bands)`` buffer
    (the layout of the file, of OpenCV and of the outputs), handed on as its
    ``(bands, rows, cols)`` view, so neither the read nor the pipeline changes the layout.
    Float64 rasters are read as float32; other unsupported dtypes are refused.
    """
    from rasterio.enums import MaskFlags

    with open_raster(path, what=what, require_crs=False) as ds:
        bands = image_band_indexes(ds)
        dtype = np.dtype(ds.dtypes[bands[0] - 1])
        georef = None
        if ds.crs is not None and ds.transform != Affine.identity():
            georef = Georef.of_dataset(ds, path=path)
        if dtype == np.float64:
            dtype = np.dtype(np.float32)
        if dtype not in (np.uint8, np.uint16, np.int16, np.float32):
            raise RasterError(f"{what}: {path} has data type {dtype}; augmentation supports "
                              "uint8, uint16, int16 and float32 images; convert it first")
        hwc = np.empty((ds.height, ds.width, len(bands)), dtype)
        with naming_read_failures(path):
            ds.read(bands, out=np.moveaxis(hwc, -1, 0))
            if alpha_band_index(ds) is None and all(
                    MaskFlags.all_valid in ds.mask_flag_enums[i - 1] for i in bands):
                valid = np.ones(hwc.shape[:2], bool)  # no mask, alpha or nodata
            else:
                valid = read_valid_mask(ds)
        names = tuple(ds.descriptions[i - 1] for i in bands)
    return Tile(path, AugImage(np.moveaxis(hwc, -1, 0), valid), georef, names)


def read_yolo(path: Path, shape: tuple[int, int]) -> Boxes | None:
    """Read YOLO boxes (``class cx cy w h``, normalised) for an image of ``shape``.

    Returns ``None`` when the file does not exist (no labels for that tile).

    Raises
    ------
    LabelError
        A malformed line (the message names the file and line).
    """
    if not path.is_file():
        return None
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        parts = line.split()
        if not parts:
            continue
        try:
            if len(parts) != 5:
                raise ValueError(f"{len(parts)} fields")
            cls = int(parts[0])
            vals = [float(v) for v in parts[1:]]
            if cls < 0 or not all(math.isfinite(v) for v in vals):
                raise ValueError("negative class or non-finite value")
            if vals[2] <= 0 or vals[3] <= 0:
                raise ValueError("width and height must be > 0")
        except ValueError as exc:
            raise LabelError(f"YOLO label file {path}, line {n}: {line.strip()!r} is not "
                             f"'class cx cy w h' ({exc}); fix or delete the line") from None
        rows.append([cls, *vals])
    return Boxes.from_yolo(np.array(rows).reshape(-1, 5), shape)


def write_yolo(path: Path, boxes: Boxes, shape: tuple[int, int]) -> Path:
    """Write boxes as YOLO ``class cx cy w h`` normalised to ``shape``, atomically.

    An image without boxes gets an empty file (YOLO's "background image").
    """
    lines = [f"{int(r[0])} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} {r[4]:.6f}\n"
             for r in boxes.to_yolo(shape)]
    return write_text(path, "".join(lines))


#: ``--compress`` choices for augmented GeoTIFFs: GDAL creation options of each (the direct
#: writer, :mod:`geosim.augment.tiff_writer`, encodes the same with ISA-L). Deflate level 1
#: with the horizontal predictor is lossless and about 40 % of the raw size of an augmented
#: image; ``none`` costs no encoding and is the fastest to load (2.5× the disk).
TIFF_COMPRESSION: dict[str, dict[str, Any]] = {
    "deflate": {"compress": "deflate", "zlevel": 1},
    "none": {"compress": "none"},
}


def write_image(path: Path, img: AugImage, *, georef: Georef | None,
                tags: Mapping[str, str], band_descriptions: Sequence[str | None] = (),
                compress: str = "deflate") -> Path:
    """Write an augmented image as a tiled GeoTIFF (``.tif``) or a PNG (``.png``), atomically.

    The GeoTIFF is a plain tiled, pixel-interleaved GeoTIFF with an internal valid mask,
    not a COG: augmented images are training data, read whole by a trainer, and most
    carry no georeference, so overviews would serve nobody (docs/augmentation.md).

    Parameters
    ----------
    path
        Output path; the suffix picks the format.
    img
        Image and valid mask (written as an internal mask band, or PNG alpha). The image
        may be a ``(bands, rows, cols)`` view of a pixel-interleaved buffer (as the
        pipeline returns it): it is read through its strides, no copy.
    georef
        Georeference to write, or ``None`` to write none (pixels off the map grid).
    tags
        Metadata tags (GeoTIFF only; PNG outputs are described by the run's CSVs
        and per-pair JSON).
    band_descriptions
        Band names (GeoTIFF).
    compress
        GeoTIFF compression, a key of :data:`TIFF_COMPRESSION`.

    Notes
    -----
    Non-georeferenced uint8/uint16 images of 1 or 3 bands (nearly every geometric
    output) are written by :mod:`geosim.augment.tiff_writer` (ISA-L deflate level 1,
    the same file layout), everything else by GDAL (:func:`write_geotiff_gdal`, libdeflate
    level 1); both are lossless and read back identically.
    """
    if path.suffix.lower() == ".png":
        return _write_png(path, img)
    if compress not in TIFF_COMPRESSION:
        raise ValueError(f"compress must be one of {', '.join(TIFF_COMPRESSION)}")
    arr = img.image
    desc = [d or f"band {i}" for i, d in enumerate(band_descriptions, start=1)]
    if tiff_writer.supports(arr, georeferenced=georef is not None, compress=compress):
        # the same layout GDAL writes, encoded without GDAL's block cache and with ISA-L
        # deflate (otherwise the dominant cost of an augmented pair; docs/augmentation.md)
        with atomic_path(path) as tmp:
            tiff_writer.write_plain_tiff(tmp, np.moveaxis(arr, 0, -1), img.mask, tags=tags,
                                         band_descriptions=desc, compress=compress)
        return path
    with atomic_path(path) as tmp:
        write_geotiff_gdal(tmp, img, georef=georef, tags=tags, band_descriptions=desc,
                           compress=compress)
    return path


def write_geotiff_gdal(path: Path, img: AugImage, *, georef: Georef | None,
                       tags: Mapping[str, str], band_descriptions: Sequence[str],
                       compress: str = "deflate") -> None:
    """:func:`write_image`'s GeoTIFF written by GDAL (georeferenced or other outputs).

    Not atomic (the caller is); ``band_descriptions``: one name per band, or none.
    """
    arr = img.image
    count, rows, cols = arr.shape
    tiled = rows >= BLOCK_PX and cols >= BLOCK_PX
    profile: dict[str, Any] = {
        "driver": "GTiff", "width": cols, "height": rows, "count": count,
        "dtype": arr.dtype.name, "interleave": "pixel", "tiled": tiled,
        "BIGTIFF": "IF_SAFER", **TIFF_COMPRESSION[compress],
    }
    if compress != "none":
        profile["predictor"] = 3 if arr.dtype.kind == "f" else 2
    if tiled:
        profile.update(blockxsize=BLOCK_PX, blockysize=BLOCK_PX)
    if georef is not None:
        profile.update(crs=georef.rasterio_crs(), transform=georef.transform)
    with (_quiet_georef(), rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True),
          rasterio.open(path, "w", **profile) as dst):
        for i, d in enumerate(band_descriptions, start=1):
            dst.set_band_description(i, d)
        dst.update_tags(**dict(tags))
        dst.write(arr)
        dst.write_mask(np.multiply(img.mask.view(np.uint8), 255, dtype=np.uint8))


@contextlib.contextmanager
def _quiet_georef():  # type: ignore[no-untyped-def]
    """Silence rasterio's NotGeoreferencedWarning: writing no georeference is the intent."""
    import warnings

    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        yield


def _write_png(path: Path, img: AugImage) -> Path:
    arr = img.image
    if arr.dtype not in (np.uint8, np.uint16) or arr.shape[0] not in (1, 3):
        raise OutputError(f"{path}: PNG holds 1 or 3 bands of uint8/uint16, not "
                          f"{arr.shape[0]} bands of {arr.dtype}; write GeoTIFF (--format tif)")
    hwc = np.moveaxis(arr, 0, -1)
    if not hwc.flags.c_contiguous:
        hwc = np.ascontiguousarray(hwc)
    # RGB (or grey) -> BGRA with alpha = full scale, then alpha 0 where invalid (the
    # colour there is already 0)
    code = cv2.COLOR_GRAY2BGRA if hwc.shape[-1] == 1 else cv2.COLOR_RGB2BGRA
    bgra = cv2.cvtColor(hwc, code)
    if not img.mask.all():
        cv2.bitwise_and(bgra, 0, dst=bgra, mask=np.logical_not(img.mask).view(np.uint8))
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), bgra, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
            raise OutputError(f"{path}: PNG encoding failed; check the folder is writable")
    return path


def write_csv(path: Path, columns: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> Path:
    """Write rows (dicts) as CSV with the given columns, atomically; missing cells empty."""
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="raise",
                               lineterminator="\n")
            w.writeheader()
            for r in rows:
                w.writerow({k: _cell(v) for k, v in r.items()})
    return path


def _cell(v: Any) -> Any:
    if isinstance(v, float):
        return repr(v)
    if isinstance(v, list | dict):
        return json.dumps(v)
    return v


def read_preview(path: Path, *, max_side_px: int = 1500) -> tuple[np.ndarray, np.ndarray, float]:
    """Read any GDAL-readable image (GeoTIFF, PNG, JPEG), decimated for a figure.

    Parameters
    ----------
    path
        Image file (no georeference needed).
    max_side_px
        Longest side of the returned arrays, pixels (averaged decimation).

    Returns
    -------
    image, mask, factor
        ``(bands, rows, cols)`` image bands, ``(rows, cols)`` bool valid mask, and
        the decimation factor (source pixels per returned pixel).
    """
    from rasterio.enums import Resampling

    with _quiet_georef(), open_raster(path, what="image to warp", require_crs=False) as ds:
        factor = max(1.0, max(ds.width, ds.height) / max_side_px)
        shape = (max(1, round(ds.height / factor)), max(1, round(ds.width / factor)))
        bands = image_band_indexes(ds)[:3]
        image = ds.read(bands, out_shape=(len(bands), *shape), resampling=Resampling.average)
        if image.dtype not in (np.uint8, np.uint16, np.int16, np.float32):
            image = image.astype(np.float32)
        alpha = alpha_band_index(ds)
        if alpha is not None:
            mask = ds.read(alpha, out_shape=shape, resampling=Resampling.nearest) > 0
        else:
            mask = ds.dataset_mask(out_shape=shape, resampling=Resampling.nearest) > 0
    return image, mask, factor
