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
from geosim.rundir import RunDir, RunPath

log = logging.getLogger(__name__)

#: Defaults of the spatial train/val split of the YOLO datasets.
VAL_FRACTION = 0.2
SPLIT_SEED = 0


def flight_tiles(out: Path, kind: str, flight: str) -> list[Path]:
    """``DIR/<kind>/<flight>/r*_c*.tif``, sorted."""
    return sorted((out / kind / flight).glob("r*_c*.tif"))


def write_mosaics(site: SiteConfig, out: Path) -> dict[str, list[str]]:
    """One VRT per flight for tiles/ and degraded/ (where that step ran)."""
    written: dict[str, list[str]] = {}
    for kind in ("tiles", "degraded"):
        for f in site.flights:
            paths = flight_tiles(out, kind, f.id)
            if paths:
                vrt = write_mosaic_vrt(paths, out / kind / f"{f.id}.vrt")
                written.setdefault(kind, []).append(vrt.relative_to(out).as_posix())
    return written


def stac_items(site: SiteConfig, out: Path) -> list[RasterItem]:
    """An item per flight tile (with its degraded tile and labels) and for the satellite."""
    items = []
    cattle = out / "labels" / "cattle.geojson"
    for f in site.flights:
        for tif in flight_tiles(out, "tiles", f.id):
            assets: dict[str, tuple[Path, str, str]] = {"image": (tif, COG_TYPE, "data")}
            deg = out / "degraded" / f.id / tif.name
            if deg.is_file():
                assets["degraded"] = (deg, COG_TYPE, "data")
            for res in ("yolo", "yolo_0.5m"):
                txt = out / "labels" / res / f.id / f"{tif.stem}.txt"
                if txt.is_file():
                    assets[f"labels_{res}"] = (txt, "text/plain", "labels")
            if cattle.is_file():
                assets["labels_geojson"] = (cattle, "application/geo+json", "labels")
            items.append(RasterItem(f"{f.id}_{tif.stem}", tif, f.acquired, assets,
                                    {"geosim:flight": f.id, "geosim:tile_id": tif.stem,
                                     "gsd": site.parameters.uav_gsd_m}))
    sat_tif = out / "grid" / "satellite.tif"
    if site.satellite is not None and site.satellite.acquired is not None and sat_tif.is_file():
        items.append(RasterItem("satellite", sat_tif, site.satellite.acquired,
                                {"image": (sat_tif, COG_TYPE, "data")},
                                {"gsd": site.parameters.sat_gsd_m}))
    elif site.satellite is not None and sat_tif.is_file():
        log.warning("satellite scene has no 'acquired' time in the site file: "
                    "it is left out of the STAC catalogue")
    return items


def write_yolo_datasets(site: SiteConfig, out: Path, *, val_fraction: float, seed: int
                        ) -> dict[str, dict[str, int]]:
    """``DIR/yolo`` from the UAV tiles and ``DIR/yolo_0.5m`` from the degraded tiles."""
    classes = out / "labels" / "classes.txt"
    if not classes.is_file():
        return {}
    names = [n.strip() for n in classes.read_text().splitlines() if n.strip()]
    done = {}
    for name, kind, labels in (("yolo", "tiles", "yolo"), ("yolo_0.5m", "degraded",
                                                           "yolo_0.5m")):
        items = [(f.id, tif.stem, tif, out / "labels" / labels / f.id / f"{tif.stem}.txt")
                 for f in site.flights for tif in flight_tiles(out, kind, f.id)]
        if items:
            ds = write_yolo_dataset(
                out / name, items, names, val_fraction=val_fraction, seed=seed,
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
    mosaics = write_mosaics(site, out)
    log.info("mosaics: %s", ", ".join(sum(mosaics.values(), [])))
    items = stac_items(site, out)
    catalog = write_stac(out, site.name, items, description=f"geosim run of {site.name}")
    yolo = write_yolo_datasets(site, out, val_fraction=val_fraction, seed=seed)
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
