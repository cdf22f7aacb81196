"""Pre-flight checks: everything that can be known before a run writes anything.

:func:`preflight` runs at the start of :func:`geosim.pipeline.run_pipeline`, before the
run folder is created. It refuses, with one :class:`~geosim.errors.GeosimError` line:

- an ``--out`` that is an input, contains one, lies inside an input folder of the site
  (``labels/PA1``, ``flights/``) or is an existing file (:func:`check_out_dir`);
- an input raster with an unsupported band layout or data type, or a block that cannot
  be read (a truncated or corrupt TIFF), naming the file and the block
  (:func:`check_raster_bands`, :func:`check_raster_readable`; the full read is done when
  a step that reads the inputs' pixels — grid, footprints, align — is about to run);
- flights whose extents (transformed into the site CRS) do not overlap, naming the flight
  that is farthest from the others and its distance, and a grid larger than
  :data:`MAX_GRID_PX` (:func:`check_extents`);
- a satellite scene that does not overlap the flights;
- label files that do not parse;
- a run that degrades with neither a satellite scene nor ``parameters.q``.

Only metadata and a block-by-block read are used (no resampling), so the checks take a
fraction of the run's time and bounded memory.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from geosim.errors import ConfigError, ExtentError, OutputError, RasterError
from geosim.io.bands import check_raster_bands

if TYPE_CHECKING:
    import rasterio
    from pyproj import CRS

    from geosim.config import SiteConfig

#: Largest UAV grid (pixels) a run may build: 4·10¹⁰ px is 100 km² at 0.05 m, far more
#: than repeated surveys of a farm; a bigger grid means a flight is somewhere else.
MAX_GRID_PX = 4e10

#: Side of the windows read by the integrity check, pixels (a whole number of blocks).
CHECK_WINDOW_PX = 1024

Bounds = tuple[float, float, float, float]


# ------------------------------------------------------------------------- --out


def site_inputs(site: SiteConfig) -> dict[str, Path]:
    """Every input path of a site, by what it is (``flight PA1 image``, ``paddocks``…)."""
    inputs: dict[str, Path] = {}
    if site.path is not None:
        inputs["site file"] = site.path
    for f in site.flights:
        inputs[f"flight {f.id} image"] = f.image
        if f.labels is not None:
            inputs[f"flight {f.id} labels"] = f.labels
    if site.satellite is not None:
        inputs["satellite image"] = site.satellite.image
    if site.paddocks is not None:
        inputs["paddocks"] = site.paddocks
    return inputs


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def check_out_path(out: str | os.PathLike[str], inputs: Mapping[str, Path], *,
                   protected_folders: Iterable[Path] = (), option: str = "--out") -> Path:
    """Refuse an output path that would overwrite, contain or live inside an input.

    Parameters
    ----------
    out
        The output folder (or file) asked for.
    inputs
        Input paths by description.
    protected_folders
        Folders holding inputs, in which no output may be written.
    option
        The option's name, for the message.

    Returns
    -------
    pathlib.Path
        ``out`` resolved.

    Raises
    ------
    OutputError
        ``out`` is an input, contains one, or is inside an input or a protected folder.
    """
    target = Path(out).resolve()
    for what, path in inputs.items():
        p = Path(path).resolve()
        if _inside(p, target):
            relation = "is" if p == target else "contains"
            raise OutputError(f"{option} {out} {relation} the {what} ({p}); geosim would "
                              "overwrite or delete it: choose a new folder outside the inputs")
        if p.is_dir() and _inside(target, p):
            raise OutputError(f"{option} {out} is inside the {what} folder ({p}); choose a "
                              "new folder outside the inputs")
    for folder in protected_folders:
        f = Path(folder).resolve()
        if _inside(target, f):
            raise OutputError(f"{option} {out} is inside the input folder {f}; choose a new "
                              "folder outside the inputs (e.g. beside the site file)")
    return target


def check_out_file(out: str | os.PathLike[str], inputs: Mapping[str, str | os.PathLike[str]],
                   *, option: str = "--out") -> Path:
    """Refuse an output file that is one of the inputs (symlinks resolved) or a folder.

    Returns
    -------
    pathlib.Path
        ``out`` resolved.
    """
    target = Path(out).resolve()
    for what, path in inputs.items():
        if Path(path).resolve() == target:
            raise OutputError(f"{option} {out} is the {what}; geosim would overwrite its own "
                              f"input: give another {option} path")
    if target.is_dir():
        raise OutputError(f"{option} {out} is a folder; give a file path (e.g. counts.csv)")
    return target


def check_out_dir(site: SiteConfig, out: str | os.PathLike[str]) -> Path:
    """Refuse a run folder that is a file, unwritable, or touches the site's inputs.

    The site folder itself may hold the run folder (``site/out``), but not the folders
    its inputs are in (``site/flights/out``, ``site/labels/out``) and not the site folder
    itself.
    """
    target = Path(out).resolve()
    if target.exists() and not target.is_dir():
        raise OutputError(f"--out {out} is an existing file, not a folder; give a folder "
                          "path (it is created if needed)")
    inputs = site_inputs(site)
    site_dir = site.path.parent.resolve() if site.path is not None else None
    folders = set()
    for what, p in inputs.items():
        parent = Path(p).resolve().parent
        if what != "site file" and site_dir is not None and _inside(parent, site_dir) \
                and parent != site_dir:
            folders.add(parent)
    check_out_path(out, inputs, protected_folders=sorted(folders))
    existing = target
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise OutputError(f"--out {out}: {existing} is a file, so the folder cannot be "
                          "created; give another --out")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise OutputError(f"--out {out}: {existing} is not writable; choose a folder you "
                          "can write to")
    return target


# ------------------------------------------------------------------------- rasters


def _check_step_rows(ds: rasterio.DatasetReader) -> int:
    """Rows of one strip of check windows (a whole number of blocks)."""
    block_rows = ds.block_shapes[0][0]
    return max(block_rows, CHECK_WINDOW_PX // block_rows * block_rows)


def _check_windows(ds: rasterio.DatasetReader, rows: tuple[int, int] | None = None
                   ) -> Iterator[rasterio.windows.Window]:
    """The check windows, row-major; only the strips starting in ``rows = (start, stop)``
    when given."""
    from rasterio.windows import Window

    block_cols = ds.block_shapes[0][1]
    step_r = _check_step_rows(ds)
    step_c = max(block_cols, CHECK_WINDOW_PX // block_cols * block_cols)
    start, stop = rows if rows is not None else (0, ds.height)
    for r in range(start, min(stop, ds.height), step_r):
        for c in range(0, ds.width, step_c):
            yield Window(c, r, min(step_c, ds.width - c), min(step_r, ds.height - r))


def _first_bad_block(ds: rasterio.DatasetReader, window: rasterio.windows.Window
                     ) -> tuple[tuple[int, int], rasterio.windows.Window, str]:
    """The first block inside ``window`` that cannot be read, its window and the error."""
    from rasterio.windows import intersect

    for ij, block in ds.block_windows(1):
        if not intersect(block, window):
            continue
        try:
            ds.read(window=block)
        except Exception as exc:  # noqa: BLE001 - any read failure names the block
            cause = exc.__cause__ or exc  # rasterio chains GDAL's own message
            text = " ".join(str(cause).split()) or type(exc).__name__
            return ij, block, text[:200]
    return (-1, -1), window, "read failed"


def check_raster_readable(ds: rasterio.DatasetReader, what: str,
                          rows: tuple[int, int] | None = None) -> int:
    """Read every block of every band once (window by window); refuse a corrupt file.

    ``rows = (start, stop)`` reads only the window strips starting in those rows
    (``start`` a multiple of the strip height), so a raster can be checked in parts.

    Returns
    -------
    int
        The number of pixels read (per band).

    Raises
    ------
    RasterError
        Naming the file, the first block that cannot be read (row, column of blocks,
        and its pixel offsets) and GDAL's reason.
    """
    n = 0
    for window in _check_windows(ds, rows):
        try:
            ds.read(window=window)
        except Exception:  # noqa: BLE001 - located below, block by block
            (bi, bj), block, reason = _first_bad_block(ds, window)
            raise RasterError(
                f"{what}: {ds.name} is truncated or corrupt: block ({bi}, {bj}) at pixel "
                f"row {int(block.row_off)}, column {int(block.col_off)} cannot be read "
                f"({reason}); re-export or re-copy the file") from None
        n += int(window.width * window.height)
    return n


# ------------------------------------------------------------------------- extents


@dataclass(frozen=True)
class Extents:
    """Extents of the site's rasters in the site CRS, metres."""

    crs: CRS
    flights: dict[str, Bounds]
    satellite: Bounds | None


