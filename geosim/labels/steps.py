"""The labels pipeline step: ``run_labels(site, out) -> StepResult``.

Reads every labelled flight's labels (in the flight's stated frame), moves them
into the aligned frame with the alignment step's correction, merges duplicates,
and writes ``labels/`` in the run folder::

    cattle.geojson            RFC 7946 (lon/lat), one box polygon per cow
    cattle.gpkg               site CRS; layers ``cattle`` (boxes) and ``cattle_centres`` (points)
    classes.txt               ``cattle`` (class 0)
    yolo/<flight>/<tile>.txt      boxes on each UAV tile (empty file: no cattle there)
    yolo_0.5m/<flight>/<tile>.txt boxes on each 0.5 m tile (same ground, phi x the pixel)

Every feature carries ``cattle_id``, ``flight``, ``acquired``, ``class_name``,
``source_file``, ``source_line``, ``source_kind``, ``width_m``, ``height_m``,
``centre_x``/``centre_y`` (site CRS, m), ``centre_lon``/``centre_lat``
(WGS 84), ``below_sat_pixel`` (a side shorter than one satellite pixel),
``n_merged``/``merged_from`` (duplicates merged into it) and ``tile_ids``
(UAV tiles where its box was written). YOLO files are written only for flights
that have labels: an empty file claims "no cattle here", which an unlabelled
flight cannot.

All labels are read and validated before anything is written, and the whole
folder is built under a temporary name and put in place by
:func:`geosim.io.publish.publish_folder`, so a bad label file or a crash leaves the
previous ``labels/`` (or none) untouched, and files in ``labels/`` that geosim did not
write are never deleted.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import geopandas as gpd
import numpy as np
import rasterio
import shapely
from affine import Affine
from pyproj import CRS, Transformer

from geosim import manifest
from geosim.config import SiteConfig
from geosim.engine import parallel_map
from geosim.errors import AlignmentError, InputFileError
from geosim.io.georef import Georef
from geosim.io.publish import publish_folder
from geosim.io.vector import write_geojson, write_gpkg
from geosim.labels.dedupe import DEFAULT_IOU, dedupe_labels
from geosim.labels.georef import affine_linear_scale, transform_geometries
from geosim.labels.sources import read_site_labels
from geosim.labels.tiles import sat_tile_geometry, tile_boxes
from geosim.labels.yolo import CLASS_NAMES, format_yolo
from geosim.result import StepResult
from geosim.rundir import TILE_ID, YOLO_SUBDIRS, RunDir, RunPath

# ----------------------------------------------------------------------- inputs


def read_grid(run: RunDir) -> Any | None:
    """The shared grid (``grid/grid.json``) as a ``SiteGrid``, or None if absent."""
    if not run.grid_json.is_file():
        return None
    from geosim.prepare.steps import read_grid as read_site_grid

    return read_site_grid(run)


def find_tiles(run: RunDir, flight_ids: list[str]) -> dict[str, list[Georef]]:
    """UAV tiles of each flight, from ``tiles/<flight>/<tile_id>.tif`` headers.

    Raises
    ------
    InputFileError
        If ``tiles/`` does not exist (the tile step has not run).
    """
    run.require(run.tiles_dir, "tile", is_dir=True,
                what="(the labels step writes YOLO files for the tiles)")
    found: dict[str, list[Georef]] = {}
    for fid in flight_ids:
        tiles = []
        for path in run.tile_files(fid):
            with rasterio.open(path) as ds:
                tiles.append(Georef.of_dataset(ds, path=path, name=path.stem))
        found[fid] = tiles
    return found


def load_corrections(run: RunDir, flight_ids: list[str], grid: Any,
                     ) -> dict[str, Affine]:
    """Per-flight affine from stated to aligned map coordinates (``alignment.json``).

    Uses :func:`geosim.prepare.alignment.correction_affine` on each flight's entry.

    Raises
    ------
    AlignmentError
        If ``alignment.json`` is missing or has no entry for a labelled flight.
    """
    path = run.alignment_json
    if not path.is_file():
        raise AlignmentError(f"{run.rel(path)} not found in {run.root}: labels are moved into "
                             "the aligned frame with the alignment correction; run "
                             "'geosim align' first")
    from geosim.prepare.alignment import correction_affine

    doc = json.loads(path.read_text())
    entries = doc.get("flights", doc) if isinstance(doc, dict) else {}
    out: dict[str, Affine] = {}
    for fid in flight_ids:
        entry = entries.get(fid) if isinstance(entries, dict) else None
        if not isinstance(entry, dict):
            raise AlignmentError(f"{path}: no entry for flight {fid}; re-run 'geosim align'")
        out[fid] = correction_affine(entry, grid)
    return out


# --------------------------------------------------------------------- building


def apply_corrections(labels: gpd.GeoDataFrame, corrections: Mapping[str, Affine],
                      ) -> gpd.GeoDataFrame:
    """Move each flight's label geometries by its correction affine (site CRS, m).

    Box sides are scaled by the affine's linear scale (``sqrt(|det|)``); the
    correction is a similarity transform (rotation, scale, shift).
    """
    out = labels.copy()
    geoms = np.asarray(out.geometry.values, dtype=object).copy()
    width = out["width_m"].to_numpy(dtype=float).copy()
    height = out["height_m"].to_numpy(dtype=float).copy()
    for fid, pos in out.groupby("flight", sort=False).indices.items():
        if fid not in corrections:
            raise AlignmentError(f"no alignment correction for flight {fid}; re-run "
                                 "'geosim align'")
        a = corrections[fid]
        geoms[pos] = transform_geometries(geoms[pos], a)
        s = affine_linear_scale(a)
        width[pos] *= s
        height[pos] *= s
    out = out.set_geometry(gpd.GeoSeries(list(geoms), crs=out.crs, index=out.index))
    out["width_m"] = width
    out["height_m"] = height
    return out


def apply_local_fields(labels: gpd.GeoDataFrame, out_dir: Path) -> gpd.GeoDataFrame:
    """Move labels with each flight's local alignment field (``align_model = "local"``).

    A label is translated so that its centre moves as the field moves that ground
    (:func:`geosim.prepare.local_align.move_points`); flights without a field are unchanged.
    """
    from geosim.prepare.local_align import label_moves

    return label_moves(labels, out_dir)


def add_feature_attributes(cattle: gpd.GeoDataFrame, *, sat_gsd_m: float,
                           ) -> gpd.GeoDataFrame:
    """Add ``cattle_id``, centre coordinates (site CRS and WGS 84) and ``below_sat_pixel``.

    Sizes and site-CRS centres are rounded to 1 µm and lon/lat to 1e-9 degree
    (0.1 mm): attribute values for people, not geometry (which keeps float64).
    """
    out = cattle.copy()
    ids: list[str] = []
    counter: dict[str, int] = {}
    for f in out["flight"]:
        counter[f] = counter.get(f, 0) + 1
        ids.append(f"{f}-{counter[f]:04d}")
    out.insert(0, "cattle_id", ids)
    centres = shapely.get_coordinates(shapely.centroid(np.asarray(out.geometry.values)))
    centres = centres.reshape(-1, 2)
    out["width_m"] = np.round(out["width_m"].to_numpy(dtype=float), 6)
    out["height_m"] = np.round(out["height_m"].to_numpy(dtype=float), 6)
    out["centre_x"] = np.round(centres[:, 0], 6)
    out["centre_y"] = np.round(centres[:, 1], 6)
    if len(out):
        lon, lat = Transformer.from_crs(out.crs, "EPSG:4326", always_xy=True).transform(
            centres[:, 0], centres[:, 1])
    else:
        lon = lat = np.zeros(0)
    out["centre_lon"] = np.round(lon, 9)
    out["centre_lat"] = np.round(lat, 9)
    out["below_sat_pixel"] = (out["width_m"] < sat_gsd_m) | (out["height_m"] < sat_gsd_m)
    return out


@dataclass
class TileLabels:
    """YOLO texts of one flight's tiles and what went into them."""

    uav: dict[str, str]
    sat: dict[str, str]
    tile_ids_per_feature: dict[int, list[str]]
    stats: dict[str, int]


