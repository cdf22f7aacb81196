"""The augmentation step over a run folder: pairs.csv in, augmented training pairs out.

Output folder layout (``OUT``)::

    OUT/images/<aug_id>_a.tif, <aug_id>_b.tif      augmented images (or .png)
    OUT/labels/<aug_id>_a.txt, <aug_id>_b.txt      YOLO labels (same stems: the
                                                    images/ ↔ labels/ layout YOLO trainers expect)
    OUT/meta/<aug_id>.json                          records, transform chains, sources
    OUT/augmented_pairs.csv                         one row per augmented pair (manifest)
    OUT/parameters.csv                              every drawn parameter, one row per pair
    OUT/classes.txt, OUT/augment.json               class names; run summary and configuration
    OUT/data.yaml, OUT/train.txt, OUT/val.txt       YOLO dataset: image lists split by source tile

``aug_id`` is ``<pair_id>_k<index>``. Output ``k`` of a pair uses the generator
``SeedSequence(seed, spawn_key=(crc32(pair_id), k))``: it does not depend on
which other pairs are processed or in which order, and the seed in
``augment.json`` regenerates every output exactly.
"""

from __future__ import annotations

import json
import os
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geosim.augment.geometry import Boxes
from geosim.augment.io import (
    TIFF_COMPRESSION,
    PairRow,
    Tile,
    read_pairs,
    read_tile,
    read_yolo,
    tile_and_label_paths,
    write_csv,
    write_image,
    write_yolo,
)
from geosim.augment.pipeline import AugImage, AugmentResult, Pipeline, flatten_records
from geosim.engine import parallel_map
from geosim.errors import OutputError, RasterError
from geosim.heap import keep_large_arrays
from geosim.io.atomic import json_default, write_json, write_text
from geosim.io.paths import safe_name
from geosim.io.raster import provenance_tags
from geosim.rundir import RunDir

__all__ = ["MANIFEST_COLUMNS", "output_rng", "run_augment"]

MANIFEST_COLUMNS = ("aug_id", "pair_id", "tile_id", "flight_a", "flight_b", "index",
                    "path_a", "path_b", "labels_a", "labels_b", "meta", "boxes_a", "boxes_b",
                    "dropped_a", "dropped_b", "on_map_grid_a", "on_map_grid_b",
                    "source_a", "source_b")

OFF_GRID_NOTE = ("geometric augmentation applied: these pixels are no longer on the map grid, "
                 "so no geotransform or CRS is written; GEOSIM_SOURCE_TILE, "
                 "GEOSIM_SOURCE_TRANSFORM and GEOSIM_TRANSFORM_CHAIN say where they came from")


def output_rng(seed: int, pair_id: str, index: int) -> np.random.Generator:
    """The generator of output ``index`` of pair ``pair_id`` for a run ``seed``."""
    key = zlib.crc32(pair_id.encode("utf-8"))
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(key, index)))




def _load(run_dir: Path, row: PairRow, resolution: str) -> tuple[Tile, Tile, list[bool]]:
    img_a, img_b, lab_a, lab_b = tile_and_label_paths(run_dir, row, resolution)
    tiles = []
    found = []
    for img, lab, flight in ((img_a, lab_a, row.flight_a), (img_b, lab_b, row.flight_b)):
        tile = read_tile(img, what=f"pair {row.pair_id} flight {flight} tile")
        boxes = read_yolo(lab, tile.data.shape)
        found.append(boxes is not None)
        data = AugImage(tile.data.image, tile.data.mask, boxes or Boxes.empty())
        tiles.append(Tile(tile.path, data, tile.georef, tile.band_descriptions))
    a, b = tiles
    if a.data.shape != b.data.shape:
        raise RasterError(f"pair {row.pair_id}: {a.path} is {a.data.shape} px but {b.path} is "
                          f"{b.data.shape} px; the tiles of a pair must cover the same pixels "
                          "(re-run the tiles step)")
    return a, b, found


@dataclass(frozen=True)
class AugmentPairTask:
    """One pair to augment ``n`` times (picklable: sent to a worker)."""

    run_dir: Path
    out: Path
    row: PairRow
    pipeline: Pipeline
    n: int
    seed: int
    resolution: str
    fmt: str
    compress: str = "deflate"


@dataclass(frozen=True)
class AugmentPairDone:
    """What one pair's task reports back: manifest and parameter rows, counts."""

    manifest_rows: list[dict[str, Any]]
    params_rows: list[dict[str, Any]]
    counts: dict[str, int]