def _box_distance_m(a: Bounds, b: Bounds) -> float:
    dx = max(0.0, max(a[0], b[0]) - min(a[2], b[2]))
    dy = max(0.0, max(a[1], b[1]) - min(a[3], b[3]))
    return math.hypot(dx, dy)


def _union(bounds: Iterable[Bounds]) -> Bounds:
    b = list(bounds)
    return (min(x[0] for x in b), min(x[1] for x in b), max(x[2] for x in b),
            max(x[3] for x in b))


def _intersection(bounds: Iterable[Bounds]) -> Bounds | None:
    b = list(bounds)
    out = (max(x[0] for x in b), max(x[1] for x in b), min(x[2] for x in b),
           min(x[3] for x in b))
    return out if out[0] < out[2] and out[1] < out[3] else None


def site_extents(site: SiteConfig) -> Extents:
    """Bounds of every flight and of the satellite scene in the site CRS (metadata only)."""
    from geosim.io.raster import open_raster
    from geosim.prepare.grid import resolve_site_crs
    from geosim.prepare.reproject import bounds_in_crs

    def bounds(path: Path, what: str, crs: object) -> Bounds:
        with open_raster(path, what=what) as ds:
            try:
                b = bounds_in_crs(ds, crs)
            except Exception as exc:  # noqa: BLE001 - pyproj/GDAL errors, one line
                raise RasterError(f"{what}: {path}: its extent cannot be transformed to "
                                  f"{crs} ({exc}); check its CRS") from None
        if not all(map(math.isfinite, b)):
            raise RasterError(f"{what}: {path}: its extent is outside the domain of {crs}; "
                              "check its CRS")
        return b

    lonlat = [bounds(f.image, f"flight {f.id}", "EPSG:4326") for f in site.flights]
    crs = resolve_site_crs(site.crs, lonlat)
    flights = {f.id: bounds(f.image, f"flight {f.id}", crs) for f in site.flights}
    sat = (bounds(site.satellite.image, "satellite scene", crs)
           if site.satellite is not None else None)
    return Extents(crs=crs, flights=flights, satellite=sat)