def build_tile_labels(cattle: gpd.GeoDataFrame, tiles: list[Georef], *, phi: int,
                      min_visible_fraction: float,
                      progress: Callable[[], None] | None = None) -> TileLabels:
    """YOLO texts for one flight's UAV tiles and their 0.5 m counterparts.

    Parameters
    ----------
    cattle
        This flight's cattle polygons in the aligned frame, site CRS.
    tiles
        The flight's UAV tiles.
    phi
        Satellite pixel size in UAV pixels.
    min_visible_fraction
        Drop a box whose visible area on a tile is below this fraction.
    """
    geoms = np.asarray(cattle.geometry.values, dtype=object)
    class_ids = np.array([CLASS_NAMES.index(c) for c in cattle["class_name"]], dtype=np.int64)
    tree = shapely.STRtree(geoms) if geoms.size else None
    uav: dict[str, str] = {}
    sat: dict[str, str] = {}
    per_feature: dict[int, list[str]] = {}
    stats = {"tiles": 0, "empty_tiles": 0, "boxes_uav": 0, "boxes_0.5m": 0, "clipped": 0,
             "dropped_below_visible_fraction": 0}
    for tile in tiles:
        cand = (np.sort(tree.query(tile.outline, predicate="intersects")) if tree is not None
                else np.zeros(0, dtype=np.int64))
        hit = tile_boxes(geoms[cand], tile.transform, tile.width_px, tile.height_px,
                         min_visible_fraction=min_visible_fraction)
        sat_transform, sat_w, sat_h = sat_tile_geometry(tile.transform, tile.width_px,
                                                        tile.height_px, phi)
        hit_sat = tile_boxes(geoms[cand], sat_transform, sat_w, sat_h,
                             min_visible_fraction=min_visible_fraction)
        uav[tile.name] = format_yolo(class_ids[cand[hit.index]], hit.boxes)
        sat[tile.name] = format_yolo(class_ids[cand[hit_sat.index]], hit_sat.boxes)
        for k in cand[hit.index]:
            per_feature.setdefault(int(k), []).append(tile.name)
        stats["tiles"] += 1
        stats["empty_tiles"] += int(len(hit) == 0)
        stats["boxes_uav"] += len(hit)
        stats["boxes_0.5m"] += len(hit_sat)
        stats["clipped"] += int(hit.clipped.sum())
        stats["dropped_below_visible_fraction"] += int(hit.dropped.size)
        if progress is not None:
            progress()
    return TileLabels(uav, sat, per_feature, stats)