def augment_pair_task(task: AugmentPairTask) -> AugmentPairDone:
    """Augment one pair ``n`` times and write its images, labels and metadata."""
    keep_large_arrays()  # large arrays reused from one output to the next (geosim/heap.py)
    row, pipeline, seed = task.row, task.pipeline, task.seed
    tile_a, tile_b, found = _load(task.run_dir, row, task.resolution)
    counts = {"boxes_in": 0, "boxes_out": 0, "boxes_dropped": 0,
              "missing_label_files": found.count(False), "off_grid_images": 0}
    gsd = tile_a.georef.gsd_m if tile_a.georef is not None else None
    scale = pipeline.length_scale(gsd)
    manifest: list[dict[str, Any]] = []
    params_rows: list[dict[str, Any]] = []
    for k in range(task.n):
        aug_id = f"{safe_name(row.pair_id)}_k{k:03d}"
        res = pipeline.apply(tile_a.data, tile_b.data, output_rng(seed, row.pair_id, k),
                             length_scale=scale)
        manifest.append(_write_outputs(task.out, aug_id, row, k, res, (tile_a, tile_b),
                                       task.run_dir, fmt=task.fmt, compress=task.compress,
                                       seed=seed,
                                       pipeline=pipeline, length_scale=scale))
        params_rows.append({"aug_id": aug_id, "pair_id": row.pair_id, "index": k,
                            "seed": seed, "length_scale": scale,
                            **flatten_records(res.records)})
        counts["boxes_in"] += len(tile_a.data.boxes) + len(tile_b.data.boxes)
        counts["boxes_out"] += len(res.a.boxes) + len(res.b.boxes)
        counts["boxes_dropped"] += res.dropped_a + res.dropped_b
        counts["off_grid_images"] += res.on_map_grid.count(False)
    return AugmentPairDone(manifest, params_rows, counts)


def _plain(obj: Any) -> Any:
    """:func:`~geosim.io.atomic.json_default`, but a float32 keeps its short text (as the
    CSV writer printed it before the JSON round trip of the resume entries)."""
    if isinstance(obj, np.floating) and not isinstance(obj, np.float64):
        return float(str(obj))
    return json_default(obj)


def _pair_key(task: AugmentPairTask) -> tuple[str, list[Path], dict[str, Any]]:
    """Manifest key, input files and parameters of one pair's outputs."""
    import dataclasses

    inputs = [p for p in tile_and_label_paths(task.run_dir, task.row, task.resolution)
              if p.is_file()]
    params = {"step": "augment", "pipeline": task.pipeline.to_dict(), "n": task.n,
              "seed": task.seed, "resolution": task.resolution, "fmt": task.fmt,
              "compress": task.compress,
              "row": dataclasses.asdict(task.row), "run_dir": str(Path(task.run_dir).resolve())}
    return f"pairs/{safe_name(task.row.pair_id)}", inputs, params


def _row_files(out: Path, rows: list[dict[str, Any]]) -> list[Path]:
    return [out / str(r[k]) for r in rows for k in ("path_a", "path_b", "labels_a",
                                                     "labels_b", "meta")]


@dataclass(frozen=True)
class ResumedPair:
    """A pair's outputs and whether they were reused (current in the manifest)."""

    done: AugmentPairDone
    skipped: bool


def resumable_pair_task(task: AugmentPairTask) -> ResumedPair:
    """:func:`augment_pair_task`, skipped when the pair's outputs are current.

    The entry (in ``OUT/.geosim/manifest/pairs/``) records the pair's tiles and label
    files, the pipeline, ``n``, seed, resolution and format, and the files written; the
    rows and counts are kept in it, so a skipped pair reports the same as a fresh one.
    """
    from geosim import manifest

    key, inputs, params = _pair_key(task)
    entry = manifest.cached(task.out, key, inputs, params,
                            outputs=_recorded(task.out, key))
    if entry is not None and isinstance(entry.get("result"), dict):
        r = entry["result"]
        return ResumedPair(AugmentPairDone(r["manifest_rows"], r["params_rows"], r["counts"]),
                           skipped=True)
    done = augment_pair_task(task)
    result = json.loads(json.dumps({"manifest_rows": done.manifest_rows,
                                    "params_rows": done.params_rows,
                                    "counts": done.counts}, default=_plain))
    manifest.record(task.out, key, inputs, params,
                    outputs=_row_files(task.out, result["manifest_rows"]), result=result)
    return ResumedPair(AugmentPairDone(result["manifest_rows"], result["params_rows"],
                                       result["counts"]), skipped=False)


