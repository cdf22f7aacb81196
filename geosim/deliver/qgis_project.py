"""A QGIS project (``DIR/geosim.qgs``) written as XML, without a QGIS dependency.

Groups (top to bottom): cattle per flight (one colour each, temporal), paddocks labelled
with their cattle counts, tile index, footprints and common extent, diagnosis (regions
and maps), degraded mosaics, flight mosaics (VRT), satellite. Paths are relative to the
project file (``./tiles/PA1.vrt``), so the run folder can move; every layer has the
temporal range of its acquisition, so QGIS's temporal controller steps through the flights.

The XML follows what QGIS 3.22 writes for the same layers (element names of
``QgsProject::write``, ``QgsMapLayer::writeLayerXml``, the layer tree and the renderers);
tests open it with real QGIS and require every layer to be valid.
"""

from __future__ import annotations

import datetime as dt
import logging
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape, quoteattr

import numpy as np
import rasterio
from pyproj import CRS as ProjCRS

from geosim.config import SiteConfig
from geosim.io.atomic import write_text
from geosim.rundir import RunDir

log = logging.getLogger(__name__)

#: One colour per flight for the cattle boxes (r, g, b), cycled.
FLIGHT_COLOURS = ((228, 26, 28), (55, 126, 184), (77, 175, 74), (152, 78, 163),
                  (255, 127, 0), (255, 255, 51), (166, 86, 40), (247, 129, 191))


@dataclass
class Layer:
    """One map layer of the project (``id`` is prefixed: QGIS ignores ids of ≤ 10 characters)."""

    id: str
    name: str
    source: str                  # relative to the project file, "./..."
    kind: str                    # "raster" or "vector"
    crs_wkt: str
    style: str = ""              # renderer XML
    geometry: str = ""           # vector: Point / Polygon
    time_range: tuple[dt.datetime, dt.datetime] | None = None
    labels: str = ""             # labeling XML (vector)

    def __post_init__(self) -> None:
        if not self.id.startswith("geosim_layer_"):
            self.id = f"geosim_layer_{self.id}"


def _srs(wkt: str) -> str:
    crs = ProjCRS.from_wkt(wkt)
    auth = crs.to_authority() or ("", "")
    authid = f"{auth[0]}:{auth[1]}" if auth[0] else ""
    with warnings.catch_warnings():   # the PROJ string is informative; QGIS reads the WKT
        warnings.simplefilter("ignore", UserWarning)
        proj4 = crs.to_proj4() or ""
    return (f"<spatialrefsys><wkt>{escape(crs.to_wkt())}</wkt>"
            f"<proj4>{escape(proj4)}</proj4>"
            f"<authid>{escape(authid)}</authid>"
            f"<description>{escape(crs.name)}</description>"
            f"<geographicflag>{'true' if crs.is_geographic else 'false'}</geographicflag>"
            "</spatialrefsys>")


def _rgba(rgb: Sequence[int], a: int = 255) -> str:
    return f"{rgb[0]},{rgb[1]},{rgb[2]},{a}"


def fill_renderer(outline: Sequence[int], *, fill_alpha: int = 0, width_mm: float = 0.5,
                  dashed: bool = False) -> str:
    """A single-symbol polygon renderer: coloured outline, optional translucent fill."""
    style = "solid" if fill_alpha else "no"
    return (
        '<renderer-v2 type="singleSymbol" symbollevels="0" enableorderby="0" forceraster="0">'
        '<symbols><symbol type="fill" name="0" alpha="1" clip_to_extent="1" force_rhr="0">'
        '<layer class="SimpleFill" enabled="1" locked="0" pass="0">'
        f'<prop k="color" v="{_rgba(outline, fill_alpha)}"/>'
        f'<prop k="style" v="{style}"/>'
        f'<prop k="outline_color" v="{_rgba(outline)}"/>'
        f'<prop k="outline_style" v="{"dash" if dashed else "solid"}"/>'
        f'<prop k="outline_width" v="{width_mm}"/><prop k="outline_width_unit" v="MM"/>'
        '</layer></symbol></symbols><rotation/><sizescale/></renderer-v2>')


def rgb_renderer(bands: int) -> str:
    """Multiband colour renderer for RGB imagery (grey for one band)."""
    if bands >= 3:
        return ('<rasterrenderer type="multibandcolor" redBand="1" greenBand="2" blueBand="3" '
                'opacity="1" alphaBand="-1" nodataColor=""><rasterTransparency/>'
                '<minMaxOrigin><limits>None</limits><extent>WholeRaster</extent>'
                '<statAccuracy>Estimated</statAccuracy></minMaxOrigin></rasterrenderer>')
    return grey_renderer(0.0, 255.0)