def check_extents(extents: Extents, *, uav_gsd_m: float) -> Bounds:
    """Refuse flights that do not overlap or a grid too big to build; return the overlap.

    Raises
    ------
    ExtentError
        The flights' extents have no common part (naming the flight farthest from the
        others and the distance), the grid over all flights would exceed
        :data:`MAX_GRID_PX`, or the satellite scene misses the flights' common extent.
    """
    fl = extents.flights
    common = _intersection(fl.values())
    if common is None:
        dist = {fid: _box_distance_m(b, _union(v for k, v in fl.items() if k != fid))
                for fid, b in fl.items()}
        worst = max(dist, key=lambda k: dist[k])
        others = ", ".join(k for k in fl if k != worst)
        where = (f"{dist[worst] / 1000:.1f} km from" if dist[worst] > 0
                 else "overlapping only some of")
        raise ExtentError(
            f"flight {worst} does not overlap the other flights (the common extent "
            f"{'∩'.join(fl)} is empty): it is {where} flight(s) "
            f"{others} in {extents.crs.to_string()}; check its CRS (a neighbouring UTM zone?) "
            "or remove it from the site file")
    u = _union(fl.values())
    grid_px = (u[2] - u[0]) * (u[3] - u[1]) / uav_gsd_m**2
    if grid_px > MAX_GRID_PX:
        largest = max(fl, key=lambda k: (fl[k][2] - fl[k][0]) * (fl[k][3] - fl[k][1]))
        raise ExtentError(
            f"the flights span {(u[2] - u[0]) / 1000:.1f} × {(u[3] - u[1]) / 1000:.1f} km, a "
            f"grid of {grid_px:.3g} px at {uav_gsd_m} m (limit {MAX_GRID_PX:.0e}); flight "
            f"{largest} is the largest: check its CRS and georeference")
    if extents.satellite is not None and _intersection([extents.satellite, common]) is None:
        d = _box_distance_m(extents.satellite, common)
        raise ExtentError(
            "satellite scene: no overlap with the flights' common extent (it is "
            f"{d / 1000:.2f} km away in {extents.crs.to_string()}); give a scene that covers "
            "the flights, or check its CRS")
    return common


