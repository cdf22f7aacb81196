"""Pipeline steps ``calibrate`` and ``degrade``: the I/O around the pure kernels.

``run_calibrate(site, out)``
    Reads ``grid/satellite.tif`` (the satellite scene on the shared 0.5 m grid)
    and each flight on the aligned 0.05 m grid (nested in the same origin family),
    resampled once on the fly from the original file through its composed warp
    (:mod:`geosim.prepare.aligned`). For each flight, over its common extent with
    the satellite (both valid), it measures the satellite's Laplacian variance,
    the LV of the degraded flight as a function of Q, and solves for the Q
    where they are equal. Writes ``calibration.json`` and ``calibration.png``.
``run_degrade(site, out, q=None)``
    Degrades every ``tiles/<flight>/<tile>.tif`` to ``degraded/<flight>/<tile>.tif``
    at Q (default: the mean Q of ``calibration.json``), with the tile's
    transform scaled by φ (same origin), same CRS, the valid mask propagated
    and provenance tags.
"""

from __future__ import annotations

import hashlib
import json
import math
import pickle
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.windows import Window
from tqdm import tqdm

from geosim import __version__, manifest
from geosim.config import SiteConfig
from geosim.degrade.blur import laplacian_moments, to_grey
from geosim.degrade.calibrate import (
    PLAUSIBLE_Q,
    GreyWindowReader,
    build_blocked_lv,
    quantization_lv,
    solve_q,
)
from geosim.degrade.core import METHODS, degrade_array, degrade_level1, level1_allowed, to_dtype
from geosim.degrade.plot import plot_calibration
from geosim.engine import parallel_map
from geosim.errors import CalibrationError, ConfigError, InputFileError, RasterError
from geosim.io.atomic import to_jsonable, write_json
from geosim.io.raster import (
    RasterData,
    acquisition_tags,
    image_band_indexes,
    open_raster,
    provenance_tags,
    read_binomial_level1,
    read_raster,
    read_window,
    write_geotiff,
)
from geosim.manifest import skip_text
from geosim.prepare.aligned import AlignedFlight, AlignedReader, aligned_flights, flight_inputs
from geosim.prepare.grid import sat_grid_offset
from geosim.result import StepResult
from geosim.rundir import RunDir, RunPath

#: Q values at which the LV curve is sampled for the figure and the JSON.
N_CURVE_SAMPLES = 16
#: Calibration blocks: core side and margin, in satellite pixels (margin error < 2e-4
#: relative LV up to Q = 8 with 16 px; see tests/test_calibrate.py).
BLOCK_SAT_PX = 300
MARGIN_SAT_PX = 24
_GREY_CHUNK_ROWS = 512
#: Tag of a degraded tile: which resolution of the UAV tile was read (provenance only).
DEGRADE_READ_TAG = "GEOSIM_DEGRADE_READ"
READ_FULL = "full resolution"
READ_LEVEL1 = "first overview (the binomial level 1 of the tile)"

LV_DEFINITION = (
    "variance (1/N) of the paper's Laplacian [[1/6,2/3,1/6],[2/3,-10/3,2/3],[1/6,2/3,1/6]] "
    "on BT.601 luma, 0-255 grey levels, over 0.5 m pixels whose 3x3 neighbourhood is valid in "
    "both the satellite and the degraded flight (a degraded pixel is valid when all its phi x "
    "phi UAV pixels are) and at least guard_sat_px from UAV no-data. Degraded LV is computed "
    "on the unrounded grey image plus the expected LV of rounding the delivered bands to the "
    "flight's dtype (quantization_lv)."
)


# --------------------------------------------------------------------------- helpers