@dataclass(frozen=True)
class FlightLabelsTask:
    """One flight's cattle and tiles (picklable: sent to a worker)."""

    cattle: gpd.GeoDataFrame
    tiles: list[Georef]
    phi: int
    min_visible_fraction: float


def flight_labels_task(task: FlightLabelsTask) -> TileLabels:
    """:func:`build_tile_labels` of one flight, as an engine task."""
    return build_tile_labels(task.cattle, task.tiles, phi=task.phi,
                             min_visible_fraction=task.min_visible_fraction)


# ---------------------------------------------------------------------- writing


_OWN_TOP = {"cattle.geojson", "cattle.gpkg", "classes.txt"}


def _legacy_own(rel: str) -> bool:
    """Whether ``rel`` (POSIX, inside labels/) is a file this step writes (by its name)."""
    parts = rel.split("/")
    if len(parts) == 1:
        return rel in _OWN_TOP
    return (len(parts) == 3 and parts[0] in YOLO_SUBDIRS.values() and rel.endswith(".txt")
            and TILE_ID.match(parts[2][:-4]) is not None)


@contextlib.contextmanager
def _staging(final: Path):
    final.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{final.name}.partial-", dir=final.parent))
    stage.chmod(0o755)  # mkdtemp makes it private; the outputs are for everyone to read
    try:
        yield stage
        publish_folder(stage, final, legacy_own=_legacy_own)
    finally:
        if stage.exists():
            shutil.rmtree(stage, ignore_errors=True)


