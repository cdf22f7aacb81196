"""Reading and writing GeoTIFFs with geosim's conventions (docs/outputs.md).

Outputs are Cloud-Optimized GeoTIFFs (internal overviews), tiled and compressed, with
CRS, transform, nodata and/or an internal mask, band descriptions and provenance tags,
written atomically.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.enums import MaskFlags
from rasterio.errors import NotGeoreferencedWarning, RasterioIOError
from rasterio.windows import Window

from geosim.errors import InputFileError, RasterError
from geosim.io.cog import WholeRaster, cog_writer
from geosim.io.overviews import LEVEL1_BINOMIAL, LEVEL1_TAG
from geosim.io.paths import relative_if_inside
from geosim.scratch import scratch_array

BLOCK_PX = 256


def open_raster(path: str | os.PathLike[str], *, what: str = "raster",
                require_crs: bool = True) -> rasterio.DatasetReader:
    """Open a raster for reading, with errors that name the file and the fix.

    Parameters
    ----------
    path
        Raster file path.
    what
        What the raster is for, used in messages (``"flight PA1"``, ``"satellite scene"``).
    require_crs
        Refuse a raster without a CRS or without a georeferencing transform.
    """
    p = Path(path)
    if not p.exists():
        raise InputFileError(f"{what}: {p} does not exist; check the path")
    try:
        with warnings.catch_warnings():
            # a missing georeference is reported below as a clear error instead
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(p)
    except RasterioIOError as exc:
        raise RasterError(f"{what}: {p} cannot be read as a raster ({exc}); "
                          "give a GeoTIFF or another GDAL-readable raster") from exc
    if require_crs:
        if ds.crs is None:
            ds.close()
            raise RasterError(f"{what}: {p} has no CRS; assign one (e.g. gdal_edit.py -a_srs "
                              "EPSG:xxxx) before using it")
        if ds.transform == Affine.identity():
            ds.close()
            raise RasterError(f"{what}: {p} has no georeferencing transform; georeference it "
                              "before using it")
    return ds


def alpha_band_index(ds: rasterio.DatasetReader) -> int | None:
    """1-based index of the alpha band, or ``None``."""
    from rasterio.enums import ColorInterp

    for i, ci in enumerate(ds.colorinterp, start=1):
        if ci == ColorInterp.alpha:
            return i
    if ds.count == 4 and ds.dtypes[0] == "uint8":
        return 4  # RGBA written without colour interpretation
    return None


def image_band_indexes(ds: rasterio.DatasetReader) -> list[int]:
    """1-based indexes of the image bands (all bands except alpha)."""
    alpha = alpha_band_index(ds)
    return [i for i in range(1, ds.count + 1) if i != alpha]


def read_valid_mask(ds: rasterio.DatasetReader, window: Window | None = None, *,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Valid-data mask (True = valid) from alpha, nodata or the internal mask.

    GDAL's dataset mask combines all three; a pixel is valid when it is non-zero.

    Parameters
    ----------
    out
        Bool (rows, cols) array to write the mask into (e.g. one reused from tile to
        tile, :mod:`geosim.scratch`); the raw mask is then decoded into a reused buffer
        too, so no new memory is touched.
    """
    alpha = alpha_band_index(ds)
    if out is None:
        raw = ds.read(alpha, window=window) if alpha is not None else \
            ds.dataset_mask(window=window)
        return raw > 0
    if alpha is not None:  # in the alpha band's own type: a cast could round 0 < a < 1 to 0
        raw = scratch_array("raster.read_valid_mask", out.shape, ds.dtypes[alpha - 1])
        ds.read(alpha, window=window, out=raw)
    elif all(MaskFlags.per_dataset in flags for flags in ds.mask_flag_enums):
        raw = scratch_array("raster.read_valid_mask", out.shape, np.uint8)
        ds.read_masks(1, window=window, out=raw)  # every band's mask is the dataset mask
    else:
        raw = ds.dataset_mask(window=window)
    return np.greater(raw, 0, out=out)