def _grey_reader(ds: AlignedReader, row0: int, col0: int, dn_max: float | None
                 ) -> GreyWindowReader:
    """Reader of grey windows relative to (row0, col0) of an aligned flight; outside =
    invalid.

    Each window comes back as a one-band :class:`RasterData` (``"grey"``) with the
    window's transform (:data:`geosim.degrade.calibrate.GreyWindowReader`).
    """

    def read(r: int, c: int, h: int, w: int) -> RasterData:
        grey = np.zeros((1, h, w), np.float32)
        valid = np.zeros((h, w), bool)
        rr, cc = row0 + r, col0 + c
        a0, b0 = max(rr, 0), max(cc, 0)
        a1, b1 = min(rr + h, ds.height), min(cc + w, ds.width)
        out = RasterData(array=grey, valid=valid,
                         transform=ds.transform @ Affine.translation(cc, rr), crs=ds.crs,
                         band_names=("grey",), path=Path(ds.name))
        if a1 <= a0 or b1 <= b0:
            return out
        for s0 in range(a0, a1, _GREY_CHUNK_ROWS):
            s1 = min(s0 + _GREY_CHUNK_ROWS, a1)
            data, ok = ds.read(Window(b0, s0, b1 - b0, s1 - s0))
            grey[0, s0 - rr:s1 - rr, b0 - cc:b1 - cc] = to_grey(data, dn_max=dn_max)
            valid[s0 - rr:s1 - rr, b0 - cc:b1 - cc] = ok
        return out

    return read


def _quantization_step_grey(dtype: str) -> float:
    dt = np.dtype(dtype)
    if np.issubdtype(dt, np.integer):
        return 255.0 / (255.0 if dt == np.uint8 else float(np.iinfo(dt).max))
    return 0.0


def guard_px(q_max: float) -> int:
    """Guard band (satellite px) left out next to UAV no-data: the first dark ring at q_max."""
    from geosim.physics.psf import first_zero_px  # SciPy's special functions: calibrate only

    return min(MARGIN_SAT_PX, math.ceil(first_zero_px(q_max, phi=1)))


def plausibility_warning(q: float, *, what: str = "calibrated Q") -> str | None:
    """A warning when Q is outside the 0.5–2 range of real cameras, pointing to diagnosis."""
    lo, hi = PLAUSIBLE_Q
    if q > hi:
        return (f"{what} = {q:.2f} is above the {lo:g}–{hi:g} of real satellite cameras: the "
                "satellite scene is blurrier than diffraction alone explains, so Q is absorbing "
                "physics the paper's model leaves out (detector integration, atmosphere, "
                "motion smear, off-nadir viewing, resampling of the product). Run "
                "`geosim diagnose SITE.toml --out DIR` to find which.")
    if q < lo:
        return (f"{what} = {q:.2f} is below the {lo:g}–{hi:g} of real satellite cameras: the "
                "satellite scene has more Laplacian variance than diffraction allows "
                "(sensor noise, sharpening or compression artefacts raise it). Run "
                "`geosim diagnose SITE.toml --out DIR` to find which.")
    return None


# --------------------------------------------------------------------------- calibrate