def grey_renderer(vmin: float, vmax: float) -> str:
    """Single-band grey renderer stretched from ``vmin`` to ``vmax``."""
    return ('<rasterrenderer type="singlebandgray" grayBand="1" gradient="BlackToWhite" '
            'opacity="1" alphaBand="-1" nodataColor=""><rasterTransparency/>'
            '<minMaxOrigin><limits>None</limits><extent>WholeRaster</extent>'
            '<statAccuracy>Estimated</statAccuracy></minMaxOrigin>'
            f'<contrastEnhancement><minValue>{vmin!r}</minValue><maxValue>{vmax!r}</maxValue>'
            '<algorithm>StretchToMinimumMaximum</algorithm></contrastEnhancement>'
            '</rasterrenderer>')


def field_labels(field_name: str, *, size_pt: float = 10.0) -> str:
    """Simple labels from a field, white with a black buffer."""
    return (
        '<labeling type="simple"><settings calloutType="simple">'
        f'<text-style fieldName={quoteattr(field_name)} isExpression="0" fontSize="{size_pt}" '
        'fontSizeUnit="Point" textColor="255,255,255,255" fontFamily="Sans Serif" '
        'fontWeight="75" textOpacity="1" multilineHeight="1">'
        '<text-buffer bufferDraw="1" bufferSize="1" bufferSizeUnits="MM" '
        'bufferColor="0,0,0,255" bufferOpacity="1"/></text-style>'
        '<text-format wrapChar="|" multilineAlign="3" autoWrapLength="0"/>'
        '<placement placement="1" dist="0" priority="5" offsetType="0"/>'
        '<rendering obstacle="1" drawLabels="1" scaleVisibility="0" displayAll="1"/>'
        '</settings></labeling>')