def _recorded(out: Path, key: str) -> list[Path]:
    from geosim import manifest

    try:
        entry = json.loads((out / manifest.MANIFEST_DIR / f"{key}.json").read_text())
        return [out / rel for rel in entry["outputs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def _remove_unlisted(out: Path, rows: list[dict[str, Any]], *, overwrite: bool) -> int:
    """Remove earlier outputs this run did not write or reuse; returns how many.

    With ``overwrite``: every file in images/, labels/ and meta/ (what ``--overwrite``
    replaces). Without: only files an earlier (interrupted) run recorded in the manifest.
    """
    from geosim import manifest

    keep = {p.resolve() for p in _row_files(out, rows)}
    if overwrite:
        candidates = [p for sub in ("images", "labels", "meta") if (out / sub).is_dir()
                      for p in (out / sub).rglob("*")]
    else:
        candidates = [p for e in sorted((out / manifest.MANIFEST_DIR / "pairs").glob("*.json"))
                      for p in _recorded(out, f"pairs/{e.stem}")]
    removed = 0
    for p in sorted(set(candidates)):
        if p.is_file() and p.resolve() not in keep:
            p.unlink()
            removed += 1
    return removed


def check_augment_out(out: Path, overwrite: bool) -> None:
    """Refuse an --out folder holding augmented pairs unless ``overwrite`` (OutputError)."""
    manifest_path = out / "augmented_pairs.csv"
    if manifest_path.exists() and not overwrite:
        raise OutputError(f"{out} already holds augmented pairs ({manifest_path.name}); choose "
                          "another --out folder or pass --overwrite")


def run_augment(pairs_csv: str | os.PathLike[str], pipeline: Pipeline, *, n: int,
                out_dir: str | os.PathLike[str], seed: int | None = None,
                resolution: str = "uav", fmt: str = "tif", compress: str = "deflate",
                overwrite: bool = False) -> dict[str, Any]:
    """Augment every pair of a run folder ``n`` times.

    Parameters
    ----------
    pairs_csv
        ``DIR/pairs.csv`` of a run folder; tiles and labels are found beside it.
    pipeline
        The augmentation pipeline.
    n
        Augmented outputs per pair.
    out_dir
        Output folder (layout in the module docstring).
    seed
        Run seed; ``None`` draws one from the OS and records it in ``augment.json``.
    resolution
        ``"uav"`` (tiles/, labels/yolo/) or ``"0.5m"`` (degraded/, labels/yolo_0.5m/).
    fmt
        ``"tif"`` (tiled GeoTIFF with internal mask, default) or ``"png"`` (8/16-bit RGB
        with the mask as alpha).
    compress
        GeoTIFF compression: ``"deflate"`` (level 1 + predictor, lossless, default) or
        ``"none"`` (no encoding: fastest to write and to load, about twice the disk).
    overwrite
        Replace the outputs of an earlier run in ``out_dir``.

    Returns
    -------
    dict
        Summary (counts, timings, paths), also written to ``augment.json``.
    """
    if n < 1:
        raise ValueError("n must be >= 1")
    if fmt not in ("tif", "png"):
        raise ValueError("fmt must be 'tif' or 'png'")
    if compress not in TIFF_COMPRESSION:
        raise ValueError(f"compress must be one of {', '.join(TIFF_COMPRESSION)}")
    pairs_csv = Path(pairs_csv)
    run_dir = pairs_csv.parent
    out = Path(out_dir)
    manifest_path = out / "augmented_pairs.csv"
    check_augment_out(out, overwrite)
    rows = read_pairs(pairs_csv)
    if seed is None:
        seed = int(np.random.SeedSequence().entropy % (2**63))
    manifest: list[dict[str, Any]] = []
    params_rows: list[dict[str, Any]] = []
    counts = {"boxes_in": 0, "boxes_out": 0, "boxes_dropped": 0, "missing_label_files": 0,
              "off_grid_images": 0}
    t0 = time.perf_counter()
    tasks = [AugmentPairTask(run_dir, out, row, pipeline, n=n, seed=seed,
                             resolution=resolution, fmt=fmt, compress=compress) for row in rows]
    n_skipped = reused_rows = 0
    for resumed in parallel_map(resumable_pair_task, tasks, desc="augment pairs"):
        done = resumed.done
        n_skipped += resumed.skipped
        reused_rows += len(done.manifest_rows) if resumed.skipped else 0
        manifest.extend(done.manifest_rows)
        params_rows.extend(done.params_rows)
        for key, value in done.counts.items():
            counts[key] += value
    seconds = time.perf_counter() - t0
    # earlier outputs this run did not make (an interrupted run's, or --overwrite's)
    _remove_unlisted(out, manifest, overwrite=overwrite)
    columns = ["aug_id", "pair_id", "index", "seed", "length_scale",
               *pipeline.record_columns()]
    params_path = write_csv(out / "parameters.csv", columns, params_rows)
    classes_src = RunDir.of(run_dir).classes_txt
    classes = classes_src.read_text() if classes_src.is_file() else "cattle\n"
    write_text(out / "classes.txt", classes)
    split = _write_split(out, manifest, classes, seed=seed)
    summary: dict[str, Any] = {
        "pairs": len(rows), "outputs_per_pair": n, "augmented_pairs": len(manifest),
        "seed": seed, "resolution": resolution, "format": fmt,
        "compress": compress if fmt == "tif" else None, **counts,
        "seconds": round(seconds, 3),
        "pairs_per_second": (round((len(manifest) - reused_rows) / seconds, 3)
                             if seconds > 0 else None),
        "out_dir": str(out), "manifest": str(manifest_path), "parameters": str(params_path),
        "split": split, "skipped_current": n_skipped,
    }
    write_json(out / "augment.json", {**summary, "pairs_csv": str(pairs_csv),
                                      "config": pipeline.to_dict()})
    # The manifest is written last: its presence marks a complete run.
    write_csv(manifest_path, MANIFEST_COLUMNS, manifest)
    return summary


def _write_split(out: Path, manifest: list[dict[str, Any]], classes: str, *, seed: int
                 ) -> dict[str, int]:
    """data.yaml + train.txt/val.txt, split by source tile (both images of a pair, all k)."""
    from geosim.deliver.yolo_dataset import write_split_lists

    by_tile: dict[str, list[str]] = {}
    for m in manifest:
        by_tile.setdefault(str(m["tile_id"]), []).extend([m["path_a"], m["path_b"]])
    names = [n.strip() for n in classes.splitlines() if n.strip()]
    return write_split_lists(out, by_tile, names, val_fraction=0.2, seed=seed,
                             note="geosim augment: split by source tile (val_fraction=0.2)")


def _write_outputs(out: Path, aug_id: str, row: PairRow, k: int, res: AugmentResult,
                   tiles: tuple[Tile, Tile], run_dir: Path, *, fmt: str, compress: str,
                   seed: int,
                   pipeline: Pipeline, length_scale: float) -> dict[str, Any]:
    mrow: dict[str, Any] = {"aug_id": aug_id, "pair_id": row.pair_id, "tile_id": row.tile_id,
                            "flight_a": row.flight_a, "flight_b": row.flight_b, "index": k}
    meta: dict[str, Any] = {"aug_id": aug_id, "pair_id": row.pair_id, "tile_id": row.tile_id,
                            "index": k, "seed": seed, "length_scale": length_scale,
                            "records": res.records, "images": {}}
    for side, img, chain, tile, dropped, on_grid, flight in (
            ("a", res.a, res.chain_a, tiles[0], res.dropped_a, res.on_map_grid[0], row.flight_a),
            ("b", res.b, res.chain_b, tiles[1], res.dropped_b, res.on_map_grid[1], row.flight_b)):
        rel_img = Path("images") / f"{aug_id}_{side}.{fmt}"
        rel_lab = Path("labels") / f"{aug_id}_{side}.txt"
        source = os.path.relpath(tile.path, run_dir)
        p2s = AugmentResult.pixel_to_source(chain)
        geo = tile.georef
        info: dict[str, Any] = {
            "flight": flight, "source_tile": source, "on_map_grid": on_grid,
            "source_crs": geo.crs.to_string() if geo else None,
            "source_transform": list(geo.transform)[:6] if geo else None,
            "transform_chain": chain,
            "pixel_to_source_pixel": p2s[:2].tolist() if p2s is not None else None,
            "boxes": len(img.boxes), "dropped_boxes": dropped,
        }
        tags = provenance_tags("augment", {"aug_id": aug_id, "image": side, "seed": seed,
                                           "records": res.records}, [source])
        tags.update({
            "GEOSIM_ON_MAP_GRID": "true" if on_grid else "false",
            "GEOSIM_SOURCE_TILE": source,
            "GEOSIM_SOURCE_CRS": info["source_crs"] or "",
            "GEOSIM_SOURCE_TRANSFORM": json.dumps(info["source_transform"]),
            "GEOSIM_TRANSFORM_CHAIN": json.dumps(chain),
            "GEOSIM_PIXEL_TO_SOURCE_PIXEL": json.dumps(info["pixel_to_source_pixel"]),
        })
        if not on_grid:
            tags["GEOSIM_NOTE"] = OFF_GRID_NOTE
        write_image(out / rel_img, img, georef=geo if on_grid else None, tags=tags,
                    band_descriptions=tile.band_descriptions, compress=compress)
        write_yolo(out / rel_lab, img.boxes, img.shape)
        meta["images"][side] = info
        mrow.update({f"path_{side}": rel_img.as_posix(), f"labels_{side}": rel_lab.as_posix(),
                     f"boxes_{side}": len(img.boxes), f"dropped_{side}": dropped,
                     f"on_map_grid_{side}": on_grid, f"source_{side}": source})
    rel_meta = Path("meta") / f"{aug_id}.json"
    write_json(out / rel_meta, meta)
    mrow["meta"] = rel_meta.as_posix()
    return mrow