def calibrate_flight(flight_id: str, flight: AlignedFlight | Path, sat: rasterio.DatasetReader,
                     *, phi: int, q_min: float, q_max: float, obscuration: float = 0.0,
                     n_curve: int = N_CURVE_SAMPLES, xtol: float = 1e-4) -> dict[str, Any]:
    """Calibrate one flight against the satellite scene (opened, on the shared grid).

    ``flight`` is the flight on the aligned grid (read through its composed warp), or the
    path of a raster on the aligned grid.

    Returns
    -------
    dict
        ``status`` (``ok``, ``no_overlap`` or ``failed``), ``q``, ``lv_satellite``,
        ``lv_at_q``, the LV curve, the area used and its window on the satellite grid.
    """
    what = f"flight {flight_id}"
    if not isinstance(flight, AlignedFlight):
        with open_raster(flight, what=f"aligned {what}"):
            pass  # a one-line error for a missing or unreadable raster
        flight = AlignedFlight.from_raster(flight_id, flight)
    flight_path = flight.path or flight.warp.src_path
    with flight.open() as ds:
        if ds.crs != sat.crs:
            raise RasterError(f"aligned {what} ({flight_path}) is in {ds.crs}, the satellite "
                              f"grid in {sat.crs}; re-run 'geosim grid' and 'geosim align'")
        row_off, col_off = sat_grid_offset(ds.transform, sat.transform, phi, f"aligned {what}")
        rows_s, cols_s = ds.height // phi, ds.width // phi
        r0, c0 = max(row_off, 0), max(col_off, 0)
        r1, c1 = min(row_off + rows_s, sat.height), min(col_off + cols_s, sat.width)
        result: dict[str, Any] = {
            "flight": flight_id,
            "aligned": (Path(flight.path).name if flight.path is not None else
                        f"{Path(flight_path).name}, resampled once onto the aligned grid")}
        if r1 <= r0 or c1 <= c0:
            return {**result, "status": "no_overlap",
                    "reason": "the flight does not overlap the satellite scene"}
        window = Window(c0, r0, c1 - c0, r1 - r0)
        sat_data = read_window(sat, window)
        sat_grey, sat_valid = to_grey(sat_data.array), sat_data.valid
        dtype = ds.dtype
        offset = quantization_lv(_quantization_step_grey(dtype), bands=ds.count)
        reader = _grey_reader(ds, (r0 - row_off) * phi, (c0 - col_off) * phi, None)
        n_blocks = math.ceil((r1 - r0) / BLOCK_SAT_PX) * math.ceil((c1 - c0) / BLOCK_SAT_PX)
        with tqdm(total=n_blocks, desc=f"calibrate {flight_id}", unit="block",
                  disable=None, leave=False) as bar:
            model = build_blocked_lv(reader, (r1 - r0, c1 - c0), phi=phi, q_min=q_min,
                                     out_mask=sat_valid, block_sat_px=BLOCK_SAT_PX,
                                     margin_sat_px=MARGIN_SAT_PX, obscuration=obscuration,
                                     offset_lv=offset, guard_sat_px=guard_px(q_max),
                                     progress=bar.update)
    lv_mask = model.lv_mask
    n_pixels = int(lv_mask.sum())
    result.update({"window_sat_px": [c0, r0, c1 - c0, r1 - r0], "n_pixels": n_pixels,
                   "area_m2": round(n_pixels * abs(sat.transform.a * sat.transform.e), 3),
                   "uav_dtype": dtype, "quantization_lv": offset,
                   "guard_sat_px": guard_px(q_max)})
    if n_pixels < 9:
        return {**result, "status": "no_overlap",
                "reason": "fewer than 9 satellite pixels are valid in both the satellite and "
                          "the degraded flight (after eroding by the Laplacian's reach)"}
    lv_sat = laplacian_moments(sat_grey, lv_mask).variance
    q_curve = np.linspace(q_min, q_max, n_curve)
    curve = [model(q) for q in q_curve]
    result.update({"lv_satellite": lv_sat,
                   "curve": {"q": q_curve.tolist(), "lv": curve}})
    try:
        sol = solve_q(model, lv_sat, q_min=q_min, q_max=q_max, xtol=xtol, name=what)
    except CalibrationError as exc:
        return {**result, "status": "failed", "error": str(exc)}
    return {**result, "status": "ok", "q": sol.q, "lv_at_q": sol.lv_at_q,
            "lv_at_q_min": sol.lv_at_q_min, "lv_at_q_max": sol.lv_at_q_max,
            "evaluations": sol.evaluations}


@dataclass(frozen=True)
class CalibrateTask:
    """One flight to calibrate against the satellite scene (picklable)."""

    out_dir: Path
    flight: str
    aligned: AlignedFlight
    sat_path: Path
    phi: int
    q_min: float
    q_max: float


@dataclass(frozen=True)
class CalibrateDone:
    """A flight's calibration record and whether it came from the manifest."""

    result: dict[str, Any]
    skipped: bool


