"""Pipeline steps of the map-coordinate preparation: grid → footprints → align → tiles → pairs.

Each ``run_<step>(site, out) -> StepResult`` reads earlier outputs from the run folder
(:class:`geosim.rundir.RunDir`, layout in docs/outputs.md), writes its own atomically
and returns a :class:`geosim.result.StepResult`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import geopandas as gpd
import numpy as np
from affine import Affine
from rasterio.windows import Window

from geosim.align.phasecorr import as_grey
from geosim.config import SiteConfig
from geosim.engine import parallel_map
from geosim.errors import AlignmentError, ExtentError
from geosim.io.atomic import write_json, write_text
from geosim.io.raster import acquisition_tags, open_raster, provenance_tags
from geosim.io.vector import write_geojson, write_gpkg
from geosim.manifest import ResumableTask, run_resumable, skip_text
from geosim.prepare import alignment as al
from geosim.prepare import anchor as anc
from geosim.prepare.footprints import common_extent, raster_footprint, source_footprint
from geosim.prepare.grid import SiteGrid, resolve_site_crs, snap_grid, union_bounds
from geosim.prepare.onewarp import (
    ComposedWarp,
    WarpedGreyReader,
    WarpRasterTask,
    warp_raster_task,
)
from geosim.prepare.pairs import pair_rows, pairs_csv_text
from geosim.prepare.reproject import bounds_in_crs, reproject_to_grid
from geosim.prepare.tiles import (
    AlignedCoverageTask,
    WarpTileTask,
    aligned_coverage_task,
    index_records,
    iter_tiles,
    select_tiles,
    warp_tile_task,
)
from geosim.result import StepResult
from geosim.rundir import RunDir, RunPath

#: A common extent smaller than this many UAV pixels (100 × 100) is "tiny": an error.
MIN_COMMON_UAV_PX = 100 * 100
#: Side of the local-check windows (UAV px) and the largest block read at once.
LOCAL_WINDOW_PX = 256
BLOCK_PX = 2048
#: Tile windows per coverage task (one flight's masks over this many tiles).
COVERAGE_CHUNK = 8


def _crs_name(crs: Any) -> str:
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg else crs.to_wkt()


def read_grid(out: RunPath) -> SiteGrid:
    """``grid/grid.json`` of the run folder as a :class:`SiteGrid` (InputFileError if absent)."""
    return SiteGrid.from_dict(json.loads(RunDir.of(out).require_grid().read_text()))


# --------------------------------------------------------------------------- grid


def run_grid(site: SiteConfig, out: RunPath) -> StepResult:
    """Choose the site CRS, build the nested grids, reproject flights and satellite onto them.

    Writes ``grid/grid.json``, ``grid/<flight>.tif`` (UAV grid, bicubic, internal mask)
    and ``grid/satellite.tif`` (satellite grid, cut to the grid's extent).
    """
    run = RunDir.of(out)
    p = site.parameters
    lonlat, what = [], {}
    for f in site.flights:
        with open_raster(f.image, what=f"flight {f.id}") as ds:
            lonlat.append(bounds_in_crs(ds, "EPSG:4326"))
    crs = resolve_site_crs(site.crs, lonlat)
    extents = []
    for f in site.flights:
        with open_raster(f.image, what=f"flight {f.id}") as ds:
            extents.append(bounds_in_crs(ds, crs))
            what[f.id] = ds.crs.to_string()
    grid = snap_grid(union_bounds(extents), crs, uav_gsd_m=p.uav_gsd_m, sat_gsd_m=p.sat_gsd_m)
    run.grid_dir.mkdir(parents=True, exist_ok=True)
    written: dict[str, Any] = {}
    params = {"uav_gsd_m": p.uav_gsd_m, "sat_gsd_m": p.sat_gsd_m, "crs": _crs_name(crs),
              "resampling": "bicubic"}
    if p.keep_intermediates:  # flights on the site grid: inspection copies only
        tasks = [WarpRasterTask(ComposedWarp.for_flight(f.image, crs, grid.uav_transform),
                                str(run.grid_raster(f.id)), tuple(grid.uav_transform)[:6],
                                grid.uav_shape, BLOCK_PX,
                                provenance_tags("grid", params, [f.image]), f"flight {f.id}")
                 for f in site.flights]
        for f, rec in zip(site.flights, parallel_map(warp_raster_task, tasks), strict=True):
            written[f.id] = {"source_crs": rec.source_crs, "valid_px": rec.valid_px}
    else:
        for f in site.flights:
            written[f.id] = {"source_crs": what[f.id], "valid_px": None,
                             "resampled": "on the fly (keep_intermediates = false)"}
    if site.satellite is not None:
        written["satellite"] = reproject_to_grid(
            site.satellite.image, run.satellite_grid, crs=crs, transform=grid.sat_transform,
            shape=grid.sat_shape, what="satellite scene", block_px=BLOCK_PX,
            tags=provenance_tags("grid", params, [site.satellite.image]))
    doc = grid.to_dict()
    doc["extent_rule"] = ("union of the flights' extents, snapped outward to whole satellite "
                          "pixels; the satellite scene is cut to it")
    doc["sources"] = {k: {kk: v[kk] for kk in ("source_crs", "valid_px", "resampled")
                          if kk in v} for k, v in written.items()}
    write_json(run.grid_json, doc)
    rows, cols = grid.uav_shape
    outputs = [run.grid_json]
    if p.keep_intermediates:
        outputs += [run.grid_raster(f.id) for f in site.flights]
    if site.satellite is not None:
        outputs.append(run.satellite_grid)
    return StepResult(
        summary=(f"{_crs_name(crs)}, UAV grid {cols}×{rows} px at {p.uav_gsd_m} m, "
                 f"{len(site.flights)} flight(s)"
                 + (" + satellite" if site.satellite is not None else "")),
        outputs=[run.rel(o) for o in outputs],
        record={"crs": _crs_name(crs), "uav_shape": list(grid.uav_shape),
                "sat_shape": list(grid.sat_shape),
                "origin_m": [grid.uav_transform.c, grid.uav_transform.f],
                "rasters": sorted(written)})


# --------------------------------------------------------------------------- footprints


@dataclass(frozen=True)
class FootprintTask:
    """One flight's valid-data footprint, traced on its own grid (an engine task)."""

    path: str
    site_crs: Any
    cell_m: float
    simplify_m: float


def footprint_task(task: FootprintTask) -> Any:
    """Run a :class:`FootprintTask` (:func:`source_footprint`): the polygon, site CRS."""
    return source_footprint(task.path, task.site_crs, cell_m=task.cell_m,
                            simplify_m=task.simplify_m)


def run_footprints(site: SiteConfig, out: RunPath) -> StepResult:
    """Trace valid-data footprints on the grid and intersect them.

    Writes ``footprints.geojson`` (+ ``.gpkg`` in the site CRS) with each raster's
    polygon and area, and ``common_extent.geojson`` (+ ``.gpkg``) with the flights'
    intersection (``name = flights``, per-flight coverage) and its intersection with
    the satellite footprint (``name = flights_and_satellite``).

    Raises
    ------
    ExtentError
        The flights' common extent is empty or smaller than 100 × 100 UAV pixels.
    """
    run = RunDir.of(out)
    grid = read_grid(run)
    p = site.parameters
    fps: dict[str, Any] = {}
    rows = []
    # traced on the original flight (no copy on the site grid needed), one task per flight
    traced = parallel_map(footprint_task, [
        FootprintTask(str(f.image), grid.crs, grid.sat_gsd_m, p.footprint_simplify_m)
        for f in site.flights], desc="footprints")
    for f, geom in zip(site.flights, traced, strict=True):
        fps[f.id] = geom
        rows.append({"id": f.id, "kind": "flight", "acquired": f.acquired.isoformat(),
                     "source": str(f.image), "area_m2": fps[f.id].area,
                     "bbox_area_m2": fps[f.id].envelope.area, "geometry": fps[f.id]})
    sat_fp = None
    sat_path = run.satellite_grid
    if site.satellite is not None and sat_path.is_file():
        sat_fp = raster_footprint(sat_path, reduce_px=1, simplify_m=p.footprint_simplify_m)
        rows.append({"id": "satellite", "kind": "satellite",
                     "acquired": site.satellite.acquired.isoformat()
                     if site.satellite.acquired else None,
                     "source": str(site.satellite.image), "area_m2": sat_fp.area,
                     "bbox_area_m2": sat_fp.envelope.area, "geometry": sat_fp})
    gdf = gpd.GeoDataFrame(rows, geometry="geometry", crs=grid.crs.to_wkt())
    write_geojson(gdf, run.footprints_geojson)
    write_gpkg(gdf, run.footprints_gpkg, layer="footprints")

    min_area = MIN_COMMON_UAV_PX * grid.uav_gsd_m ** 2
    common = common_extent(fps, min_area_m2=min_area)
    ce_rows = [{"name": "flights", "flights": ",".join(fps), "area_m2": common.area,
                **{f"coverage_{k}": common.area / v.area for k, v in fps.items()},
                "geometry": common}]
    sat_area = None
    if sat_fp is not None:
        with_sat = common.intersection(sat_fp)
        sat_area = with_sat.area
        ce_rows.append({"name": "flights_and_satellite", "flights": ",".join(fps),
                        "area_m2": sat_area,
                        **{f"coverage_{k}": sat_area / v.area for k, v in fps.items()},
                        "geometry": with_sat if not with_sat.is_empty else None})
    ce = gpd.GeoDataFrame(ce_rows, geometry="geometry", crs=grid.crs.to_wkt())
    write_geojson(ce, run.common_extent_geojson)
    write_gpkg(ce, run.common_extent_gpkg, layer="common_extent")
    warnings = []
    if sat_area is not None and sat_area <= 0:
        warnings.append("the satellite footprint does not overlap the flights' common "
                        "extent: calibration and diagnosis will have nothing to compare")
    return StepResult(
        summary=(f"common extent {common.area:.0f} m² of {len(fps)} flight(s)"
                 + ("" if sat_area is None else f", {sat_area:.0f} m² with the satellite")),
        warnings=warnings,
        outputs=[run.rel(o) for o in (run.footprints_geojson, run.footprints_gpkg,
                                      run.common_extent_geojson, run.common_extent_gpkg)],
        record={"common_area_m2": round(common.area, 3),
                "footprint_area_m2": {k: round(v.area, 3) for k, v in fps.items()},
                "satellite_overlap_m2": None if sat_area is None else round(sat_area, 3)})


def read_common_extent(out: RunPath) -> Any:
    """The flights' common extent polygon (site CRS) from ``common_extent.gpkg``."""
    gdf = gpd.read_file(RunDir.of(out).require_common_extent())
    return gdf.loc[gdf["name"] == "flights"].geometry.iloc[0]


# --------------------------------------------------------------------------- align


CONVENTION_REFERENCE = (
    "Per flight, the correction C maps map coordinates (site CRS, x east, y north, m) "
    "as stated by that flight's georeference to the aligned frame (the reference "
    "flight's): C(p) = center_m + shift_m + scale * R(rotation_deg) * (p - center_m), "
    "rotation counter-clockwise on a north-up map. matrix_px: reference window pixel "
    "-> moving window pixel (pixel centres at integers); matrix_grid_px: the same in "
    "site UAV grid corner coordinates.")
CONVENTION_SATELLITE = (
    "Per flight, the correction C' = T o C maps map coordinates (site CRS, x east, y north, "
    "m) as stated by that flight's georeference to the aligned frame, which is the "
    "satellite scene's: C registers the flight to the reference flight (kept under "
    "to_reference), T (anchor) registers the reference flight to the satellite scene. "
    "C'(p) = center_m + shift_m + scale * R(rotation_deg) * (p - center_m), rotation "
    "counter-clockwise on a north-up map. matrix_px: the kernel's reference window pixel "
    "-> moving window pixel (flight to reference flight, pixel centres at integers); "
    "matrix_grid_px: aligned-frame site UAV grid corner coordinates -> the flight's grid "
    "corner coordinates (C' as applied).")
ANCHOR_NONE_METHOD = ("none: the aligned frame is the reference flight's stated georeference "
                      "(the paper's behaviour)")


def _identity_anchor(center_m: list[float]) -> dict[str, Any]:
    return {"to": "reference_flight", "shift_m": [0.0, 0.0], "rotation_deg": 0.0,
            "scale": 1.0, "center_m": list(center_m), "confidence": 1.0,
            "method": ANCHOR_NONE_METHOD, "model": "identity"}


def anchor_to_satellite(site: SiteConfig, out: RunPath, grid: SiteGrid, window: Any,
                        center_m: list[float]) -> tuple[Affine, dict[str, Any]]:
    """Register the reference flight to the satellite scene on the 0.5 m grid.

    The reference flight (``grid/<ref>.tif``) is area-averaged over ``window`` (the
    aligned window, whole satellite pixels) and registered to the same window of
    ``grid/satellite.tif`` (:func:`geosim.prepare.anchor.register_to_satellite`).

    Returns
    -------
    (T, record)
        ``T`` maps reference-frame map coordinates to satellite-frame ones; the
        record is ``alignment.json["anchor"]``.

    Raises
    ------
    AlignmentError
        The registration confidence is below ``min_align_confidence`` or the overlap
        is too small; the message names the satellite and the reference flight and
        points to ``anchor = "reference_flight"``.
    InputFileError
        ``grid/satellite.tif`` is missing.
    """
    run = RunDir.of(out)
    ref_id = site.reference_flight
    sat_path = run.require(run.satellite_grid, "grid",
                           what="(site.anchor = 'satellite' registers the reference flight "
                                "to it)")
    phi = grid.phi
    kept = run.grid_raster(ref_id)
    if kept.is_file():  # keep_intermediates: the reference already on the site grid
        ref = anc.read_averaged_window(kept, window, phi, block_px=(BLOCK_PX // phi) * phi)
        ref_grey, ref_valid = ref.array[0], ref.valid
    else:  # resampled on the fly, strip by strip on the engine (nothing written)
        ref_grey, ref_valid = anc.read_averaged_through_warp(
            ComposedWarp.for_flight(site.flight(ref_id).image, grid.crs, grid.uav_transform),
            grid.uav_transform, window, phi, block_px=(BLOCK_PX // phi) * phi)
    sat_win = Window(int(window.col_off) // phi, int(window.row_off) // phi,
                     int(window.width) // phi, int(window.height) // phi)
    sat = anc.read_satellite_window(sat_path, sat_win)
    sat_grey, sat_valid, sat_t = as_grey(sat.array), sat.valid, sat.transform
    sat_name = site.satellite.image if site.satellite is not None else sat_path
    try:
        fit = anc.register_to_satellite(ref_grey, ref_valid, sat_grey, sat_valid,
                                        min_confidence=site.parameters.min_align_confidence,
                                        what=f"reference flight {ref_id} against the satellite")
    except AlignmentError as exc:
        raise AlignmentError(
            f"site.anchor = 'satellite': cannot register reference flight {ref_id} to the "
            f"satellite scene {sat_name} ({exc}); the two share too little stable texture "
            "(other season, clouds, little overlap). Set anchor = \"reference_flight\" in "
            "[site] to keep the reference flight's georeference (the paper's behaviour), or "
            "lower parameters.min_align_confidence if you trust the scene") from exc
    t = anc.anchor_affine(fit.matrix_px, sat_t)
    cx, cy = center_m
    moved = t @ (cx, cy)
    record = {
        "to": "satellite",
        "shift_m": [float(moved[0] - cx), float(moved[1] - cy)],
        "rotation_deg": math.degrees(math.atan2(t.d, t.a)),
        "scale": math.sqrt(abs(t.determinant)),
        "center_m": [float(cx), float(cy)],
        "confidence": fit.confidence,
        "method": anc.METHOD,
        "model": fit.model,
        "correction_affine": [float(v) for v in list(t)[:6]],
        "reference_flight": ref_id,
        "satellite": run.rel(run.satellite_grid),
        "satellite_source": str(sat_name),
        "window_sat_px": {"col_off": int(sat_win.col_off), "row_off": int(sat_win.row_off),
                          "width": int(sat_win.width), "height": int(sat_win.height)},
        "registration": fit.to_dict(),
        "convention": ("T maps map coordinates in the reference flight's frame to the "
                       "satellite scene's frame: T(p) = center_m + shift_m + scale * "
                       "R(rotation_deg) * (p - center_m); registration.matrix_px maps "
                       "satellite pixel centres to the area-averaged reference's (window "
                       "window_sat_px of grid/satellite.tif)."),
    }
    return t, record


def _local_fields(site: SiteConfig, run: RunDir, grid: SiteGrid, awin: Window,
                  tasks: dict[str, WarpRasterTask], params: dict[str, Any]
                  ) -> tuple[dict[str, dict[str, Any]], list[WarpRasterTask]]:
    """``align_model = "local"``: estimate each flight's displacement field.

    The field is measured between the aligned reference and the globally aligned flight,
    both read on the fly through their composed warps (nothing written), fitted
    (:mod:`geosim.align.field`) and written to ``alignment_field/<flight>.tif``. Returns
    the ``local_field`` record per flight and the other flights' warp tasks with the field
    plugged into the composed warp: each flight is then resampled once, from its original
    file, onto the aligned grid (tile by tile by the tiles step; whole, into ``aligned/``,
    only with ``keep_intermediates``).
    """
    from dataclasses import replace

    from geosim.align.field import fit_field, reject_outliers
    from geosim.prepare import local_align as la

    ref_id = site.reference_flight
    ref = site.flight(ref_id)
    aligned_transform = grid.uav_window_transform(awin)
    shape = (int(awin.height), int(awin.width))
    records: dict[str, dict[str, Any]] = {}
    local_tasks = []
    ref_task = tasks[ref_id]
    measured = la.measure_local_shifts_many(  # every flight's strips: engine tasks
        WarpedGreyReader(ref_task.warp, ref_task.dst_transform),
        {f.id: WarpedGreyReader(tasks[f.id].warp, tasks[f.id].dst_transform)
         for f in site.flights if f.id != ref_id}, shape=shape)
    for f in site.flights:
        if f.id == ref_id:
            continue
        task = tasks[f.id]
        shifts = reject_outliers(measured[f.id],
                                 min_confidence=site.parameters.min_align_confidence)
        field = fit_field(shifts, aligned_transform, shape)
        rel = run.rel(run.alignment_field(f.id))
        tags = provenance_tags("align", params, [ref.image, f.image], base_dir=run.root)
        la.write_field_geotiff(run.alignment_field(f.id), field, grid.crs, tags=tags)
        warp_tags = provenance_tags(
            "align", {**params, "resampled": "once, from the original flight, through the "
                      "global correction and the local field"},
            [f.image, run.alignment_field(f.id)], base_dir=run.root)
        local_tasks.append(replace(task, warp=la.with_field(task.warp, field), tags=warp_tags))
        records[f.id] = la.field_record(field, shifts, rel)
    return records, local_tasks


def _aligned_tasks(site: SiteConfig, run: RunDir, grid: SiteGrid,
                   warps: dict[str, ComposedWarp], entries: dict[str, dict[str, Any]],
                   rwin: Window, awin: Window, params: dict[str, Any]
                   ) -> dict[str, WarpRasterTask]:
    """The warps of every flight onto the aligned grid through its global correction, as
    engine tasks writing ``aligned/<flight>.tif`` (run only with ``keep_intermediates``).
    Records each flight's ``C⁻¹`` in ``entries[flight]["aligned_to_stated"]``."""
    aligned_transform = grid.uav_window_transform(awin)
    g3 = al._3x3(grid.uav_transform)
    tasks = {}
    for f in site.flights:
        if site.anchor == "satellite":
            m_grid = np.vstack([np.array(entries[f.id]["matrix_grid_px"]), [0.0, 0.0, 1.0]])
        else:
            m_grid = al.window_to_grid_matrix(np.array(entries[f.id]["matrix_px"]), rwin)
        # C⁻¹ in map coordinates: aligned frame → the flight's stated frame
        c_inv = al._affine_from_3x3(g3 @ m_grid @ np.linalg.inv(g3))
        # recorded: the tiles, the calibration and the diagnosis rebuild the warp from it
        entries[f.id]["aligned_to_stated"] = [float(v) for v in tuple(c_inv)[:6]]
        tasks[f.id] = WarpRasterTask(
            warps[f.id].with_correction(c_inv), str(run.aligned(f.id)),
            tuple(aligned_transform)[:6], (int(awin.height), int(awin.width)), BLOCK_PX,
            provenance_tags("align", {**params, "resampled": "once, from the original flight"},
                            [f.image], base_dir=run.root), f.id)
    return tasks


def _run_warps(run: RunDir, tasks: list[WarpRasterTask]) -> int:
    """Run warp tasks (resumable: a raster made by the same task — warp, field, tags — from
    the same file is skipped); returns how many were skipped."""
    return sum(parallel_map(run_resumable, [
        ResumableTask(str(run.root), warp_raster_task, t, t.dst_path, (t.warp.src_path,))
        for t in tasks], desc="align"))


def _local_check(site: SiteConfig, run: RunDir, grid: SiteGrid, awin: Window,
                 tasks: dict[str, WarpRasterTask]) -> tuple[dict[str, Any], bool]:
    """Remaining shift field between each aligned flight and the reference (both read
    through their warps); writes ``alignment_check.geojson``. Returns the ``local_check``
    statistics per flight and whether the arrows file was written."""
    ref_id = site.reference_flight
    p = site.parameters
    aligned_transform = grid.uav_window_transform(awin)
    local: dict[str, Any] = {}
    arrows = []
    win_px = int(min(LOCAL_WINDOW_PX, max(64, min(awin.width, awin.height) // 4)))
    shape = (int(awin.height), int(awin.width))
    checks = al.local_checks(
        WarpedGreyReader(tasks[ref_id].warp, tasks[ref_id].dst_transform),
        {f.id: WarpedGreyReader(tasks[f.id].warp, tasks[f.id].dst_transform)
         for f in site.flights if f.id != ref_id},
        shape=shape, window_px=win_px, block_px=BLOCK_PX, min_confidence=p.min_align_confidence)
    for f in site.flights:
        if f.id == ref_id:
            continue
        recs = checks[f.id]
        shifts = np.array([[r["dx_px"], r["dy_px"]] for r in recs]).reshape(-1, 2)
        conf = np.array([r["confident"] for r in recs], dtype=bool)
        local[f.id] = {**al.local_field_stats(shifts, conf, grid.uav_gsd_m),
                       "window_px": win_px}
        arrows.append(al.arrows_gdf(recs, aligned_transform, grid.crs.to_wkt(), f.id))
    if arrows:
        import pandas as pd

        gdf = gpd.GeoDataFrame(pd.concat(arrows, ignore_index=True), geometry="geometry",
                               crs=grid.crs.to_wkt())
        write_geojson(gdf, run.alignment_check_geojson)
    return local, bool(arrows)


def run_align(site: SiteConfig, out: RunPath) -> StepResult:
    """Register every flight to the reference and resample it onto the aligned grid.

    With ``site.anchor = "satellite"`` the reference flight is also registered to the
    satellite scene (:func:`anchor_to_satellite`) and that transform ``T`` is composed
    into every flight's correction (``C' = T ∘ C``), so the aligned flights (the
    reference included, then resampled rather than copied) land in the satellite's
    frame; the aligned window follows ``T``.

    Writes ``aligned/<flight>.tif``, ``alignment.json`` and ``alignment_check.geojson``
    (local shift arrows). See :mod:`geosim.prepare.alignment` for the conventions;
    ``alignment.json["anchor"]`` records ``to``, ``shift_m``, ``rotation_deg``,
    ``scale``, ``center_m``, ``confidence`` and ``method``.

    Raises
    ------
    AlignmentError
        A flight's registration confidence (or the reference flight's against the
        satellite, with the satellite anchor) is below ``min_align_confidence``.
    """
    run = RunDir.of(out)
    grid = read_grid(run)
    common = read_common_extent(run)
    p = site.parameters
    ref_id = site.reference_flight
    awin = al.aligned_window(common, grid)
    rwin = al.registration_window(common, grid, awin, p.align_window_px)
    # flights reach the site grid on the fly, through the same composed warp as the tiles
    warps = {f.id: ComposedWarp.for_flight(f.image, grid.crs, grid.uav_transform)
             for f in site.flights}
    win_dict = {"col_off": int(rwin.col_off), "row_off": int(rwin.row_off),
                "width": int(rwin.width), "height": int(rwin.height)}
    regs = _register_flights(site, warps, rwin, win_dict)
    entries: dict[str, dict[str, Any]] = {}
    for f in site.flights:
        if f.id == ref_id:
            entry = al.identity_entry(rwin, grid.uav_transform)
        else:
            reg = regs[f.id]
            entry = al.correction_from_matrix(np.array(reg["matrix_px"]), rwin,
                                              grid.uav_transform)
            entry.update(confidence=reg["confidence"], matrix_px=reg["matrix_px"],
                         kernel=reg["kernel"])
        entry["window"] = win_dict
        if p.keep_intermediates:
            entry["path"] = run.rel(run.aligned(f.id))
        entries[f.id] = entry

    center_m = entries[ref_id]["center_m"]
    params = {"reference": ref_id, "align_window_px": p.align_window_px}
    if site.anchor == "satellite":
        t_anchor, anchor = anchor_to_satellite(site, run, grid, awin, center_m)
        entries = {k: anc.compose_entry(e, t_anchor, grid.uav_transform)
                   for k, e in entries.items()}
        from shapely.affinity import affine_transform

        awin = al.aligned_window(affine_transform(common, [t_anchor.a, t_anchor.b, t_anchor.d,
                                                           t_anchor.e, t_anchor.c, t_anchor.f]),
                                 grid)
        params["anchor"] = "satellite"
    else:
        anchor = _identity_anchor(center_m)
    aligned_transform = grid.uav_window_transform(awin)
    tasks = _aligned_tasks(site, run, grid, warps, entries, rwin, awin, params)
    if p.align_model == "local":
        params["align_model"] = "local"
        # the field is measured against the reference read through its warp (nothing
        # written); every other flight is then resampled once, from its original file,
        # through global correction + field
        records, local_tasks = _local_fields(site, run, grid, awin, tasks, params)
        for fid, rec in records.items():
            entries[fid]["local_field"] = rec
        tasks.update({t.what: t for t in local_tasks})
    n_skipped = 0
    if p.keep_intermediates:  # the whole-flight aligned rasters: inspection copies only
        n_skipped = _run_warps(run, list(tasks.values()))

    # local check: remaining shift field between each aligned flight and the reference
    local, arrows = _local_check(site, run, grid, awin, tasks)

    doc = {
        "reference": ref_id,
        "convention": (CONVENTION_SATELLITE if site.anchor == "satellite"
                       else CONVENTION_REFERENCE),
        "anchor": anchor,
        "crs": _crs_name(grid.crs),
        "aligned_grid": {"transform": list(aligned_transform)[:6],
                         "shape": [int(awin.height), int(awin.width)],
                         "window_px": {"col_off": int(awin.col_off),
                                       "row_off": int(awin.row_off),
                                       "width": int(awin.width), "height": int(awin.height)}},
        "registration_window_px": win_dict,
        "align_model": p.align_model,
        "flights": entries,
        "local_check": local,
    }
    write_json(run.alignment_json, doc)
    worst = max((abs(e["shift_m"][0]) + abs(e["shift_m"][1]), k) for k, e in entries.items())
    anchor_text = ("" if anchor["to"] != "satellite" else
                   f"; anchored to the satellite (shift {anchor['shift_m'][0]:+.3f}, "
                   f"{anchor['shift_m'][1]:+.3f} m, {anchor['model']}, confidence "
                   f"{anchor['confidence']:.2f})")
    outputs = [run.alignment_json]
    if p.keep_intermediates:
        outputs += [run.aligned(f.id) for f in site.flights]
    outputs += [run.alignment_field(k) for k, e in entries.items() if "local_field" in e]
    if arrows:
        outputs.append(run.alignment_check_geojson)
    record = {"reference": ref_id, "aligned_shape": [int(awin.height), int(awin.width)],
            "anchor": {"to": anchor["to"], "shift_m": [round(v, 4) for v in anchor["shift_m"]],
                       "rotation_deg": round(anchor["rotation_deg"], 5),
                       "scale": round(anchor["scale"], 6),
                       "confidence": round(anchor["confidence"], 3)},
            "flights": {k: {"shift_m": [round(v, 4) for v in e["shift_m"]],
                            "rotation_deg": round(e["rotation_deg"], 5),
                            "scale": round(e["scale"], 6),
                            "confidence": round(e["confidence"], 3)}
                        for k, e in entries.items()},
            "local_median_shift_px": {k: v["median_shift_px"] for k, v in local.items()},
            "align_model": p.align_model, "skipped_current": n_skipped}
    return StepResult(
        summary=(f"{len(entries)} flight(s) on reference {ref_id} ({p.align_model}); "
                 f"aligned grid {int(awin.width)}×{int(awin.height)} px; largest |shift| "
                 f"at flight {worst[1]}{anchor_text}"
                 + ("" if p.keep_intermediates else "; flights resampled once, tile by tile, "
                   "by the tiles step (aligned/ kept only with keep_intermediates)")
                + skip_text(n_skipped, len(entries)).replace("current", "aligned")),
        warnings=_fallback_warnings(entries), outputs=[run.rel(o) for o in outputs],
        record=record)


def _register_flights(site: SiteConfig, warps: dict[str, ComposedWarp], rwin: Window,
                      win_dict: dict[str, int]) -> dict[str, dict[str, Any]]:
    """Register every other flight to the reference over ``rwin`` (site grid): one engine
    task per flight, each reading both windows through their warps (nothing written)."""
    ref_id = site.reference_flight

    def on_grid(fid: str) -> WarpedGreyReader:
        warp = warps[fid].with_correction(Affine.identity())
        return WarpedGreyReader(warp, warp.grid_transform)

    others = [f.id for f in site.flights if f.id != ref_id]
    tasks = [al.RegistrationTask(
        on_grid(ref_id), on_grid(fid), rwin, site.parameters.min_align_confidence,
        (f"flight {fid} against reference flight {ref_id} (window {win_dict}; check the "
         "flight, choose another reference_flight or a larger align_window_px)"))
        for fid in others]
    return dict(zip(others, parallel_map(al.registration_task, tasks, desc="register"),
                    strict=True))


def _fallback_warnings(entries: dict[str, dict[str, Any]]) -> list[str]:
    """A warning when the local field fell back to the global similarity somewhere."""
    fallback = {k: e["local_field"]["fallback"]["node_fraction"] for k, e in entries.items()
                if "local_field" in e and e["local_field"]["fallback"]["node_fraction"] > 0}
    if not fallback:
        return []
    return ["local field not estimated (global similarity kept) on "
            + ", ".join(f"{v:.1%} of the nodes of {k}" for k, v in fallback.items())
            + "; see local_field.fallback in alignment.json and the masks of alignment_field/"]


# --------------------------------------------------------------------------- tiles


def read_alignment(out: RunPath) -> dict[str, Any]:
    """``alignment.json`` (InputFileError if absent)."""
    return json.loads(RunDir.of(out).require_alignment().read_text())


def run_tiles(site: SiteConfig, out: RunPath) -> StepResult:
    """Resample every flight once, tile by tile, onto ``tile_px`` tiles of the aligned grid.

    Each tile of each flight is one engine task that reads the original flight through its
    composed warp (:mod:`geosim.prepare.aligned`): no full-flight aligned raster is needed.
    Writes ``tiles/<flight>/<tile_id>.tif`` and ``tiles/index.geojson`` (+ ``.gpkg``,
    ``.json``). Tiles of an earlier run that this one does not write are removed by the
    runner (:func:`geosim.pipeline.run_pipeline`), from run.json's record of outputs.
    """
    from geosim.prepare.aligned import aligned_flights, flight_inputs

    run = RunDir.of(out)
    grid = read_grid(run)
    doc = read_alignment(run)
    p = site.parameters
    ag = doc["aligned_grid"]
    aligned_transform = Affine(*ag["transform"])
    shape = (int(ag["shape"][0]), int(ag["shape"][1]))
    tiles = list(iter_tiles(shape, aligned_transform, p.tile_px))
    flights = aligned_flights(site, run)
    windows = tuple(t.window for t in tiles)
    chunks = [windows[k:k + COVERAGE_CHUNK] for k in range(0, len(windows), COVERAGE_CHUNK)]
    jobs_cov = [(fid, c) for fid in flights for c in chunks]
    fractions = parallel_map(aligned_coverage_task, [
        AlignedCoverageTask(flights[fid], c, BLOCK_PX) for fid, c in jobs_cov],
        desc="tile coverage")
    coverage: dict[str, list[float]] = {fid: [] for fid in flights}
    for (fid, _), part in zip(jobs_cov, fractions, strict=True):
        coverage[fid].extend(part)
    selected = select_tiles(tiles, coverage, keep_partial=p.keep_partial_tiles)
    if not selected:  # refuse before anything is written: an empty tile set helps nobody
        size_m = p.tile_px * p.uav_gsd_m
        why = (f"none of the {len(tiles)} tile(s) is fully covered by every flight's valid "
               "data" if tiles else "the aligned common extent is smaller than one tile")
        raise ExtentError(f"{site.path or 'site'}: no tiles of {p.tile_px} px ({size_m:g} m): "
                          f"{why}; set a smaller parameters.tile_px (a multiple of "
                          f"{p.phi}) or keep_partial_tiles = true")
    params = {"tile_px": p.tile_px, "keep_partial_tiles": p.keep_partial_tiles,
              "resampled": "once, from the original flight (bicubic)",
              # named only when not the default, so default tiles keep their tags
              **({"tile_compression": p.tile_compression}
                 if p.tile_compression != "deflate" else {})}
    jobs = [(t, fid) for t, cov in selected for fid in flights if cov[fid] > 0]
    acquired = {f.id: f.acquired for f in site.flights}
    cut = [WarpTileTask(flights[fid], str(run.tile(fid, t.id)), t,
                        {**provenance_tags("tiles", params, list(flight_inputs(flights[fid])),
                                           base_dir=run.root),
                         "GEOSIM_TILE_ID": t.id, "GEOSIM_FLIGHT": fid,
                         **acquisition_tags(acquired[fid])}, BLOCK_PX, p.tile_compression)
           for t, fid in jobs]
    n_skipped = sum(parallel_map(run_resumable, [  # resumable: current tiles are skipped
        ResumableTask(str(run.root), warp_tile_task, c, c.dst_path, flight_inputs(c.flight))
        for c in cut], desc="tiles"))
    outputs: list[Path] = [run.tile(fid, t.id) for t, fid in jobs]
    written = len(outputs)
    records = index_records(selected, _crs_name(grid.crs), p.tile_px,
                            reference=site.reference_flight)
    from shapely.geometry import box

    gdf = gpd.GeoDataFrame(records, geometry=[box(r["minx"], r["miny"], r["maxx"], r["maxy"])
                                              for r in records], crs=grid.crs.to_wkt())
    run.tiles_dir.mkdir(parents=True, exist_ok=True)
    write_geojson(gdf, run.tiles_index_geojson)
    write_gpkg(gdf, run.tiles_index_gpkg, layer="tiles")
    write_json(run.tiles_index_json, {"crs": _crs_name(grid.crs), "tile_px": p.tile_px,
                                      "aligned_transform": ag["transform"],
                                      "tiles": records})
    outputs += [run.tiles_index_geojson, run.tiles_index_gpkg, run.tiles_index_json]
    n_all = len(tiles)
    return StepResult(
        summary=(f"{len(selected)} of {n_all} tile(s) of {p.tile_px} px kept, "
                 f"{written} file(s)" + skip_text(n_skipped, written)),
        outputs=[run.rel(o) for o in outputs],
        record={"tiles": len(selected), "tiles_considered": n_all, "files": written,
                "tile_px": p.tile_px, "skipped_current": n_skipped})


# --------------------------------------------------------------------------- pairs


def run_pairs(site: SiteConfig, out: RunPath) -> StepResult:
    """Write ``pairs.csv``: every unordered flight pair for every tile (paths, not pixels)."""
    run = RunDir.of(out)
    records = json.loads(run.require_tiles_index().read_text())["tiles"]
    acquired = {f.id: f.acquired for f in site.flights}
    rows = pair_rows(records, [f.id for f in site.flights], acquired)
    write_text(run.pairs_csv, pairs_csv_text(rows))
    return StepResult(summary=f"{len(rows)} pair(s) over {len(records)} tile(s)",
                      outputs=[run.rel(run.pairs_csv)],
                      record={"pairs": len(rows), "tiles": len(records)})


__all__ = ["run_grid", "run_footprints", "run_align", "run_tiles", "run_pairs", "read_grid"]