def _centres_layer(cattle: gpd.GeoDataFrame) -> gpd.GeoDataFrame:
    points = shapely.points(cattle[["centre_x", "centre_y"]].to_numpy())
    return gpd.GeoDataFrame(cattle.drop(columns="geometry"), geometry=points, crs=cattle.crs)


def run_labels(site: SiteConfig, out: RunPath, *,
               corrections: Mapping[str, Affine] | None = None,
               iou_threshold: float = DEFAULT_IOU) -> StepResult:
    """Fill ``out_dir/labels/`` from the site's labels (see the module docstring).

    Parameters
    ----------
    site
        The site; flights with ``labels`` are processed.
    out
        The run folder; needs ``grid/grid.json``, ``tiles/`` and ``alignment.json``.
    corrections
        Stated -> aligned affine per flight (site CRS, metres); default: from
        ``alignment.json`` through the alignment step's ``correction_affine``.
    iou_threshold
        IoU at which two labels of one flight are the same cow.

    Returns
    -------
    StepResult
        Outputs written, per-flight counts (record ``flights``), ``cattle``.
    """
    run = RunDir.of(out)
    labelled = [f.id for f in site.flights if f.labels is not None]
    if not labelled:
        return StepResult(summary="no flight has labels in the site file; nothing written",
                          record={"cattle": 0, "flights": {}})
    grid = read_grid(run)
    tiles = find_tiles(run, labelled)
    inputs, key_params = _resume_key(site, run, labelled, tiles, corrections, iou_threshold)
    entry = manifest.cached(run.root, LABELS_KEY, inputs, key_params,
                            outputs=_recorded_outputs(run))
    if entry is not None and isinstance(entry.get("result"), dict):
        done = entry["result"]
        return StepResult(summary=done["summary"] + "; already current, skipped",
                          outputs=list(done["outputs"]),
                          record={**done["record"], "skipped_current": 1})
    result = _build_labels(site, run, labelled, grid, tiles, corrections, iou_threshold)
    manifest.record(run.root, LABELS_KEY, inputs, key_params,
                    outputs=[run.root / rel for rel in result.outputs],
                    result=json.loads(json.dumps({"summary": result.summary,
                                                  "outputs": list(result.outputs),
                                                  "record": result.record}, default=str)))
    return dataclasses.replace(result, record={**result.record, "skipped_current": 0})


#: Manifest key of the labels step (one entry: the folder is written all-or-nothing).
LABELS_KEY = "labels/step"