def _temporal(layer: Layer) -> str:
    if layer.time_range is None:
        return ""
    start, end = (t.astimezone(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ") for t in layer.time_range)
    rng = f"<fixedRange><start>{start}</start><end>{end}</end></fixedRange>"
    if layer.kind == "raster":
        return f'<temporal enabled="1" mode="0" fetchMode="0">{rng}</temporal>'
    return ('<temporal enabled="1" mode="0" limitMode="0" accumulate="0" startField="" '
            'endField="" durationField="" durationUnit="min" fixedDuration="0" '
            f'startExpression="" endExpression="">{rng}</temporal>')


def _maplayer(layer: Layer) -> str:
    attrs = f'type="{layer.kind}"'
    if layer.kind == "vector":
        attrs += (f' geometry="{layer.geometry}" labelsEnabled="{1 if layer.labels else 0}"'
                  ' readOnly="0"')
    provider = ('<provider>gdal</provider>' if layer.kind == "raster"
                else '<provider encoding="UTF-8">ogr</provider>')
    return (f"<maplayer {attrs} hasScaleBasedVisibilityFlag=\"0\" autoRefreshEnabled=\"0\">"
            f"<id>{escape(layer.id)}</id><datasource>{escape(layer.source)}</datasource>"
            f"<layername>{escape(layer.name)}</layername><srs>{_srs(layer.crs_wkt)}</srs>"
            f"{provider}{_temporal(layer)}"
            + (f"<pipe>{layer.style}</pipe>" if layer.kind == "raster" else layer.style)
            + layer.labels + "<blendMode>0</blendMode></maplayer>")


def _tree(groups: Sequence[tuple[str, Sequence[Layer]]]) -> str:
    parts = ["<layer-tree-group><customproperties/>"]
    for name, layers in groups:
        parts.append(f"<layer-tree-group name={quoteattr(name)} checked=\"Qt::Checked\" "
                     "expanded=\"1\"><customproperties/>")
        for ly in layers:
            provider = "gdal" if ly.kind == "raster" else "ogr"
            parts.append(f"<layer-tree-layer id={quoteattr(ly.id)} name={quoteattr(ly.name)} "
                         f"source={quoteattr(ly.source)} providerKey=\"{provider}\" "
                         "checked=\"Qt::Checked\" expanded=\"0\"><customproperties/>"
                         "</layer-tree-layer>")
        parts.append("</layer-tree-group>")
    parts.append("</layer-tree-group>")
    return "".join(parts)


def project_xml(title: str, crs_wkt: str, extent: tuple[float, float, float, float],
                groups: Sequence[tuple[str, Sequence[Layer]]]) -> str:
    """The whole ``.qgs`` document."""
    from geosim import __version__

    layers = [ly for _, lys in groups for ly in lys]
    xmin, ymin, xmax, ymax = extent
    return (
        "<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>\n"
        f"<qgis projectname={quoteattr(title)} version=\"3.22.16-Białowieża\" "
        f"saveUser=\"geosim\" saveUserFull=\"geosim {escape(__version__)}\">\n"
        f"<homePath path=\"\"/><title>{escape(title)}</title>\n"
        f"<projectCrs>{_srs(crs_wkt)}</projectCrs>\n"
        + _tree(groups) + "\n"
        "<mapcanvas annotationsVisible=\"1\" name=\"theMapCanvas\"><units>meters</units>"
        f"<extent><xmin>{xmin!r}</xmin><ymin>{ymin!r}</ymin><xmax>{xmax!r}</xmax>"
        f"<ymax>{ymax!r}</ymax></extent><rotation>0</rotation>"
        f"<destinationsrs>{_srs(crs_wkt)}</destinationsrs></mapcanvas>\n"
        "<projectlayers>\n" + "\n".join(_maplayer(ly) for ly in layers) + "\n</projectlayers>\n"
        "<layerorder>" + "".join(f"<layer id={quoteattr(ly.id)}/>" for ly in layers)
        + "</layerorder>\n"
        "<properties><Paths><Absolute type=\"bool\">false</Absolute></Paths>"
        # QGIS reads <projectCrs> only when this (legacy) flag is set
        "<SpatialRefSys><ProjectionsEnabled type=\"int\">1</ProjectionsEnabled></SpatialRefSys>"
        "<Measurement><DistanceUnits type=\"QString\">meters</DistanceUnits>"
        "<AreaUnits type=\"QString\">m2</AreaUnits></Measurement></properties>\n"
        "</qgis>\n")


def _instant(t: dt.datetime) -> tuple[dt.datetime, dt.datetime]:
    """A one-minute range starting at ``t`` (QGIS ranges need an end after the start)."""
    return (t, t + dt.timedelta(minutes=1))


def _raster(out: Path, rel: str, name: str, lid: str, *, time: dt.datetime | None = None,
            stretch: bool = False) -> Layer | None:
    path = out / rel
    if not path.is_file():
        return None
    with rasterio.open(path) as ds:
        wkt = ds.crs.to_wkt()
        if stretch:
            ov = ds.overviews(1)
            f = ov[-1] if ov else 1
            arr = ds.read(1, masked=True, out_shape=(max(1, ds.height // f),
                                                     max(1, ds.width // f)))
            vals = arr.compressed()
            vals = vals[np.isfinite(vals)]
            lo, hi = (np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0))
            style = grey_renderer(float(lo), float(hi if hi > lo else lo + 1))
        else:
            style = rgb_renderer(ds.count)
    return Layer(lid, name, f"./{rel}", "raster", wkt, style,
                 time_range=_instant(time) if time else None)


def _vector(out: Path, rel: str, layer: str, name: str, lid: str, style: str, geometry: str,
            *, subset: str = "", time: dt.datetime | None = None, labels: str = ""
            ) -> Layer | None:
    import pyogrio

    path = out / rel
    if not path.is_file():
        return None
    info = pyogrio.read_info(path, layer=layer)
    wkt = ProjCRS.from_user_input(info["crs"]).to_wkt()
    source = f"./{rel}|layername={layer}" + (f"|subset={subset}" if subset else "")
    return Layer(lid, name, source, "vector", wkt, style, geometry,
                 time_range=_instant(time) if time else None, labels=labels)


def _keep(layers: Sequence[Layer | None]) -> list[Layer]:
    return [ly for ly in layers if ly is not None]


def write_paddock_counts(site: SiteConfig, out: Path) -> Path | None:
    """``DIR/paddocks.gpkg``: paddock polygons with cattle counts per flight and a label."""
    from geosim.io.vector import write_gpkg
    from geosim.labels.paddocks import OUTSIDE, cattle_per_paddock
    from geosim.labels.sources import read_paddocks

    cattle_path = RunDir.of(out).labels_dir / "cattle.gpkg"
    if site.paddocks is None or not cattle_path.is_file():
        return None
    import geopandas as gpd

    pads = read_paddocks(site.paddocks)
    cattle = gpd.read_file(cattle_path, layer="cattle")
    table = cattle_per_paddock(cattle, pads)
    table = table[table["paddock"] != OUTSIDE]
    names = list(dict.fromkeys(table["paddock"]))
    flights = list(dict.fromkeys(table["flight"]))
    geoms = [pads[pads["name"].astype(str) == n].geometry.union_all() for n in names]
    gdf = gpd.GeoDataFrame({"paddock": names}, geometry=geoms, crs=pads.crs).to_crs(cattle.crs)
    counts = {(r.flight, r.paddock): int(r.count) for r in table.itertuples()}
    for f in flights:
        gdf[f"cattle_{f}"] = [counts.get((f, n), 0) for n in names]
    gdf["label"] = [f"{n}\n" + ", ".join(f"{f}: {counts.get((f, n), 0)}" for f in flights)
                    for n in names]
    return write_gpkg(gdf, out / "paddocks.gpkg", layer="paddocks")


def build_groups(site: SiteConfig, out: Path) -> list[tuple[str, list[Layer]]]:
    """The project's layer groups from what the run folder holds (top group drawn last)."""
    flights = site.flights
    cattle = [_vector(out, "labels/cattle.gpkg", "cattle", f"cattle {f.id}", f"cattle_{f.id}",
                      fill_renderer(FLIGHT_COLOURS[i % len(FLIGHT_COLOURS)], width_mm=0.4),
                      "Polygon", subset=f"\"flight\" = '{f.id}'", time=f.acquired)
              for i, f in enumerate(flights)]
    paddocks_gpkg = write_paddock_counts(site, out)
    paddocks = [_vector(out, "paddocks.gpkg", "paddocks", "paddocks (cattle per flight)",
                        "paddocks", fill_renderer((0, 255, 255), width_mm=0.8), "Polygon",
                        labels=field_labels("label"))] if paddocks_gpkg else []
    diag = [_vector(out, "diagnosis/regions.gpkg", "regions", "mismatch regions",
                    "diag_regions", fill_renderer((255, 0, 255), fill_alpha=60), "Polygon"),
            _vector(out, "diagnosis/moved_objects.gpkg", "moved_objects",
                    "moved objects (scene change, modelled)", "diag_moved_objects",
                    fill_renderer((0, 200, 255), fill_alpha=90), "Polygon",
                    labels=field_labels("change"))]
    diag += [_raster(out, f"diagnosis/{m}.tif", m.replace("_", " "), f"diag_{m}", stretch=True)
             for m in ("map_residual_energy", "map_blur_ratio", "map_gain", "map_offset")]
    sat_time = site.satellite.acquired if site.satellite else None
    return [
        ("Cattle (per flight)", _keep(cattle)),
        ("Paddocks", _keep(paddocks)),
        ("Tile index", _keep([_vector(out, "tiles/index.gpkg", "tiles", "tile index",
                                      "tile_index", fill_renderer((255, 255, 0), dashed=True),
                                      "Polygon")])),
        ("Footprints", _keep([
            _vector(out, "common_extent.gpkg", "common_extent", "common extent",
                    "common_extent", fill_renderer((255, 255, 255), width_mm=0.8), "Polygon"),
            _vector(out, "footprints.gpkg", "footprints", "footprints", "footprints",
                    fill_renderer((255, 140, 0)), "Polygon")])),
        ("Diagnosis", _keep(diag)),
        ("Degraded (0.5 m)", _keep([_raster(out, f"degraded/{f.id}.vrt", f"degraded {f.id}",
                                            f"degraded_{f.id}", time=f.acquired)
                                    for f in flights])),
        ("Flights (UAV mosaics)", _keep([_raster(out, f"tiles/{f.id}.vrt", f"flight {f.id}",
                                                 f"flight_{f.id}", time=f.acquired)
                                         for f in flights])),
        ("Satellite", _keep([_raster(out, "grid/satellite.tif", "satellite", "satellite",
                                     time=sat_time)])),
    ]


def write_qgis_project(site: SiteConfig, out_dir: str | Path) -> Path:
    """Write ``DIR/geosim.qgs`` for the run folder (layers that exist); returns its path."""
    import json

    run = RunDir.of(out_dir)
    out = run.root
    groups = [(name, layers) for name, layers in build_groups(site, out) if layers]
    grid = json.loads(run.grid_json.read_text())
    crs_wkt = ProjCRS.from_user_input(grid["crs"]).to_wkt()
    with rasterio.open(run.tiles_dir / f"{site.flights[0].id}.vrt") as ds:
        extent = tuple(ds.bounds)
    log.info("QGIS project: %d layer(s) in %d group(s)",
             sum(len(g[1]) for g in groups), len(groups))
    return write_text(out / "geosim.qgs", project_xml(f"geosim: {site.name}", crs_wkt,
                                                      extent, groups))


__all__ = ["Layer", "build_groups", "project_xml", "write_paddock_counts",
           "write_qgis_project"]
