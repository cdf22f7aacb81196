"""Writing a diagnosis: GeoTIFFs, regions.geojson, moved_objects.geojson, diagnosis.json,
plots and report.md
(figures in :mod:`~geosim.diagnose.report_figures`, the markdown in
:mod:`~geosim.diagnose.report_markdown`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import Diagnosis
from geosim.diagnose.report_figures import (
    COMBINED_PLOT,
    DEFAULT_DPI,
    diagnosis_plots,
    flights_figure,
    save_png,
)
from geosim.diagnose.report_markdown import combined_markdown, diagnosis_markdown
from geosim.io.atomic import atomic_path, to_jsonable, write_json, write_text
from geosim.io.raster import provenance_tags, write_geotiff

__all__ = ["write_diagnosis", "write_combined", "FILES", "MAPS"]

FILES = {"satellite": "satellite_on_grid.tif", "baseline": "sim_baseline.tif",
         "refined": "sim_refined.tif"}
MAPS = {"residual_energy": "map_residual_energy.tif", "blur_ratio": "map_blur_ratio.tif",
        "gain": "map_gain.tif", "offset": "map_offset.tif"}


def _regions_gdf(diag: Diagnosis, transform: Affine, crs: CRS):
    import geopandas as gpd
    from rasterio import features
    from shapely.geometry import shape

    rows = []
    if diag.labels is not None:
        by_label = {r.label: r for r in diag.regions}
        lab = diag.labels.astype(np.int32)
        for geom, val in features.shapes(lab, mask=lab > 0, transform=transform):
            reg = by_label.get(int(val))
            if reg is None:
                continue
            rows.append({"rank": reg.rank, "kind": reg.kind, "area_m2":
                         reg.area_px * abs(transform.a * transform.e),
                         "excess_energy_dn2": reg.excess_energy,
                         "mean_ratio": reg.mean_ratio, "geometry": shape(geom)})
    gdf = gpd.GeoDataFrame(rows, columns=["rank", "kind", "area_m2", "excess_energy_dn2",
                                          "mean_ratio", "geometry"], geometry="geometry", crs=crs)
    if len(gdf):
        gdf = gdf.dissolve(by="rank", as_index=False, aggfunc="first").sort_values("rank")
    return gdf


#: columns of moved_objects.geojson (with the geometry: the object's ellipse)
OBJECT_COLUMNS = ["object", "change", "length_m", "width_m", "angle_deg", "contrast_dn",
                  "rss_drop"]


def _objects_gdf(summary: dict[str, Any], transform: Affine, crs: CRS):
    """The refined simulation's moved objects (``summary["refined"]["moved_objects"]``) as
    ellipse polygons in map coordinates (32 vertices)."""
    import geopandas as gpd
    from shapely.geometry import Polygon

    gsd_m = abs(transform.a)
    t = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    rows = []
    for k, o in enumerate(summary.get("refined", {}).get("moved_objects", []), start=1):
        a, b = o["size_m"][0] / (2 * gsd_m), o["size_m"][1] / (2 * gsd_m)
        th = np.deg2rad(o["angle_deg"])
        # pixel (col, row); the major axis turns anticlockwise on the map (rows run south)
        col = o["centre_px"][0] + a * np.cos(t) * np.cos(th) + b * np.sin(t) * np.sin(th)
        row = o["centre_px"][1] - a * np.cos(t) * np.sin(th) + b * np.sin(t) * np.cos(th)
        xs, ys = transform * (col, row)
        rows.append({"object": k, "change": o["change"], "length_m": o["size_m"][0],
                     "width_m": o["size_m"][1], "angle_deg": o["angle_deg"],
                     "contrast_dn": ", ".join(f"{c:g}" for c in o["contrast_dn"]),
                     "rss_drop": o["rss_drop"], "geometry": Polygon(np.column_stack([xs, ys]))})
    return gpd.GeoDataFrame(rows, columns=[*OBJECT_COLUMNS, "geometry"], geometry="geometry",
                            crs=crs)


def write_diagnosis(diag: Diagnosis, out_dir: str | Path, *, transform: Affine, crs: CRS | str,
                    sources: list[str] | None = None, extra: dict[str, Any] | None = None,
                    dpi: int = DEFAULT_DPI) -> dict[str, Any]:
    """Write all outputs of a diagnosis into ``out_dir``; returns the diagnosis.json dict.

    The figures name ``extra["flight"]`` when given and are rendered at ``dpi`` (dots per
    inch: the PNGs' pixel size scales with it).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    crs = CRS.from_user_input(crs)
    tags = provenance_tags("diagnose", {"q_base": diag.summary["baseline"]["q"]}, sources or [])
    names = ["red", "green", "blue"] if diag.real.shape[0] == 3 else None
    for key, arr in (("satellite", diag.real), ("baseline", diag.baseline),
                     ("refined", diag.refined)):
        write_geotiff(out / FILES[key], arr.astype(np.float32), transform=transform, crs=crs,
                      nodata=np.nan, mask=diag.valid, band_descriptions=names, tags=tags)
    for key, fname in MAPS.items():
        write_geotiff(out / fname, diag.maps[key].astype(np.float32), transform=transform,
                      crs=crs, nodata=np.nan, band_descriptions=[key], tags=tags)
    from geosim.io.vector import write_geojson, write_gpkg

    gdf = _regions_gdf(diag, transform, crs)
    write_geojson(gdf, out / "regions.geojson")
    if len(gdf):
        write_gpkg(gdf, out / "regions.gpkg", layer="regions")
    objects = _objects_gdf(diag.summary, transform, crs)
    write_geojson(objects, out / "moved_objects.geojson")
    if len(objects):
        write_gpkg(objects, out / "moved_objects.gpkg", layer="moved_objects")
    plots = diagnosis_plots(diag, out, transform=transform, crs=crs,
                            flight=(extra or {}).get("flight"), dpi=dpi)
    summary = dict(diag.summary)
    summary["n_regions"] = len(diag.regions)
    doc: dict[str, Any] = {
        "grid": {"crs": crs.to_string(), "transform": list(transform)[:6],
                 "width": int(diag.real.shape[-1]), "height": int(diag.real.shape[-2])},
        **summary,
        "regions": "regions.geojson",
        "moved_objects": "moved_objects.geojson",
        "files": dict(FILES),
        "maps": dict(MAPS),
        "plots": plots,
        "report": "report.md",
    }
    if extra:
        doc.update(extra)
    write_json(out / "diagnosis.json", to_jsonable(doc, nan_to_null=True))
    write_text(out / "report.md", diagnosis_markdown(summary))
    return doc


def _copy_atomic(src: Path, dst: Path) -> None:
    import shutil

    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def write_combined(per: dict[str, dict[str, Any]], out_dir: str | Path, *, reference: str,
                   dirs: dict[str, str], skipped: dict[str, str] | None = None,
                   extra: dict[str, Any] | None = None, dpi: int = DEFAULT_DPI
                   ) -> dict[str, Any]:
    """Write the combined diagnosis of several flights into ``out_dir``.

    ``per`` holds each flight's diagnosis dict (as returned by :func:`write_diagnosis`,
    written to ``out_dir/dirs[flight]``). Writes ``diagnosis.json`` (the issue's schema
    for the combined verdict, plus ``flights``), ``report.md``, ``regions.geojson`` and
    ``moved_objects.geojson`` (all flights' regions and moved objects, attribute
    ``flight``) and copies of the reference flight's
    GeoTIFFs, maps and plots (titled with the reference flight), so that ``files``
    resolves at the top level, and ``flights_combined.png`` (every flight's Q and RMSE
    beside the combined verdict, titled "All flights (combined)") at ``dpi``.
    """
    import geopandas as gpd
    import pandas as pd

    from geosim.diagnose.combine import combine_flights
    from geosim.io.vector import write_geojson, write_gpkg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ref_dir = out / dirs[reference]
    ref = per[reference]
    for name in [*FILES.values(), *MAPS.values(), *ref.get("plots", [])]:
        _copy_atomic(ref_dir / name, out / name)
    crs = CRS.from_user_input(ref["grid"]["crs"])

    def all_flights(name: str, empty_columns: list[str], *, optional: bool = False
                    ) -> gpd.GeoDataFrame:
        """Every flight's ``name`` layer in one, attribute ``flight`` first; ``optional``:
        a flight without the file (a diagnosis reused from before the file existed)
        contributes nothing, else its absence is an error as any missing output."""
        frames = []
        for f in per:
            path = out / dirs[f] / name
            g = None if optional and not path.is_file() else gpd.read_file(path)
            if g is not None and len(g):
                g = g.to_crs(crs)
                g.insert(0, "flight", f)
                frames.append(g)
        if frames:
            return gpd.GeoDataFrame(pd.concat(frames, ignore_index=True),
                                    geometry="geometry", crs=crs)
        return gpd.GeoDataFrame({c: [] for c in ["flight", *empty_columns]}, geometry=[],
                                crs=crs)

    gdf = all_flights("regions.geojson", ["rank", "kind"])
    write_geojson(gdf, out / "regions.geojson")
    objects = all_flights("moved_objects.geojson", OBJECT_COLUMNS, optional=True)
    write_geojson(objects, out / "moved_objects.geojson")
    if len(objects):
        write_gpkg(objects, out / "moved_objects.gpkg", layer="moved_objects")
    if len(gdf):
        write_gpkg(gdf, out / "regions.gpkg", layer="regions")
    comb = combine_flights(per, reference=reference)
    plots = [*ref.get("plots", []),
             save_png(flights_figure(per, comb), out / COMBINED_PLOT, dpi=dpi)]
    flights = {f: {**to_jsonable(d, nan_to_null=True), "dir": dirs[f]} for f, d in per.items()}
    doc: dict[str, Any] = {
        "grid": ref["grid"], **comb,
        "regions": "regions.geojson", "moved_objects": "moved_objects.geojson",
        "files": dict(FILES), "maps": dict(MAPS), "plots": plots,
        "report": "report.md", "reference_flight": reference,
        "flights": flights, "flights_skipped": dict(skipped or {}),
        "n_regions": int(len(gdf)),
    }
    if extra:
        doc.update(extra)
    write_json(out / "diagnosis.json", to_jsonable(doc, nan_to_null=True))
    write_text(out / "report.md", combined_markdown(doc, per, dirs))
    return doc