def _recorded_outputs(run: RunDir) -> list[Path]:
    """The files the last labels run recorded (their stats must be unchanged to skip)."""
    try:
        entry = json.loads((run.root / manifest.MANIFEST_DIR / f"{LABELS_KEY}.json").read_text())
        return [run.root / rel for rel in entry["result"]["outputs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _resume_key(site: SiteConfig, run: RunDir, labelled: list[str],
                tiles: Mapping[str, list[Georef]], corrections: Mapping[str, Affine] | None,
                iou_threshold: float) -> tuple[list[Path], dict[str, Any]]:
    """What the labels are made from: input files and the parameters (for the manifest).

    Tiles enter by their georeference (name, transform, size: what the YOLO boxes depend
    on), not their pixels, so re-cut tiles with the same grid do not invalidate labels.
    """
    inputs = [p for p in (run.alignment_json, run.grid_json) if p.is_file()]
    for fid in labelled:
        src = site.flight(fid).labels
        if src is not None and src.is_dir():
            inputs += sorted(p for p in src.iterdir() if p.is_file())
        elif src is not None:
            inputs.append(src)
        field = run.alignment_field(fid)
        if field.is_file():
            inputs.append(field)
    p = site.parameters
    key_params = {
        "step": "labels", "phi": p.phi, "sat_gsd_m": p.sat_gsd_m,
        "min_visible_fraction": p.min_visible_fraction, "iou_threshold": iou_threshold,
        "flights": {fid: str(site.flight(fid).acquired) for fid in labelled},
        "tiles": {fid: [[g.name, list(g.transform)[:6], g.width_px, g.height_px] for g in tl]
                  for fid, tl in tiles.items()},
        "corrections": None if corrections is None else
        {k: list(v)[:6] for k, v in sorted(corrections.items())},
    }
    return inputs, key_params


def _build_labels(site: SiteConfig, run: RunDir, labelled: list[str], grid: Any | None,
                  tiles: dict[str, list[Georef]], corrections: Mapping[str, Affine] | None,
                  iou_threshold: float) -> StepResult:
    """Build and write ``labels/`` (the work of :func:`run_labels` when not current)."""
    params = site.parameters
    crs = _site_crs(grid, tiles, run)
    base_dir = site.path.parent if site.path is not None else None
    final = run.labels_dir

    # Read and validate everything before writing anything.
    stated = read_site_labels([site.flight(f) for f in labelled], crs, base_dir=base_dir)
    if corrections is None:
        corrections = load_corrections(run, labelled, grid)
    aligned = apply_corrections(stated, corrections)
    aligned = apply_local_fields(aligned, run.root)  # align_model = "local" only
    cattle = dedupe_labels(aligned, iou_threshold=iou_threshold)
    cattle = add_feature_attributes(cattle, sat_gsd_m=params.sat_gsd_m)

    per_flight: dict[str, dict[str, Any]] = {}
    # paths relative to labels/ (built in a staging folder, then swapped in)
    texts: dict[Path, str] = {run.classes_txt.relative_to(final):
                              "".join(f"{c}\n" for c in CLASS_NAMES)}
    uav_dir, sat_dir = (run.yolo_dir(r).relative_to(final) for r in ("uav", "0.5m"))
    tile_ids = [""] * len(cattle)
    positions = {fid: np.flatnonzero((cattle["flight"] == fid).to_numpy()) for fid in labelled}
    tasks = [FlightLabelsTask(cattle.iloc[positions[fid]], tiles[fid], params.phi,
                              params.min_visible_fraction) for fid in labelled]
    for fid, built in zip(labelled, parallel_map(flight_labels_task, tasks,
                                                 desc="labels per flight"), strict=True):
        pos = positions[fid]
        for tid, text in built.uav.items():
            texts[uav_dir / fid / f"{tid}.txt"] = text
        for tid, text in built.sat.items():
            texts[sat_dir / fid / f"{tid}.txt"] = text
        for k, ids in built.tile_ids_per_feature.items():
            tile_ids[pos[k]] = ";".join(ids)
        n_read = int((stated["flight"] == fid).sum())
        per_flight[fid] = {
            "labels_read": n_read,
            "cattle": int(pos.size),
            "duplicates_merged": n_read - int(pos.size),
            "below_sat_pixel": int(cattle["below_sat_pixel"].iloc[pos].sum()),
            **built.stats,
        }
    cattle["tile_ids"] = tile_ids

    with _staging(final) as stage:
        for rel, text in texts.items():
            (stage / rel).parent.mkdir(parents=True, exist_ok=True)
            (stage / rel).write_text(text)
        write_geojson(cattle, stage / "cattle.geojson")
        write_gpkg(cattle, stage / "cattle.gpkg", layer="cattle")
        write_gpkg(_centres_layer(cattle), stage / "cattle.gpkg", layer="cattle_centres",
                   append=True)

    total = len(cattle)
    n_yolo = sum(1 for rel in texts if rel.parts[0] == uav_dir.name)
    written = [final / rel for rel in texts] + [final / "cattle.geojson", final / "cattle.gpkg"]
    return StepResult(
        summary=(f"{total} cattle in {len(labelled)} labelled flight(s), "
                 f"{n_yolo} tile label files per resolution -> {final}"),
        outputs=sorted(run.rel(p) for p in written),
        record={"crs": crs.to_string(), "cattle": total, "yolo_files_per_resolution": n_yolo,
                "flights": per_flight})


def _site_crs(grid: Any | None, tiles: Mapping[str, list[Georef]], run: RunDir) -> CRS:
    if grid is not None:
        return CRS.from_user_input(grid.crs.to_wkt())
    for tl in tiles.values():
        if tl:
            return tl[0].crs
    raise InputFileError(f"{run.root}: neither {run.rel(run.grid_json)} nor any tile says "
                         "which CRS the site uses; run 'geosim grid' and 'geosim tile' first")
