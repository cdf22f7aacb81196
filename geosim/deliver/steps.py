"""The ``deliver`` step: VRT mosaics, STAC catalogue, YOLO datasets and a QGIS project.

Reads the outputs of the earlier steps (whatever of them exists: a run without a
satellite scene or without labels still gets mosaics and a catalogue) and writes::

    DIR/tiles/<flight>.vrt, DIR/degraded/<flight>.vrt     mosaics (relative paths)
    DIR/stac/catalog.json                                 catalogue -> collection -> items
    DIR/yolo/, DIR/yolo_0.5m/                             YOLO datasets split by tile
    DIR/geosim.qgs                                        QGIS project (relative paths)
"""

from __future__ import annotations

import logging
from pathlib import Path

from geosim.config import SiteConfig
from geosim.deliver.stac import COG_TYPE, RasterItem, write_stac
from geosim.deliver.vrt import write_mosaic_vrt
from geosim.deliver.yolo_dataset import write_yolo_dataset
from geosim.result import StepResult
from geosim.rundir import YOLO_SUBDIRS, RunDir, RunPath

log = logging.getLogger(__name__)

#: Defaults of the spatial train/val split of the YOLO datasets.
VAL_FRACTION = 0.2
SPLIT_SEED = 0


def _flight_tiles(run: RunDir, resolution: str, flight: str) -> list[Path]:
    """The flight's tiles at ``resolution`` (``"uav"``: tiles/, ``"0.5m"``: degraded/)."""
    return run.tile_files(flight) if resolution == "uav" else run.degraded_files(flight)


def write_mosaics(site: SiteConfig, run: RunDir) -> dict[str, list[str]]:
    """One VRT per flight for tiles/ and degraded/ (where that step ran)."""
    written: dict[str, list[str]] = {}
    for resolution, folder in (("uav", run.tiles_dir), ("0.5m", run.degraded_dir)):
        for f in site.flights:
            paths = _flight_tiles(run, resolution, f.id)
            if paths:
                vrt = write_mosaic_vrt(paths, folder / f"{f.id}.vrt")
                written.setdefault(folder.name, []).append(run.rel(vrt))
    return written


def stac_items(site: SiteConfig, run: RunDir) -> list[RasterItem]:
    """An item per flight tile (with its degraded tile and labels) and for the satellite."""
    items = []
    cattle = run.labels_dir / "cattle.geojson"
    for f in site.flights:
        for tif in run.tile_files(f.id):
            assets: dict[str, tuple[Path, str, str]] = {"image": (tif, COG_TYPE, "data")}
            deg = run.degraded(f.id, tif.stem)
            if deg.is_file():
                assets["degraded"] = (deg, COG_TYPE, "data")
            for resolution in YOLO_SUBDIRS:
                txt = run.yolo_file(resolution, f.id, tif.stem)
                if txt.is_file():
                    assets[f"labels_{YOLO_SUBDIRS[resolution]}"] = (txt, "text/plain", "labels")
            if cattle.is_file():
                assets["labels_geojson"] = (cattle, "application/geo+json", "labels")
            items.append(RasterItem(f"{f.id}_{tif.stem}", tif, f.acquired, assets,
                                    {"geosim:flight": f.id, "geosim:tile_id": tif.stem,
                                     "gsd": site.parameters.uav_gsd_m}))
    sat_tif = run.satellite_grid
    if site.satellite is not None and site.satellite.acquired is not None and sat_tif.is_file():
        items.append(RasterItem("satellite", sat_tif, site.satellite.acquired,
                                {"image": (sat_tif, COG_TYPE, "data")},
                                {"gsd": site.parameters.sat_gsd_m}))
    elif site.satellite is not None and sat_tif.is_file():
        log.warning("satellite scene has no 'acquired' time in the site file: "
                    "it is left out of the STAC catalogue")
    return items


def write_yolo_datasets(site: SiteConfig, run: RunDir, *, val_fraction: float, seed: int
                        ) -> dict[str, dict[str, int]]:
    """``DIR/yolo`` from the UAV tiles and ``DIR/yolo_0.5m`` from the degraded tiles."""
    if not run.classes_txt.is_file():
        return {}
    names = [n.strip() for n in run.classes_txt.read_text().splitlines() if n.strip()]
    done = {}
    for resolution, name in YOLO_SUBDIRS.items():
        items = [(f.id, tif.stem, tif, run.yolo_file(resolution, f.id, tif.stem))
                 for f in site.flights for tif in _flight_tiles(run, resolution, f.id)]
        if items:
            kind = "tiles" if resolution == "uav" else "degraded"
            ds = write_yolo_dataset(
                run.root / name, items, names, val_fraction=val_fraction, seed=seed,
                note=f"geosim {kind} of site {site.name}: split by tile "
                     f"(val_fraction={val_fraction}, seed={seed})")
            done[name] = ds.images
    return done


def run_deliver(site: SiteConfig, out_dir: RunPath, *, val_fraction: float = VAL_FRACTION,
                seed: int = SPLIT_SEED) -> StepResult:
    """Write the delivery files of a run folder (see the module docstring).

    Parameters
    ----------
    site
        The site (flights, acquisition times, satellite).
    out_dir
        Run folder holding at least the tiles.
    val_fraction, seed
        Spatial split of the YOLO datasets (:func:`geosim.deliver.yolo_dataset.split_tiles`).
    """
    from geosim.deliver.qgis_project import write_qgis_project

    run = RunDir.of(out_dir)
    run.require_tiles_index()
    out = run.root
    mosaics = write_mosaics(site, run)
    log.info("mosaics: %s", ", ".join(sum(mosaics.values(), [])))
    items = stac_items(site, run)
    catalog = write_stac(out, site.name, items, description=f"geosim run of {site.name}")
    yolo = write_yolo_datasets(site, run, val_fraction=val_fraction, seed=seed)
    qgs = write_qgis_project(site, out)
    n_vrt = sum(len(v) for v in mosaics.values())
    yolo_text = ", ".join(f"{k} {v['train']}/{v['val']} train/val" for k, v in yolo.items())
    # every file of the folders this step owns (stac/, yolo/, yolo_0.5m/) is its output
    owned = [path for name in ("stac", *yolo) for path in (out / name).rglob("*")
             if path.is_file()]
    outputs = sorted({*sum(mosaics.values(), []), run.rel(qgs), *map(run.rel, owned)})
    return StepResult(
        summary=(f"{n_vrt} VRT mosaic(s), STAC with {len(items)} item(s), "
                 f"YOLO {yolo_text or 'none (no labels)'}, {qgs.name}"),
        outputs=outputs,
        record={"vrt": mosaics, "stac_items": len(items),
                "stac": catalog.relative_to(out).as_posix(), "yolo": yolo,
                "qgis_project": qgs.relative_to(out).as_posix()})


__all__ = ["run_deliver", "write_mosaics", "stac_items", "write_yolo_datasets"]