def calibrate_task(task: CalibrateTask) -> CalibrateDone:
    """Calibrate one flight (:func:`calibrate_flight`), or reuse its current record."""
    key = f"calibration/{task.flight}"
    inputs = [*flight_inputs(task.aligned), task.sat_path]
    params = {"step": "calibrate", "flight": task.flight, "phi": task.phi,
              "aligned_sha256": hashlib.sha256(pickle.dumps(task.aligned, protocol=4)
                                               ).hexdigest(),
              "q_min": task.q_min, "q_max": task.q_max, "n_curve": N_CURVE_SAMPLES,
              "block_sat_px": BLOCK_SAT_PX, "margin_sat_px": MARGIN_SAT_PX}
    entry = manifest.cached(task.out_dir, key, inputs, params)
    if entry is not None and isinstance(entry.get("result"), dict):
        return CalibrateDone(entry["result"], skipped=True)
    with open_raster(task.sat_path, what="satellite scene on the shared grid") as sat:
        result = calibrate_flight(task.flight, task.aligned, sat, phi=task.phi,
                                  q_min=task.q_min, q_max=task.q_max)
    # Through JSON now, so that a fresh and a reused record are the same values.
    result = to_jsonable(result)
    manifest.record(task.out_dir, key, inputs, params, result=result)
    return CalibrateDone(result, skipped=False)


def run_calibrate(site: SiteConfig, out: RunPath) -> StepResult:
    """Calibrate Q of every flight against the satellite scene; write JSON and figure.

    Parameters
    ----------
    site
        The validated site (its ``parameters`` give φ, ``q_min`` and ``q_max``).
    out
        Run folder holding ``grid/satellite.tif``, ``grid/grid.json`` and
        ``alignment.json`` (the flights are read through their composed warps).

    Returns
    -------
    StepResult
        Record: ``mean_q``, per-flight ``q`` and ``lv_satellite``, ``not_calibrated``;
        warnings when a Q is outside the range of real cameras.

    Raises
    ------
    InputFileError
        An input of this step is missing (run the earlier steps first).
    CalibrationError
        No flight could be calibrated (``calibration.json`` is still written).
    """
    run = RunDir.of(out)
    p = site.parameters
    if site.satellite is None:
        raise ConfigError(f"site {site.name!r} has no [satellite] scene; calibration needs one "
                          "(add a [satellite] table with the image path)")
    sat_path = run.require_satellite_grid()
    flights_on_grid = aligned_flights(site, run)
    start = time.perf_counter()
    with open_raster(sat_path, what="satellite scene on the shared grid") as sat:
        if not image_band_indexes(sat):
            raise RasterError(f"{sat_path}: no image bands")
    tasks = [CalibrateTask(run.root, fid, flight, sat_path, phi=p.phi, q_min=p.q_min,
                           q_max=p.q_max) for fid, flight in flights_on_grid.items()]
    done = parallel_map(calibrate_task, tasks, desc="calibrate")
    flights = [d.result for d in done]
    n_skipped = sum(d.skipped for d in done)
    ok = [f for f in flights if f["status"] == "ok"]
    mean_q = float(np.mean([f["q"] for f in ok])) if ok else None
    warnings = [w for f in ok if (w := plausibility_warning(f["q"], what=f"Q of {f['flight']}"))]
    warning = plausibility_warning(mean_q, what="the mean calibrated Q") if ok else None
    doc: dict[str, Any] = {
        "site": site.name,
        "geosim_version": __version__,
        "satellite": run.rel(sat_path),
        "satellite_source": str(site.satellite.image),
        "satellite_acquired": (site.satellite.acquired.isoformat()
                               if site.satellite.acquired else None),
        "phi": p.phi, "uav_gsd_m": p.uav_gsd_m, "sat_gsd_m": p.sat_gsd_m,
        "q_min": p.q_min, "q_max": p.q_max, "obscuration": 0.0,
        "lv_definition": LV_DEFINITION,
        "solver": "Brent's method on LV(Q) - LV_satellite over [q_min, q_max], xtol 1e-4",
        "plausible_q_range": list(PLAUSIBLE_Q),
        "flights": flights,
        "mean_q": mean_q,
        "q_std": float(np.std([f["q"] for f in ok])) if ok else None,
        "n_calibrated": len(ok),
        "warning": warning,
        "flight_warnings": warnings,
        "seconds": round(time.perf_counter() - start, 3),
    }
    write_json(run.calibration_json, doc)
    plot_calibration(doc, run.calibration_png)
    if not ok:
        reasons = "; ".join(f"{f['flight']}: {f.get('error') or f.get('reason')}"
                            for f in flights)
        raise CalibrationError(f"no flight could be calibrated against the satellite scene "
                               f"({reasons}); see {run.calibration_json}")
    per = ", ".join(f"{f['flight']} {f['q']:.2f}" for f in ok)
    text = f"mean Q = {mean_q:.2f} over {len(ok)} flight(s) ({per})"
    skipped = [f["flight"] for f in flights if f["status"] != "ok"]
    if skipped:
        text += f"; not calibrated: {', '.join(skipped)}"
    text += skip_text(n_skipped, len(flights)).replace("current", "calibrated")
    return StepResult(
        summary=text + (" — Q outside 0.5–2: run geosim diagnose" if warning else ""),
        warnings=[warning] if warning else [],
        outputs=[run.rel(run.calibration_json), run.rel(run.calibration_png)],
        record={"mean_q": mean_q, "q": {f["flight"]: f["q"] for f in ok},
                "lv_satellite": {f["flight"]: f["lv_satellite"] for f in ok},
                "not_calibrated": skipped, "skipped_current": n_skipped})