@dataclass(frozen=True)
class RasterData:
    """Pixels read from a raster, with everything needed to place and write them again.

    The read edge of geosim (modelled on rio-tiler's ``ImageData``): kernels take the
    plain arrays (``array``, ``valid``), I/O code keeps the rest with them.

    Attributes
    ----------
    array
        Image bands, bands first ``(bands, rows, cols)``; alpha is not an image band.
    valid
        ``(rows, cols)`` bool, True where the pixel holds data (alpha, nodata or mask).
    transform
        Pixel-corner -> map affine of ``array`` (of the window when one was read).
    crs
        The raster's CRS (None when it has none).
    band_names
        Band descriptions, one per image band (None where unset).
    nodata
        The nodata value of the file, if any.
    path
        The file read.
    """

    array: np.ndarray
    valid: np.ndarray
    transform: Affine
    crs: CRS | None
    band_names: tuple[str | None, ...]
    nodata: float | None = None
    path: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return self.valid.shape  # type: ignore[return-value]


def read_window(ds: rasterio.DatasetReader, window: Window | None = None, *,
                bands: Sequence[int] | None = None, max_bands: int | None = None,
                out_dtype: Any = None, boundless: bool = False,
                path: str | os.PathLike[str] | None = None, out: np.ndarray | None = None,
                valid_out: np.ndarray | None = None) -> RasterData:
    """Read image bands and the valid mask of an opened raster (or of a window of it).

    Parameters
    ----------
    ds
        An opened rasterio dataset (:func:`open_raster`).
    window
        Only this window (default: the whole raster).
    bands
        1-based band indexes (default: every image band, alpha excluded).
    max_bands
        Keep at most this many of those bands (``3``: RGB of an RGB + NIR raster).
    out_dtype
        Data type to read into (default: the file's).
    boundless
        Allow a window that reaches outside the raster: pixels outside read as 0 and
        invalid (the first band's mask decides validity there).
    path
        Recorded in :attr:`RasterData.path` (default: the dataset's name).
    out, valid_out
        Arrays to decode the image bands ``(bands, rows, cols)``, of ``out_dtype`` or the
        file's type, and the bool mask ``(rows, cols)`` into, instead of new ones (e.g.
        reused from tile to tile, :mod:`geosim.scratch`); not for boundless reads.
    """
    idx = list(bands) if bands is not None else image_band_indexes(ds)
    if max_bands is not None:
        idx = idx[:max_bands]
    outside = window is not None and boundless and not (
        window.col_off >= 0 and window.row_off >= 0
        and window.col_off + window.width <= ds.width
        and window.row_off + window.height <= ds.height)
    if outside:
        if out is not None or valid_out is not None:
            raise ValueError("out / valid_out are not supported for a boundless read")
        array = ds.read(idx, window=window, boundless=True, fill_value=0, out_dtype=out_dtype)
        valid = ds.read_masks(1, window=window, boundless=True) > 0
    else:
        array = ds.read(idx, window=window, out_dtype=out_dtype, out=out)
        valid = read_valid_mask(ds, window, out=valid_out)
    return RasterData(
        array=array, valid=valid,
        transform=ds.window_transform(window) if window is not None else ds.transform,
        crs=ds.crs, band_names=tuple(ds.descriptions[i - 1] for i in idx),
        nodata=ds.nodata, path=Path(path if path is not None else ds.name))


def read_raster(path: str | os.PathLike[str], *, what: str = "raster",
                window: Window | None = None, bands: Sequence[int] | None = None,
                max_bands: int | None = None, out_dtype: Any = None,
                boundless: bool = False, require_crs: bool = True,
                reuse_buffers: bool = False) -> RasterData:
    """Open ``path`` (:func:`open_raster`) and :func:`read_window` it.

    Parameters
    ----------
    path
        The raster.
    what
        Words naming it in error messages (``"UAV tile"``).
    window, bands, max_bands, out_dtype, boundless
        As for :func:`read_window`.
    require_crs
        Refuse a raster without a CRS (:func:`open_raster`).
    reuse_buffers
        Decode a whole raster (no ``window``) into this thread's reused scratch arrays
        (:mod:`geosim.scratch`) instead of new ones: no fresh memory to fault in, but the
        arrays returned are valid only until the next ``read_raster(...,
        reuse_buffers=True)`` in this thread.
    """
    with open_raster(path, what=what, require_crs=require_crs) as ds, \
            naming_read_failures(path):
        out = valid_out = None
        if reuse_buffers and window is None:
            idx = list(bands) if bands is not None else image_band_indexes(ds)
            idx = idx[:max_bands] if max_bands is not None else idx
            out, valid_out = _reused_buffers(ds, "read_raster", len(idx),
                                             out_dtype if out_dtype is not None
                                             else ds.dtypes[idx[0] - 1])
        return read_window(ds, window, bands=bands, max_bands=max_bands,
                           out_dtype=out_dtype, boundless=boundless, path=path,
                           out=out, valid_out=valid_out)