# ------------------------------------------------------------------------- all


#: Pixels (per band) of one engine task of the integrity read: large flights are read in
#: parts, in parallel on the workers.
CHECK_TASK_PX = 64 * 1024 * 1024


@dataclass(frozen=True)
class ReadCheckTask:
    """Rows ``rows = (start, stop)`` of one raster to read in full (an engine task)."""

    path: str
    what: str
    rows: tuple[int, int]


def read_check_task(task: ReadCheckTask) -> str | None:
    """Run a :class:`ReadCheckTask`; the error message of its first unreadable block, or
    None (returned, not raised, so that the caller reports the first one in file order
    whichever task finished first)."""
    from geosim.io.raster import open_raster

    try:
        with open_raster(task.path, what=task.what) as ds:
            check_raster_readable(ds, task.what, task.rows)
    except RasterError as exc:
        return str(exc)
    return None


def check_rasters(site: SiteConfig) -> None:
    """Band layout, data type and a full block-by-block read of every input raster.

    The read is split into strips of about :data:`CHECK_TASK_PX` pixels run on the active
    engine (:func:`geosim.engine.parallel_map`; in this process when all the rasters
    together are smaller than one strip); the first unreadable block in file order is
    reported, as by a read from start to end.
    """
    from geosim.engine import parallel_map
    from geosim.io.raster import open_raster

    items = [(f"flight {f.id}", f.image) for f in site.flights]
    if site.satellite is not None:
        items.append(("satellite scene", site.satellite.image))
    tasks, total_px = [], 0
    for what, path in items:
        with open_raster(path, what=what) as ds:
            check_raster_bands(ds, what)
            total_px += ds.width * ds.height
            step_r = _check_step_rows(ds)
            strip = max(1, CHECK_TASK_PX // max(1, step_r * ds.width)) * step_r
            tasks += [ReadCheckTask(str(path), what, (r, min(r + strip, ds.height)))
                      for r in range(0, ds.height, strip)]
    # a read smaller than one task is not worth starting a cluster for
    small = total_px <= CHECK_TASK_PX
    errors = map(read_check_task, tasks) if small else parallel_map(
        read_check_task, tasks, desc="check inputs")
    for error in errors:
        if error is not None:
            raise RasterError(error)


def preflight(site: SiteConfig, out: str | os.PathLike[str],
              steps: Sequence[str] | None = None) -> Extents:
    """Every check that needs no pixel work beyond one read; see the module docstring.

    Parameters
    ----------
    site
        A validated site.
    out
        The run folder asked for (need not exist).
    steps
        Names of the steps about to run (default: all).

    Returns
    -------
    Extents
        The rasters' extents in the site CRS.
    """
    check_out_dir(site, out)
    names = set(steps) if steps else None
    if (names is None or "degrade" in names) and site.satellite is None \
            and site.parameters.q is None:
        where = site.path or "the site"
        raise ConfigError(f"{where}: no satellite scene and no parameters.q: degrading needs "
                          "a Q; add a [satellite] table (Q is calibrated against it) or set "
                          "parameters.q (e.g. q = 4.34, the paper's calibrated value)")
    extents = site_extents(site)
    check_extents(extents, uav_gsd_m=site.parameters.uav_gsd_m)
    # the steps that read the inputs' pixels (footprints and align read the original
    # flights since they are resampled once, straight onto the aligned grid)
    if names is None or {"grid", "footprints", "align"} & set(names):
        check_rasters(site)
    if names is None or "labels" in names:
        from geosim.labels.sources import read_site_labels

        labelled = [f for f in site.flights if f.labels is not None]
        if labelled:
            read_site_labels(labelled, extents.crs,
                             base_dir=site.path.parent if site.path is not None else None)
    return extents