# --------------------------------------------------------------------------- degrade

def read_calibrated_q(out: RunPath) -> float:
    """Mean Q from the run folder's ``calibration.json``."""
    path = RunDir.of(out).require_calibration()
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputFileError(f"{path} is not valid JSON ({exc}); re-run 'geosim calibrate'") \
            from None
    q = doc.get("mean_q") if isinstance(doc, dict) else None
    if not isinstance(q, (int, float)) or not math.isfinite(q) or q <= 0:
        raise CalibrationError(f"{path} has no calibrated mean Q (mean_q = {q!r}); fix the "
                               "calibration or give Q explicitly with --q")
    return float(q)


def degraded_transform(tile_transform: Affine, phi: int) -> Affine:
    """The 0.5 m tile's transform: same origin, pixel size × φ (exactly)."""
    return tile_transform @ Affine.scale(phi)


def degrade_tile(src: str | Path, dst: str | Path, *, q: float, phi: int,
                 method: str = "fast", obscuration: float = 0.0,
                 uav_gsd_m: float | None = None, tags: dict[str, str] | None = None,
                 trust_first_overview: bool = False) -> dict[str, Any]:
    """Degrade one UAV tile GeoTIFF to a satellite-resolution GeoTIFF.

    Parameters
    ----------
    src, dst
        Input UAV tile and output path (written atomically).
    q
        Q (dimensionless).
    phi
        UAV pixels per satellite pixel (whole number).
    method
        ``"fast"`` or ``"reference"``.
    uav_gsd_m
        Expected tile pixel size in metres (checked when given).
    tags
        Extra GeoTIFF tags (provenance).
    trust_first_overview
        The tile is known to be the file ``geosim tile`` wrote (its manifest entry vouches
        for it), so a tagged binomial first overview (:mod:`geosim.io.overviews`) is that
        of its pixels: the fast method then reads it instead of the full resolution where
        it can stand in (:func:`~geosim.degrade.core.level1_allowed`). Not for a tile
        edited in place since (its overviews would be stale).

    Returns
    -------
    dict
        ``shape`` (rows, cols) and ``valid_fraction`` of the output, and ``read_from``
        (:data:`READ_FULL` or :data:`READ_LEVEL1`).
    """
    from geosim.prepare.reproject import warp_threads

    src, dst = Path(src), Path(dst)
    # decode the compressed tile blocks (image and mask) on the task's threads; the
    # internal 1-bit mask is read as 0/1, without GDAL's pass scaling it to 0/255 (only
    # "non-zero = valid" is used): 0.026 → 0.016 s CPU for a 5000² mask. Both are decoded
    # into this thread's buffers of the previous tile (geosim.scratch: no new memory to
    # fault in); nothing below keeps them past this call.
    with rasterio.Env(GDAL_NUM_THREADS=str(warp_threads()),
                      GDAL_TIFF_INTERNAL_MASK_TO_8BIT=False):
        # a tile geosim wrote whole and valid carries the degradation's own first pyramid
        # level as its first overview: a quarter of the pixels to decode (the fast method
        # only; its rounding to whole DN is the one difference, docs/degradation.md)
        first = None
        if method == "fast" and trust_first_overview:
            first = read_binomial_level1(src, what="UAV tile", reuse_buffers=True,
                                         usable=lambda shape: level1_allowed(shape, q * phi))
        tile = (read_raster(src, what="UAV tile", reuse_buffers=True) if first is None
                else first.level)
    (rows, cols), transform = ((tile.shape, tile.transform) if first is None
                               else (first.shape, first.transform))
    if uav_gsd_m is not None and not math.isclose(abs(transform.a), uav_gsd_m,
                                                   rel_tol=1e-6):
        raise RasterError(f"{src}: pixel size {abs(transform.a)} m is not "
                          f"parameters.uav_gsd_m = {uav_gsd_m} m; the tiles come from "
                          "another run: re-run 'geosim tile'")
    if rows < phi or cols < phi:
        raise RasterError(f"{src}: {cols} × {rows} px is smaller than one "
                          f"satellite pixel ({phi} × {phi} px)")
    if first is None:
        degraded, valid_out = degrade_array(tile.array, q=q, phi=phi, valid=tile.valid,
                                            method=method, obscuration=obscuration,
                                            reuse_buffers=True)
    else:
        degraded, valid_out = degrade_level1(tile.array, (rows, cols), q=q, phi=phi,
                                             obscuration=obscuration, reuse_buffers=True)
    out = to_dtype(degraded, tile.array.dtype)
    names = list(tile.band_names)
    read_from = READ_FULL if first is None else READ_LEVEL1
    write_geotiff(dst, out, transform=degraded_transform(transform, phi), crs=tile.crs,
                  nodata=tile.nodata, mask=valid_out,
                  band_descriptions=names if all(names) else None,
                  tags={**(tags or {}), DEGRADE_READ_TAG: read_from})
    return {"shape": list(out.shape[1:]), "valid_fraction": float(valid_out.mean()),
            "read_from": read_from}