def _reused_buffers(ds: rasterio.DatasetReader, key: str, n_bands: int, dtype: Any
                    ) -> tuple[np.ndarray, np.ndarray]:
    """This thread's reused arrays (:mod:`geosim.scratch`) to decode a whole dataset into:
    the ``(n_bands, rows, cols)`` image of ``dtype`` and the bool mask, named by ``key``."""
    return (scratch_array(f"{key}.image", (n_bands, ds.height, ds.width), dtype),
            scratch_array(f"{key}.valid", (ds.height, ds.width), bool))


@dataclass(frozen=True)
class BinomialLevel1:
    """A raster's binomial first overview level (:mod:`geosim.io.overviews`), read in place
    of its full resolution.

    Attributes
    ----------
    level
        The level's bands and mask (every pixel valid), with its own transform.
    shape
        ``(rows, cols)`` of the full resolution.
    transform
        Pixel-corner -> map affine of the full resolution.
    """

    level: RasterData
    shape: tuple[int, int]
    transform: Affine


def read_binomial_level1(path: str | os.PathLike[str], *, what: str = "raster",
                         usable: Callable[[tuple[int, int]], bool] | None = None,
                         reuse_buffers: bool = False) -> BinomialLevel1 | None:
    """The binomial first overview level of a raster geosim wrote, or None.

    None where the raster does not carry :data:`~geosim.io.overviews.LEVEL1_TAG` (written
    by another program or version, partial, odd-sized or not 8-bit), where its first
    overview is not exactly half its size or has an invalid pixel, or where
    ``usable(shape)`` (full resolution, rows and cols) is False; the header alone is read
    before deciding. ``reuse_buffers`` as for :func:`read_raster`.
    """
    with open_raster(path, what=what) as ds:
        if ds.tags().get(LEVEL1_TAG) != LEVEL1_BINOMIAL or ds.overviews(1)[:1] != [2]:
            return None
        shape, transform = (ds.height, ds.width), ds.transform
    if usable is not None and not usable(shape):
        return None
    with naming_read_failures(path), rasterio.open(path, overview_level=0) as ds:
        if (ds.height, ds.width) != (shape[0] // 2, shape[1] // 2):
            return None
        out = valid_out = None
        if reuse_buffers:
            idx = image_band_indexes(ds)
            out, valid_out = _reused_buffers(ds, "read_raster.level1", len(idx),
                                             ds.dtypes[idx[0] - 1])
        level = read_window(ds, path=path, out=out, valid_out=valid_out)
    return BinomialLevel1(level, shape, transform) if level.valid.all() else None


def geotiff_profile(*, width: int, height: int, count: int, dtype: str | np.dtype,
                    crs: CRS | str, transform: Affine, nodata: float | None = None,
                    ) -> dict[str, Any]:
    """Creation options for a tiled, deflate-compressed GeoTIFF."""
    dtype = np.dtype(dtype).name
    tiled = width >= BLOCK_PX and height >= BLOCK_PX
    profile: dict[str, Any] = {
        "driver": "GTiff", "width": int(width), "height": int(height), "count": int(count),
        "dtype": dtype, "crs": CRS.from_user_input(crs), "transform": transform,
        "compress": "deflate", "predictor": 3 if dtype.startswith("float") else 2,
        "tiled": tiled, "interleave": "pixel", "BIGTIFF": "IF_SAFER",
    }
    if tiled:
        profile.update(blockxsize=BLOCK_PX, blockysize=BLOCK_PX)
    if nodata is not None:
        profile["nodata"] = nodata
    return profile


def provenance_tags(step: str, params: Mapping[str, Any] | None = None,
                    sources: Sequence[str | os.PathLike[str]] = (), *,
                    base_dir: str | os.PathLike[str] | None = None) -> dict[str, str]:
    """GeoTIFF metadata tags that say what made a file.

    Parameters
    ----------
    step
        The pipeline step that wrote the file.
    params
        The step's parameters (JSON-serialised).
    sources
        Files the output was made from.
    base_dir
        The run folder: sources inside it are recorded relative to it (POSIX), so the
        tags stay true when the folder is moved; sources outside it stay absolute.
    """
    from geosim import __version__

    return {
        "GEOSIM_VERSION": __version__,
        "GEOSIM_STEP": step,
        "GEOSIM_PARAMS": json.dumps(dict(params or {}), sort_keys=True, default=str),
        "GEOSIM_SOURCES": json.dumps([_source_name(s, base_dir) for s in sources]),
    }


def acquisition_tags(acquired: dt.datetime | None) -> dict[str, str]:
    """GeoTIFF tags with the acquisition time of the imagery (empty when unknown).

    ``GEOSIM_ACQUIRED`` is ISO 8601 with its UTC offset; ``TIFFTAG_DATETIME`` is the
    baseline TIFF tag (``YYYY:MM:DD HH:MM:SS``, local time of the stated offset).
    """
    if acquired is None:
        return {}
    return {"GEOSIM_ACQUIRED": acquired.isoformat(),
            "TIFFTAG_DATETIME": acquired.strftime("%Y:%m:%d %H:%M:%S")}


def _source_name(source: str | os.PathLike[str], base_dir: str | os.PathLike[str] | None
                 ) -> str:
    """Relative to ``base_dir`` when inside it; otherwise absolute (when it can be resolved)."""
    path = Path(source)
    if not path.is_absolute() and path.exists():
        path = path.resolve()
    return relative_if_inside(path, base_dir)


@contextlib.contextmanager
def create_geotiff(path: str | os.PathLike[str], *, width: int, height: int, count: int,
                   dtype: str | np.dtype, crs: CRS | str, transform: Affine,
                   nodata: float | None = None, band_descriptions: Sequence[str] | None = None,
                   tags: Mapping[str, str] | None = None, internal_mask: bool = False,
                   creation_options: Mapping[str, str] | None = None,
                   cog_overrides: Mapping[str, Any] | None = None,
                   whole: WholeRaster | None = None,
                   ) -> Iterator[rasterio.io.DatasetWriter]:
    """Open a GeoTIFF for windowed writing; on success it is renamed into place as a COG.

    Use this when the raster is written window by window: the windows go to a scratch
    GeoTIFF that :func:`geosim.io.cog.cog_writer` copies once into a Cloud-Optimized
    GeoTIFF with internal overviews (masks, tags and descriptions kept). ``internal_mask=True``
    adds a GDAL internal mask band (write it with ``dst.write_mask``).
    ``creation_options`` are extra GTiff options (e.g. ``ZLEVEL``, ``NUM_THREADS``) of the
    scratch file; ``cog_overrides`` replace COG options of the final file (e.g. ``LEVEL``).
    A writer holding the whole raster in memory passes it as ``whole``
    (:class:`geosim.io.cog.WholeRaster`): the overviews are then computed from it.
    """
    profile = geotiff_profile(width=width, height=height, count=count, dtype=dtype, crs=crs,
                              transform=transform, nodata=nodata)
    profile.update(creation_options or {})
    with cog_writer(path, profile, internal_mask=internal_mask,
                    cog_overrides=cog_overrides, whole=whole) as dst:
        if band_descriptions is not None:
            for i, desc in enumerate(band_descriptions, start=1):
                dst.set_band_description(i, desc)
        if tags:
            dst.update_tags(**tags)
        yield dst


def write_geotiff(path: str | os.PathLike[str], array: np.ndarray, *, transform: Affine,
                  crs: CRS | str, nodata: float | None = None, mask: np.ndarray | None = None,
                  band_descriptions: Sequence[str] | None = None,
                  tags: Mapping[str, str] | None = None,
                  cog_overrides: Mapping[str, Any] | None = None) -> Path:
    """Write a whole array (bands, rows, cols) or (rows, cols) as a GeoTIFF, atomically.

    Parameters
    ----------
    array
        Pixel values; a 2-D array is written as one band.
    transform, crs
        Georeference of pixel (0, 0)'s outer corner and the CRS it is in.
    nodata
        Nodata value written into the file; pixels where ``mask`` is False are set to it.
    mask
        Valid-data mask (True = valid), written as an internal mask band when given.
    cog_overrides
        COG creation options replacing geosim's defaults (:func:`geosim.io.cog.cog_options`).
    """
    arr = array[np.newaxis] if array.ndim == 2 else array
    if mask is not None and nodata is not None:
        arr = np.where(mask[np.newaxis], arr, np.asarray(nodata, dtype=arr.dtype))
    with create_geotiff(path, width=arr.shape[2], height=arr.shape[1], count=arr.shape[0],
                        dtype=arr.dtype, crs=crs, transform=transform, nodata=nodata,
                        band_descriptions=band_descriptions, tags=tags,
                        internal_mask=mask is not None, cog_overrides=cog_overrides,
                        whole=None if mask is None else WholeRaster(
                            arr, np.asarray(mask, dtype=bool), 0 if nodata is None else nodata),
                        ) as dst:
        dst.write(arr)
        if mask is not None:
            dst.write_mask(mask.astype(np.uint8) * 255)
    return Path(path)


def sha256_file(path: str | os.PathLike[str], *, chunk_bytes: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file, read in chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk_bytes):
            h.update(block)
    return h.hexdigest()


def iter_windows(width: int, height: int, *, block_px: int = 2048) -> Iterator[Window]:
    """Row-major windows of at most ``block_px`` × ``block_px`` covering a raster."""
    for row in range(0, height, block_px):
        for col in range(0, width, block_px):
            yield Window(col, row, min(block_px, width - col), min(block_px, height - row))


def read_failure(exc: BaseException) -> RasterError | None:
    """One-line :class:`RasterError` for a failed raster read in the middle of a step.

    Inputs are read in full before a run (:mod:`geosim.validate`), so this is for files
    in the run folder (a truncated tile, a grid raster cut short by a full disk): GDAL's
    own message, which rasterio chains as the cause, names the file and the block.
    Returns None for anything that is not a rasterio read error.
    """
    from rasterio.errors import RasterioError

    if not isinstance(exc, RasterioError) or "read" not in str(exc).lower():
        return None
    cause = exc.__cause__ or exc.__context__ or exc
    detail = " ".join(str(cause).split())[:240] or type(exc).__name__
    return RasterError(f"a raster cannot be read: {detail}; it is truncated or corrupt: if "
                       "it is in the run folder, delete it and rerun the step that wrote it, "
                       "otherwise re-copy the input")


@contextlib.contextmanager
def naming_read_failures(path: str | os.PathLike[str]) -> Iterator[None]:
    """A failed read of ``path`` inside the block becomes the one-line
    :class:`RasterError` of :func:`read_failure`, naming the file; other errors pass."""
    from rasterio.errors import RasterioError

    try:
        yield
    except RasterioError as exc:  # a block cut short: GDAL names the bytes, not the file
        failure = read_failure(exc)
        if failure is None:
            raise
        raise type(failure)(f"{path}: {failure}") from exc


def band_descriptions(src: rasterio.DatasetReader, bands: list[int]) -> list[str]:
    """Band descriptions (or colour interpretation names) of the given bands."""
    from rasterio.enums import ColorInterp

    out = []
    for b in bands:
        desc = src.descriptions[b - 1]
        ci = src.colorinterp[b - 1]
        out.append(desc or (ci.name if ci not in (ColorInterp.undefined, ColorInterp.gray)
                            else f"band {b}"))
    return out