@dataclass(frozen=True)
class DegradeTileTask:
    """Degrade one UAV tile file (an engine task: picklable, writes its own output)."""

    src: str
    dst: str
    q: float
    phi: int
    method: str
    obscuration: float
    uav_gsd_m: float | None
    tags: dict[str, str]
    #: Run folder whose manifest says whether ``dst`` is current (None: always degrade).
    run_dir: str | None = None


def degrade_tile_task(task: DegradeTileTask) -> dict[str, Any]:
    """Run a :class:`DegradeTileTask` (see :func:`degrade_tile`) unless ``dst`` is current.

    The tags hold every parameter (Q, method, φ, GSDs, obscuration, sources); the result
    says whether the tile was ``skipped``.
    """
    if task.run_dir is not None and manifest.is_current(task.run_dir, task.dst, [task.src],
                                                        task.tags):
        return {"skipped": True}
    done = degrade_tile(task.src, task.dst, q=task.q, phi=task.phi, method=task.method,
                        obscuration=task.obscuration, uav_gsd_m=task.uav_gsd_m, tags=task.tags,
                        trust_first_overview=task.run_dir is not None
                        and manifest.vouched_for(task.run_dir, task.src))
    if task.run_dir is not None:
        manifest.record_output(task.run_dir, task.dst, [task.src], task.tags)
    return {**done, "skipped": False}


def run_degrade(site: SiteConfig, out: RunPath, q: float | None = None, *,
                method: str = "fast", obscuration: float = 0.0) -> StepResult:
    """Degrade every UAV tile to the satellite grid.

    Parameters
    ----------
    site
        The validated site (φ and GSDs from its parameters).
    out
        Run folder with ``tiles/<flight>/<tile>.tif``; writes ``degraded/<flight>/<tile>.tif``.
        Degraded tiles of an earlier run whose UAV tile is gone are removed by the runner
        (:func:`geosim.pipeline.run_pipeline`), from run.json's record of outputs.
    q
        Q to use; None = the site's ``parameters.q`` when set, else the mean calibrated
        Q from ``calibration.json``.
    method
        ``"fast"`` (default) or ``"reference"`` (the paper's literal operation).
    obscuration
        Central obscuration of the simulated telescope, diameter ratio in [0, 1).

    Returns
    -------
    StepResult
        Record: ``q``, ``q_source``, ``method``, tiles per flight, timing.
    """
    run = RunDir.of(out)
    p = site.parameters
    if method not in METHODS:
        raise ConfigError(f"method {method!r} is not one of {', '.join(METHODS)}")
    if not 0.0 <= obscuration < 1.0:
        raise ConfigError(f"obscuration = {obscuration} must be a diameter ratio in [0, 1)")
    if q is None and p.q is not None:
        q, q_source = p.q, "site parameters.q"
    elif q is None:
        q, q_source = read_calibrated_q(run), run.rel(run.calibration_json)
    else:
        q_source = "user"
        if not (isinstance(q, (int, float)) and math.isfinite(q) and q > 0):
            raise ConfigError(f"Q = {q!r} must be a positive number (e.g. 4.34)")
        q = float(q)
    tiles_dir = run.require_tiles_dir()
    jobs = [(f.id, path) for f in site.flights for path in run.tile_files(f.id)]
    if not jobs:
        raise InputFileError(f"no tiles in {tiles_dir}/<flight>/ for flights "
                             f"{', '.join(site.flight_ids)}; run 'geosim tile' first")
    params = {"q": q, "q_source": q_source, "phi": p.phi, "uav_gsd_m": p.uav_gsd_m,
              "sat_gsd_m": p.sat_gsd_m, "method": method, "obscuration": obscuration,
              "model": "I_sat = (I_uav conv PSF_airy(Q)) downsampled by phi with "
                       "cv2 INTER_CUBIC; symmetric boundary; no-data filled by pull-push"}
    counts: dict[str, int] = {fid: 0 for fid in site.flight_ids}
    acquired = {f.id: f.acquired for f in site.flights}
    start = time.perf_counter()
    tasks = []
    outputs = []
    for fid, src in jobs:
        dst = run.degraded(fid, src.stem)
        tags = {**provenance_tags("degrade", params, [src], base_dir=run.root),
                "GEOSIM_Q": f"{q:.6g}", "GEOSIM_METHOD": method,
                "GEOSIM_UAV_GSD_M": f"{p.uav_gsd_m:g}", "GEOSIM_SAT_GSD_M": f"{p.sat_gsd_m:g}",
                "GEOSIM_FLIGHT": fid, "GEOSIM_TILE_ID": src.stem,
                **acquisition_tags(acquired[fid])}
        tasks.append(DegradeTileTask(str(src), str(dst), q, p.phi, method, obscuration,
                                     p.uav_gsd_m, tags, str(run.root)))
        outputs.append(run.rel(dst))
    results = list(parallel_map(degrade_tile_task, tasks, desc="degrade"))
    n_skipped = sum(r["skipped"] for r in results)
    n_level1 = sum(r.get("read_from") == READ_LEVEL1 for r in results)
    for fid, _src in jobs:
        counts[fid] += 1
    seconds = time.perf_counter() - start
    warning = plausibility_warning(q, what="Q")
    return StepResult(
        summary=(f"{len(jobs)} tile(s) degraded to {p.sat_gsd_m:g} m at Q = {q:.3g} "
                 f"({q_source}, {method} method) in {run.rel(run.degraded_dir)}/"
                 + skip_text(n_skipped, len(jobs))),
        warnings=[warning] if warning else [], outputs=outputs,
        record={"q": q, "q_source": q_source, "method": method, "tiles": len(jobs),
                "tiles_per_flight": counts, "out": run.rel(run.degraded_dir),
                "seconds_per_tile": round(seconds / len(jobs), 3),
                "skipped_current": n_skipped,
                # tiles degraded from their binomial first overview (the rest: full resolution)
                "read_from_first_overview": n_level1})
