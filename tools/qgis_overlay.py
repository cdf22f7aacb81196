#!/usr/bin/env python3
"""Check in QGIS that a geosim run's outputs overlay, and render pictures of it.

Run with the system Python that has the QGIS bindings (Debian: ``apt-get install
python3-qgis``), not the project venv::

    QT_QPA_PLATFORM=offscreen /usr/bin/python3 tools/qgis_overlay.py RUN_DIR OUT.png

It starts a headless ``QgsApplication``, loads from RUN_DIR (the output folder of
``geosim run`` / ``geosim demo``):

* ``grid/satellite.tif`` (the satellite scene on the shared 0.5 m grid),
* one UAV tile ``tiles/<flight>/<tile_id>.tif`` (0.05 m) and its degraded twin
  ``degraded/<flight>/<tile_id>.tif`` (0.5 m),
* ``labels/cattle.geojson`` (filtered to the flight), ``tiles/index.geojson``,
* the site's paddocks GeoJSON (from ``run.json``, or ``--paddocks``),

checks that every layer is valid, has the expected CRS (rasters: the site CRS from
``grid/grid.json``; GeoJSON: EPSG:4326 as RFC 7946 requires), that every extent
intersects the satellite scene in the project (site) CRS, that the UAV and degraded
tiles cover exactly the same ground and match their ``tiles/index.geojson`` feature,
and prints the table. It measures the offset between the degraded tile and the
satellite (sub-pixel phase correlation, metres east/north) and renders:

* OUT.png: the UAV tile, the cattle boxes (red outlines) of that flight, the
  paddock boundaries (cyan) and the tile index (yellow, dashed) over the satellite;
* OUT2 (``--out2``; default: OUT with ``_overlay`` replaced by
  ``_degraded_vs_satellite``, or ``_degraded_vs_satellite`` appended): the degraded
  tile, the satellite, and the satellite at 50 % opacity over the degraded tile,
  side by side on the same extent, with a 5 m reference grid.

Exit status: 0 when every check passes, 1 when a layer is invalid or misplaced
(the message says which and why), 2 on bad arguments or missing files.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402

try:
    from osgeo import gdal  # noqa: E402
    from qgis.core import (  # noqa: E402
        Qgis,
        QgsApplication,
        QgsContrastEnhancement,
        QgsCoordinateReferenceSystem,
        QgsCoordinateTransform,
        QgsFeatureRequest,
        QgsFillSymbol,
        QgsGeometry,
        QgsMapRendererParallelJob,
        QgsMapSettings,
        QgsMultiBandColorRenderer,
        QgsPalLayerSettings,
        QgsProject,
        QgsRasterLayer,
        QgsRectangle,
        QgsSingleSymbolRenderer,
        QgsTextBufferSettings,
        QgsTextFormat,
        QgsVectorLayer,
        QgsVectorLayerSimpleLabeling,
    )
    from qgis.PyQt.QtCore import QPointF, QRectF, QSize, Qt  # noqa: E402
    from qgis.PyQt.QtGui import QColor, QFont, QImage, QPainter, QPen  # noqa: E402
except ImportError as exc:  # pragma: no cover - depends on the machine
    sys.exit(f"qgis_overlay: cannot import the QGIS Python bindings ({exc}); install them "
             "(Debian: apt-get install python3-qgis) and run with /usr/bin/python3, "
             "not the project venv")

GEOJSON_CRS = "EPSG:4326"
CATTLE_RGB = (230, 20, 20)
PADDOCK_RGB = (0, 230, 255)
TILE_RGB = (255, 220, 0)
OFFSET_RGB = (255, 140, 0)


class CheckFailed(Exception):
    """A layer is invalid or misplaced; the message says which and why."""


@dataclass
class LayerCheck:
    """One row of the printed check table."""

    name: str
    path: str
    valid: bool
    crs: str
    expected_crs: str
    crs_ok: bool
    extent: QgsRectangle | None  # in the project CRS (m)
    intersects: bool
    note: str = ""


# --------------------------------------------------------------------------- inputs
def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    p = argparse.ArgumentParser(
        description="Load a geosim run in headless QGIS, check the layers overlay, "
                    "render overlay pictures.")
    p.add_argument("run_dir", type=Path, help="output folder of `geosim run` / `geosim demo`")
    p.add_argument("out_png", type=Path, help="overlay picture (PNG) to write")
    p.add_argument("--out2", type=Path, default=None,
                   help="degraded-vs-satellite picture (default: derived from OUT_PNG)")
    p.add_argument("--flight", default=None,
                   help="flight id (default: the alignment reference flight)")
    p.add_argument("--tile", default=None,
                   help="tile id r###_c### (default: the tile with most cattle of the flight)")
    p.add_argument("--paddocks", type=Path, default=None,
                   help="paddocks vector file (default: the site's, from run.json)")
    p.add_argument("--margin-m", type=float, default=6.0,
                   help="map margin around the tile in the overlay picture, m (default 6)")
    p.add_argument("--max-offset-m", type=float, default=5.0,
                   help="fail when the degraded tile and the satellite are confidently offset "
                        "by more than this, m (default 5; the sample site's deliberate "
                        "georeferencing errors give about 1.5 m)")
    p.add_argument("--max-kb", type=float, default=400.0,
                   help="keep each PNG below this size, KiB (palette/scale down if needed)")
    p.add_argument("--title", default=None, help="title prefix for the pictures")
    return p.parse_args(argv)


def default_out2(out_png: Path) -> Path:
    """OUT.png -> OUT with `_overlay` replaced by `_degraded_vs_satellite`."""
    stem = out_png.stem
    stem = (stem[: -len("_overlay")] if stem.endswith("_overlay") else stem)
    return out_png.with_name(f"{stem}_degraded_vs_satellite.png")


def read_json(path: Path) -> dict:
    """Read a JSON file or exit 2 with a message naming it."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        fail_usage(f"{path} is missing: is {path.parent} the output folder of a finished "
                   "`geosim run`?")
    except json.JSONDecodeError as exc:
        fail_usage(f"{path} is not valid JSON ({exc}); re-run geosim")


def fail_usage(msg: str) -> None:
    """Print ``msg`` and exit with status 2 (bad arguments or missing files)."""
    print(f"qgis_overlay: {msg}", file=sys.stderr)
    raise SystemExit(2)


def require(path: Path, what: str) -> Path:
    """Exit 2 with a message when an expected run output is missing."""
    if not path.exists():
        fail_usage(f"{what} {path} is missing: is the run complete "
                   "(`geosim run SITE.toml --out DIR`)?")
    return path


# --------------------------------------------------------------------------- layers
def raster_layer(path: Path, name: str) -> QgsRasterLayer:
    """A GDAL raster layer (not yet styled), owned by the project when valid."""
    layer = QgsRasterLayer(str(path), name, "gdal")
    QgsProject.instance().addMapLayer(layer, False)
    return layer


def vector_layer(path: Path, name: str, subset: str | None = None) -> QgsVectorLayer:
    """An OGR vector layer, optionally filtered by an OGR SQL subset string."""
    layer = QgsVectorLayer(str(path), name, "ogr")
    if subset and layer.isValid():
        layer.setSubsetString(subset)
    QgsProject.instance().addMapLayer(layer, False)
    return layer


def same_crs(crs: QgsCoordinateReferenceSystem, expected: str) -> bool:
    """True when ``crs`` is the CRS named ``expected`` (authid or equivalent definition)."""
    if not crs.isValid():
        return False
    if crs.authid().upper() == expected.upper():
        return True
    return crs == QgsCoordinateReferenceSystem(expected)


def extent_in(layer, dest: QgsCoordinateReferenceSystem) -> QgsRectangle:
    """The layer's extent transformed to ``dest`` (m for a projected CRS)."""
    if layer.crs() == dest:
        return QgsRectangle(layer.extent())
    xform = QgsCoordinateTransform(layer.crs(), dest, QgsProject.instance())
    return xform.transformBoundingBox(layer.extent())


def check_layer(layer, name: str, path: Path, expected_crs: str | None,
                project_crs: QgsCoordinateReferenceSystem,
                area: QgsRectangle | None) -> LayerCheck:
    """Validity, CRS and extent-intersection check of one layer."""
    valid = layer.isValid()
    crs = layer.crs().authid() if valid else ""
    if valid and not crs:
        crs = layer.crs().description() or "(none)"
    crs_ok = valid and (same_crs(layer.crs(), expected_crs) if expected_crs
                        else layer.crs().isValid())
    ext = extent_in(layer, project_crs) if valid and layer.crs().isValid() else None
    inter = bool(ext is not None and (area is None or ext.intersects(area)))
    return LayerCheck(name, str(path), valid, crs, expected_crs or "any valid",
                      crs_ok, ext, inter)


def fmt_extent(r: QgsRectangle | None) -> str:
    """xmin..xmax, ymin..ymax in metres, 2 decimals."""
    if r is None:
        return "-"
    return (f"{r.xMinimum():.2f}..{r.xMaximum():.2f}, "
            f"{r.yMinimum():.2f}..{r.yMaximum():.2f}")


def max_corner_diff(a: QgsRectangle, b: QgsRectangle) -> float:
    """Largest difference between the bounds of two rectangles, map units (m)."""
    return max(abs(a.xMinimum() - b.xMinimum()), abs(a.yMinimum() - b.yMinimum()),
               abs(a.xMaximum() - b.xMaximum()), abs(a.yMaximum() - b.yMaximum()))


def print_table(rows: list[LayerCheck], project_crs: str) -> None:
    """Markdown table of the layer checks."""
    print(f"\nLayer checks (extents in the project CRS {project_crs}, m):\n")
    print("| layer | valid | CRS | expected | CRS ok | extent x, y | intersects | note |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r.name} | {'yes' if r.valid else 'NO'} | {r.crs or '-'} | {r.expected_crs} "
              f"| {'yes' if r.crs_ok else 'NO'} | {fmt_extent(r.extent)} "
              f"| {'yes' if r.intersects else 'NO'} | {r.note} |")
    print()


# --------------------------------------------------------------------------- styling
def style_rgb(layer: QgsRasterLayer, lo: list[float], hi: list[float],
              opacity: float = 1.0) -> None:
    """Bands 1-3 as RGB with the same linear stretch lo..hi (DN) for every layer."""
    prov = layer.dataProvider()
    ren = QgsMultiBandColorRenderer(prov, 1, 2, 3)
    setters = (ren.setRedContrastEnhancement, ren.setGreenContrastEnhancement,
               ren.setBlueContrastEnhancement)
    for band, setter in enumerate(setters, start=1):
        ce = QgsContrastEnhancement(prov.dataType(band))
        ce.setContrastEnhancementAlgorithm(QgsContrastEnhancement.StretchToMinimumMaximum)
        ce.setMinimumValue(lo[band - 1])
        ce.setMaximumValue(hi[band - 1])
        setter(ce)
    ren.setOpacity(opacity)
    layer.setRenderer(ren)


def style_outline(layer: QgsVectorLayer, rgb: tuple[int, int, int], width_mm: float,
                  dashed: bool = False) -> None:
    """Unfilled polygons with a coloured outline."""
    sym = QgsFillSymbol.createSimple({
        "color": "0,0,0,0", "style": "no",
        "outline_color": ",".join(map(str, rgb)), "outline_width": str(width_mm),
        "outline_width_unit": "MM", "outline_style": "dash" if dashed else "solid",
        "joinstyle": "miter",
    })
    layer.setRenderer(QgsSingleSymbolRenderer(sym))


def label_layer(layer: QgsVectorLayer, field: str, rgb: tuple[int, int, int],
                size_pt: float = 9.0) -> None:
    """Simple labels of ``field`` with a dark halo."""
    fmt = QgsTextFormat()
    fmt.setFont(QFont("DejaVu Sans"))
    fmt.setSize(size_pt)
    fmt.setColor(QColor(*rgb))
    buf = QgsTextBufferSettings()
    buf.setEnabled(True)
    buf.setSize(0.8)
    buf.setColor(QColor(0, 0, 0))
    fmt.setBuffer(buf)
    pal = QgsPalLayerSettings()
    pal.fieldName = field
    pal.setFormat(fmt)
    pal.placement = QgsPalLayerSettings.Horizontal  # along the polygon's interior
    pal.centroidInside = True
    layer.setLabeling(QgsVectorLayerSimpleLabeling(pal))
    layer.setLabelsEnabled(True)


# --------------------------------------------------------------------------- pixels
def read_rgb(path: Path, xoff: int = 0, yoff: int = 0, xsize: int | None = None,
             ysize: int | None = None) -> np.ndarray:
    """Bands 1-3 of a GeoTIFF window as float64 (3, rows, cols), masked pixels NaN."""
    ds = gdal.Open(str(path))
    xsize = ds.RasterXSize if xsize is None else xsize
    ysize = ds.RasterYSize if ysize is None else ysize
    out = np.empty((3, ysize, xsize))
    for i in range(3):
        band = ds.GetRasterBand(i + 1)
        out[i] = band.ReadAsArray(xoff, yoff, xsize, ysize).astype(np.float64)
        mask = band.GetMaskBand().ReadAsArray(xoff, yoff, xsize, ysize)
        out[i][mask == 0] = np.nan
    return out


def stretch_limits(*stacks: np.ndarray) -> tuple[list[float], list[float]]:
    """One linear stretch for all bands (keeps colour balance), DN.

    Low = the smallest per-band 0.5th percentile, high = the largest per-band 99.5th
    percentile over all given stacks (valid pixels only); the same for R, G and B.
    """
    lo, hi = [], []
    for b in range(3):
        vals = np.concatenate([s[b][np.isfinite(s[b])].ravel() for s in stacks])
        lo.append(float(np.percentile(vals, 0.5)))
        hi.append(float(np.percentile(vals, 99.5)))
    return [min(lo)] * 3, [max(hi)] * 3


def luma(rgb: np.ndarray) -> np.ndarray:
    """BT.601 luma of a (3, rows, cols) stack; NaN replaced by the mean."""
    y = 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]
    return np.where(np.isfinite(y), y, np.nanmean(y))


def phase_correlation_shift(ref: np.ndarray, mov: np.ndarray,
                            upsample: int = 20) -> tuple[float, float, float]:
    """Sub-pixel translation d with mov(p) ~ ref(p - d), by phase correlation.

    Parameters
    ----------
    ref, mov : (rows, cols) arrays of the same shape.
    upsample : int
        Refinement factor: the correlation peak is located to 1/upsample px by a
        matrix DFT around the integer peak.

    Returns
    -------
    (drow_px, dcol_px, peak_ratio) : shift in pixels (row down, col right) and the
    correlation peak height divided by the largest value away from it (a clear
    peak is > 2).
    """
    rows, cols = ref.shape
    win = np.outer(np.hanning(rows), np.hanning(cols))
    fa = np.fft.fft2((ref - ref.mean()) * win)
    fb = np.fft.fft2((mov - mov.mean()) * win)
    cross = fb * np.conj(fa)
    cross /= np.abs(cross) + 1e-12
    ky = np.fft.fftfreq(rows)[:, None]
    kx = np.fft.fftfreq(cols)[None, :]
    cross *= np.exp(-((ky ** 2 + kx ** 2) / (2 * 0.2 ** 2)))  # damp noisy high frequencies
    corr = np.fft.ifft2(cross).real
    r0, c0 = np.unravel_index(np.argmax(corr), corr.shape)
    peak = corr[r0, c0]
    away = corr.copy()
    for dr in range(-2, 3):
        for dc in range(-2, 3):
            away[(r0 + dr) % rows, (c0 + dc) % cols] = -np.inf
    ratio = float(peak / max(away.max(), 1e-12))
    r0 = r0 - rows if r0 > rows // 2 else r0
    c0 = c0 - cols if c0 > cols // 2 else c0
    # matrix-DFT refinement on a +-1 px neighbourhood of the integer peak
    offs = np.arange(-upsample, upsample + 1) / upsample
    dr = r0 + offs
    dc = c0 + offs
    er = np.exp(2j * np.pi * dr[:, None] * np.fft.fftfreq(rows)[None, :])  # (n, rows)
    ec = np.exp(2j * np.pi * np.fft.fftfreq(cols)[:, None] * dc[None, :])  # (cols, n)
    fine = (er @ cross @ ec).real
    i, j = np.unravel_index(np.argmax(fine), fine.shape)
    return float(dr[i]), float(dc[j]), ratio


def measure_offset(sat_path: Path, deg_path: Path) -> dict:
    """Offset of the satellite relative to the degraded tile on the same 0.5 m grid.

    Returns dx_m (east), dy_m (north): a feature at p in the degraded tile appears at
    p + (dx_m, dy_m) in the satellite; plus the same in pixels and the peak ratio.
    """
    sat = gdal.Open(str(sat_path))
    deg = gdal.Open(str(deg_path))
    gs, gd = sat.GetGeoTransform(), deg.GetGeoTransform()
    col = (gd[0] - gs[0]) / gs[1]
    row = (gd[3] - gs[3]) / gs[5]
    if abs(gd[1] - gs[1]) > 1e-9 or abs(col - round(col)) > 1e-6 or abs(row - round(row)) > 1e-6:
        raise CheckFailed(f"{deg_path} is not on the satellite's 0.5 m pixel grid "
                          f"(origin at satellite col {col:.4f}, row {row:.4f}, pixel "
                          f"{gd[1]} m vs {gs[1]} m)")
    d = read_rgb(deg_path)
    s = read_rgb(sat_path, int(round(col)), int(round(row)), deg.RasterXSize, deg.RasterYSize)
    drow, dcol, ratio = phase_correlation_shift(luma(d), luma(s))
    return {"dx_px": dcol, "dy_px": -drow, "dx_m": dcol * gs[1], "dy_m": drow * gs[5],
            "peak_ratio": ratio, "sat_px_m": gs[1]}


# --------------------------------------------------------------------------- render
def render(layers: list, extent: QgsRectangle, crs: QgsCoordinateReferenceSystem,
           size_px: tuple[int, int]) -> QImage:
    """Render ``layers`` (top first) headlessly to an image of size_px (w, h)."""
    ms = QgsMapSettings()
    ms.setLayers(layers)
    ms.setDestinationCrs(crs)
    ms.setOutputSize(QSize(*size_px))
    ms.setOutputDpi(96)
    ms.setBackgroundColor(QColor(235, 235, 235))
    ms.setExtent(extent)
    job = QgsMapRendererParallelJob(ms)
    job.start()
    job.waitForFinished()
    errors = job.errors()
    if errors:
        msgs = "; ".join(f"{e.layerID}: {e.message}" for e in errors)
        raise CheckFailed(f"QGIS reported rendering errors: {msgs}")
    return job.renderedImage()


def world_to_px(extent: QgsRectangle, size: tuple[int, int], x: float, y: float) -> QPointF:
    """Map coordinates (m) -> pixel position in an image rendered for ``extent``."""
    w, h = size
    return QPointF((x - extent.xMinimum()) / extent.width() * w,
                   (extent.yMaximum() - y) / extent.height() * h)


def draw_scale_bar(p: QPainter, x: float, y: float, px_per_m: float, length_m: float) -> None:
    """Black/white scale bar with its length in metres, left end at (x, y)."""
    w = length_m * px_per_m
    p.setPen(QPen(QColor(0, 0, 0), 1))
    for k in range(int(length_m)):
        p.fillRect(QRectF(x + k * px_per_m, y, px_per_m, 6),
                   QColor(0, 0, 0) if k % 2 == 0 else QColor(255, 255, 255))
    p.drawRect(QRectF(x, y, w, 6))
    p.setFont(QFont("DejaVu Sans", 9))
    p.drawText(QPointF(x + w + 6, y + 7), f"{length_m:g} m")


def compose(panels: list[tuple[QImage, str]], header: list[str], legend: list[tuple],
            px_per_m: float, width_total: int | None = None) -> QImage:
    """Panels side by side under a text header, with a legend and scale bar below."""
    gap = 8
    head_h = 18 * len(header) + 10
    foot_h = 30
    w = sum(img.width() for img, _ in panels) + gap * (len(panels) + 1)
    w = max(w, width_total or 0)
    ph = max(img.height() for img, _ in panels)
    cap_h = 20 if any(c for _, c in panels) else 0
    out = QImage(w, head_h + cap_h + ph + foot_h + gap, QImage.Format_RGB32)
    out.fill(QColor(255, 255, 255))
    p = QPainter(out)
    p.setRenderHint(QPainter.Antialiasing, True)
    p.setRenderHint(QPainter.TextAntialiasing, True)
    p.setPen(QColor(0, 0, 0))
    for i, line in enumerate(header):
        p.setFont(QFont("DejaVu Sans", 11 if i == 0 else 9, QFont.Bold if i == 0 else -1))
        p.drawText(QPointF(gap, 18 + 18 * i), line)
    x = gap
    for img, caption in panels:
        if caption:
            p.setFont(QFont("DejaVu Sans", 9, QFont.Bold))
            p.drawText(QPointF(x, head_h + 14), caption)
        p.drawImage(QPointF(x, head_h + cap_h), img)
        x += img.width() + gap
    y = head_h + cap_h + ph + 12
    lx = gap
    p.setFont(QFont("DejaVu Sans", 9))
    for rgb, text, dashed in legend:
        pen = QPen(QColor(*rgb), 3)
        if dashed:
            pen.setStyle(Qt.DashLine)
        p.setPen(pen)
        p.fillRect(QRectF(lx, y, 16, 10), QColor(110, 110, 110))
        p.drawRect(QRectF(lx, y, 16, 10))
        p.setPen(QColor(0, 0, 0))
        p.drawText(QPointF(lx + 22, y + 10), text)
        lx += 30 + p.fontMetrics().horizontalAdvance(text)
    draw_scale_bar(p, max(lx + 10, w - 5 * px_per_m - 60), y + 2, px_per_m, 5)
    p.end()
    return out


def draw_grid(img: QImage, extent: QgsRectangle, step_m: float,
              rgb: tuple[int, int, int] = (255, 255, 255)) -> None:
    """Thin reference lines every ``step_m`` of easting/northing, in place."""
    p = QPainter(img)
    p.setPen(QPen(QColor(*rgb, 170), 1, Qt.DotLine))
    size = (img.width(), img.height())
    x = math.ceil(extent.xMinimum() / step_m) * step_m
    while x <= extent.xMaximum():
        a = world_to_px(extent, size, x, extent.yMaximum())
        b = world_to_px(extent, size, x, extent.yMinimum())
        p.drawLine(a, b)
        x += step_m
    y = math.ceil(extent.yMinimum() / step_m) * step_m
    while y <= extent.yMaximum():
        a = world_to_px(extent, size, extent.xMinimum(), y)
        b = world_to_px(extent, size, extent.xMaximum(), y)
        p.drawLine(a, b)
        y += step_m
    p.end()


def draw_rect(img: QImage, extent: QgsRectangle, rect: QgsRectangle,
              rgb: tuple[int, int, int], dashed: bool) -> None:
    """Outline of the map rectangle ``rect`` (m) on an image rendered for ``extent``."""
    size = (img.width(), img.height())
    a = world_to_px(extent, size, rect.xMinimum(), rect.yMaximum())
    b = world_to_px(extent, size, rect.xMaximum(), rect.yMinimum())
    p = QPainter(img)
    p.setRenderHint(QPainter.Antialiasing, True)
    pen = QPen(QColor(*rgb), 2)
    if dashed:
        pen.setStyle(Qt.DashLine)
    p.setPen(pen)
    p.drawRect(QRectF(a, b))
    p.end()


def save_png(img: QImage, path: Path, max_kb: float) -> tuple[int, str]:
    """Save ``img`` as PNG below max_kb: full colour, else a 256-colour palette, else smaller.

    Returns (bytes written, how it was stored).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    attempts = [("RGB", img),
                ("256-colour palette", img.convertToFormat(QImage.Format_Indexed8,
                                                            Qt.DiffuseDither))]
    for scale in (0.85, 0.7, 0.55):
        small = img.scaledToWidth(int(img.width() * scale), Qt.SmoothTransformation)
        attempts.append((f"palette, scaled x{scale}",
                         small.convertToFormat(QImage.Format_Indexed8, Qt.DiffuseDither)))
    stored = ""
    for label, candidate in attempts:
        if not candidate.save(str(tmp), "PNG", 9):
            raise CheckFailed(f"could not write {tmp}: check the folder is writable")
        size, stored = tmp.stat().st_size, label
        if size <= max_kb * 1024:
            break
    os.replace(tmp, path)
    return size, stored


# --------------------------------------------------------------------------- main
def pick_tile(index: QgsVectorLayer, cattle: QgsVectorLayer, tile: str | None) -> str:
    """The requested tile id, or the tile holding most of the (filtered) cattle boxes."""
    ids = [f["tile_id"] for f in index.getFeatures()]
    if not ids:
        raise CheckFailed(f"{index.source()} has no tiles: nothing to show")
    if tile is not None:
        if tile not in ids:
            raise CheckFailed(f"tile {tile!r} is not in {index.source()} (tiles: "
                              f"{', '.join(sorted(ids))})")
        return tile
    counts = {}
    boxes = [f.geometry() for f in cattle.getFeatures()] if cattle.isValid() else []
    for f in index.getFeatures():
        g = f.geometry()
        counts[f["tile_id"]] = sum(1 for b in boxes if g.contains(b.centroid()))
    return max(sorted(counts), key=lambda t: counts[t])


def main(argv: list[str] | None = None) -> int:
    """Run the checks and render; return the exit status."""
    args = parse_args(argv)
    run = args.run_dir.resolve()
    out2 = args.out2 or default_out2(args.out_png)
    grid = read_json(require(run / "grid" / "grid.json", "grid description"))
    site_crs_name = grid.get("crs") or f"EPSG:{grid.get('crs_epsg')}"
    alignment = read_json(run / "alignment.json") if (run / "alignment.json").exists() else {}
    run_info = read_json(run / "run.json") if (run / "run.json").exists() else {}
    flight = args.flight or alignment.get("reference")
    if flight is None:
        flights = sorted(p.name for p in (run / "tiles").iterdir() if p.is_dir()) \
            if (run / "tiles").is_dir() else []
        if not flights:
            print(f"qgis_overlay: no flights under {run / 'tiles'}", file=sys.stderr)
            return 2
        flight = flights[0]
    paddocks = args.paddocks or (Path(run_info["site"]["paddocks"])
                                 if run_info.get("site", {}).get("paddocks") else None)
    sat_path = require(run / "grid" / "satellite.tif", "satellite on the grid")
    index_path = require(run / "tiles" / "index.geojson", "tile index")
    cattle_path = require(run / "labels" / "cattle.geojson", "cattle labels")
    if paddocks is not None:
        require(paddocks, "paddocks file")

    qgs = QgsApplication([], False)
    QgsApplication.setPrefixPath(os.environ.get("QGIS_PREFIX_PATH", "/usr"), True)
    qgs.initQgis()
    try:
        return _run(args, run, out2, site_crs_name, flight, paddocks, sat_path,
                    index_path, cattle_path, run_info)
    except CheckFailed as exc:
        print(f"qgis_overlay: FAILED: {exc}", file=sys.stderr)
        return 1
    finally:
        QgsProject.instance().clear()
        qgs.exitQgis()


def _run(args, run: Path, out2: Path, site_crs_name: str, flight: str,
         paddocks: Path | None, sat_path: Path, index_path: Path, cattle_path: Path,
         run_info: dict) -> int:
    """Load, check, measure and render (see the module docstring); 0 when all is well."""
    site_info = run_info.get("site", {})
    title = args.title or site_info.get("name") or run.name
    when_uav = next((f.get("acquired", "")[:16].replace("T", " ")
                     for f in site_info.get("flights", []) if f.get("id") == flight), "")
    when_sat = (site_info.get("satellite") or {}).get("acquired", "")[:16].replace("T", " ")
    project_crs = QgsCoordinateReferenceSystem(site_crs_name)
    if not project_crs.isValid():
        raise CheckFailed(f"grid/grid.json names CRS {site_crs_name!r}, which QGIS "
                          "does not know")
    QgsProject.instance().setCrs(project_crs)

    sat = raster_layer(sat_path, "satellite (grid)")
    index = vector_layer(index_path, "tile index")
    cattle = vector_layer(cattle_path, f"cattle {flight}",
                          subset=f"\"flight\" = '{flight}'")
    tile_id = pick_tile(index, cattle, args.tile) if index.isValid() else None
    if tile_id is None:
        raise CheckFailed(f"{index_path} is not a readable vector file")
    uav_path = require(run / "tiles" / flight / f"{tile_id}.tif", "UAV tile")
    deg_path = require(run / "degraded" / flight / f"{tile_id}.tif", "degraded tile")
    uav = raster_layer(uav_path, f"UAV tile {flight}/{tile_id}")
    deg = raster_layer(deg_path, f"degraded {flight}/{tile_id}")
    pad = vector_layer(paddocks, "paddocks") if paddocks is not None else None

    sat_check = check_layer(sat, "satellite grid/satellite.tif", sat_path, site_crs_name,
                            project_crs, None)
    area = sat_check.extent
    rows = [sat_check,
            check_layer(uav, f"UAV tiles/{flight}/{tile_id}.tif", uav_path, site_crs_name,
                        project_crs, area),
            check_layer(deg, f"degraded/{flight}/{tile_id}.tif", deg_path, site_crs_name,
                        project_crs, area),
            check_layer(cattle, f"labels/cattle.geojson ({flight})", cattle_path,
                        GEOJSON_CRS, project_crs, area),
            check_layer(index, "tiles/index.geojson", index_path, GEOJSON_CRS,
                        project_crs, area)]
    if pad is not None:
        rows.append(check_layer(pad, f"paddocks {paddocks.name}", paddocks, None,
                                project_crs, area))
    layers_by_row = [sat, uav, deg, cattle, index] + ([pad] if pad is not None else [])
    problems = []
    for r, lyr in zip(rows, layers_by_row, strict=True):
        if r.valid and isinstance(lyr, QgsVectorLayer):
            r.note = f"{lyr.featureCount()} features"
        if not r.valid:
            problems.append(f"{r.path}: QGIS cannot open it as a layer (isValid() is False)")
        elif not r.crs_ok:
            problems.append(f"{r.path}: CRS is {r.crs or 'missing'}, expected {r.expected_crs}")
        elif not r.intersects:
            problems.append(f"{r.path}: extent {fmt_extent(r.extent)} (m, {site_crs_name}) "
                            "does not intersect the satellite scene "
                            f"{fmt_extent(area)}: misplaced")

    # the tile trio must cover exactly the same ground, as the tile index says
    tile_ext = rows[1].extent
    if rows[1].crs_ok and rows[2].crs_ok and rows[4].crs_ok:
        d = max_corner_diff(tile_ext, rows[2].extent)
        rows[2].note = f"bounds differ from the UAV tile by {d:.2e} m"
        if d > 1e-3:
            problems.append(f"{deg_path}: covers {fmt_extent(rows[2].extent)}, the UAV tile "
                            f"{fmt_extent(tile_ext)} (differ by {d:.3f} m): misplaced")
        feats = list(index.getFeatures(QgsFeatureRequest().setFilterExpression(
            f"\"tile_id\" = '{tile_id}'")))
        if len(feats) != 1:
            problems.append(f"{index_path}: {len(feats)} features with tile_id {tile_id}, "
                            "expected 1")
        else:
            xf = QgsCoordinateTransform(index.crs(), project_crs, QgsProject.instance())
            g = QgsGeometry(feats[0].geometry())
            g.transform(xf)
            bb = g.boundingBox()
            di = max_corner_diff(bb, tile_ext)
            rows[4].note += f"; {tile_id} polygon vs UAV tile bounds: {di:.4f} m"
            if di > 0.01:
                problems.append(f"{index_path}: polygon of {tile_id} has bounds "
                                f"{fmt_extent(bb)}, the tile raster {fmt_extent(tile_ext)} "
                                f"(differ by {di:.3f} m): misplaced")
        n_in = sum(1 for f in cattle.getFeatures()
                   if tile_ext.contains(extent_point(f.geometry(), cattle, project_crs)))
        rows[3].note += f"; {n_in} centred in {tile_id}"

    print(f"run: {run}\nsite CRS (project CRS): {site_crs_name}; flight {flight}, "
          f"tile {tile_id}")
    print_table(rows, site_crs_name)
    if problems:
        raise CheckFailed("\n  " + "\n  ".join(problems))

    offset = measure_offset(sat_path, deg_path)
    mag = math.hypot(offset["dx_m"], offset["dy_m"])
    clear = offset["peak_ratio"] > 1.5
    print(f"offset satellite - degraded tile {flight}/{tile_id}: dx = {offset['dx_m']:+.2f} m "
          f"east, dy = {offset['dy_m']:+.2f} m north (|d| = {mag:.2f} m = "
          f"{mag / offset['sat_px_m']:.1f} satellite px; peak ratio "
          f"{offset['peak_ratio']:.1f}{'' if clear else ', NOT a clear peak'})")
    if clear and mag > args.max_offset_m:
        raise CheckFailed(f"{deg_path} and {sat_path} are offset by {mag:.2f} m "
                          f"(> --max-offset-m {args.max_offset_m}): misplaced")

    # ---------------------------------------------------------------- styles
    uav_px = read_rgb(uav_path)
    deg_px = read_rgb(deg_path)
    lo, hi = stretch_limits(uav_px, deg_px)
    for lyr in (sat, uav, deg):
        style_rgb(lyr, lo, hi)
    style_outline(cattle, CATTLE_RGB, 0.5)
    style_outline(index, TILE_RGB, 0.5, dashed=True)
    label_layer(index, "tile_id", TILE_RGB, 8)
    if pad is not None:
        style_outline(pad, PADDOCK_RGB, 0.7)
        label_layer(pad, "name", PADDOCK_RGB, 9)

    off_txt = (f"measured offset satellite - tile: {offset['dx_m']:+.2f} m E, "
               f"{offset['dy_m']:+.2f} m N ({mag:.2f} m)")

    # ---------------------------------------------------------------- picture 1
    m = args.margin_m
    ext1 = QgsRectangle(tile_ext.xMinimum() - m, tile_ext.yMinimum() - m,
                        tile_ext.xMaximum() + m, tile_ext.yMaximum() + m)
    px_per_m = 20.0
    size1 = (int(round(ext1.width() * px_per_m)), int(round(ext1.height() * px_per_m)))
    top = [index, cattle] + ([pad] if pad is not None else []) + [uav, sat]
    img1 = render(top, ext1, project_crs, size1)
    header1 = [f"{title}: UAV tile {flight}/{tile_id} (0.05 m) over the satellite (0.5 m)",
               f"QGIS {Qgis.QGIS_VERSION.split('-')[0]}, {site_crs_name}; {off_txt}"]
    legend1 = [(CATTLE_RGB, f"cattle labels {flight}", False),
               (PADDOCK_RGB, "paddock boundaries", False),
               (TILE_RGB, "tiles/index.geojson", True)]
    pic1 = compose([(img1, "")], header1, legend1, px_per_m)
    n1, how1 = save_png(pic1, args.out_png, args.max_kb)
    print(f"wrote {args.out_png} ({pic1.width()}x{pic1.height()} px, {n1 / 1024:.0f} KiB, {how1})")

    # ---------------------------------------------------------------- picture 2
    m2 = 2.0
    ext2 = QgsRectangle(tile_ext.xMinimum() - m2, tile_ext.yMinimum() - m2,
                        tile_ext.xMaximum() + m2, tile_ext.yMaximum() + m2)
    px2 = 14.0
    size2 = (int(round(ext2.width() * px2)), int(round(ext2.height() * px2)))
    panel_a = render([cattle, deg], ext2, project_crs, size2)
    panel_b = render([cattle, sat], ext2, project_crs, size2)
    sat_half = sat.clone()
    style_rgb(sat_half, lo, hi, opacity=0.5)
    QgsProject.instance().addMapLayer(sat_half, False)
    panel_c = render([cattle, sat_half, deg], ext2, project_crs, size2)
    moved = QgsRectangle(tile_ext)
    moved.setXMinimum(tile_ext.xMinimum() + offset["dx_m"])
    moved.setXMaximum(tile_ext.xMaximum() + offset["dx_m"])
    moved.setYMinimum(tile_ext.yMinimum() + offset["dy_m"])
    moved.setYMaximum(tile_ext.yMaximum() + offset["dy_m"])
    for img in (panel_a, panel_b, panel_c):
        draw_grid(img, ext2, 5.0)
    for img in (panel_b, panel_c):
        draw_rect(img, ext2, tile_ext, (255, 255, 255), dashed=False)
        draw_rect(img, ext2, moved, OFFSET_RGB, dashed=True)
    header2 = [f"{title}: degraded tile {flight}/{tile_id} vs the satellite, same 0.5 m "
               "grid and extent (QGIS)",
               f"{off_txt}; dotted lines every 5 m of {site_crs_name}",
               f"UAV {when_uav}, satellite {when_sat}: sun and cattle differ, compare "
               "ground patches, crowns, fences"]
    legend2 = [(CATTLE_RGB, f"cattle labels {flight}", False),
               ((255, 255, 255), "tile", False),
               (OFFSET_RGB, "tile moved by the measured offset", True)]
    q = gdal.Open(str(deg_path)).GetMetadataItem("GEOSIM_Q")
    q_txt = f", Q = {float(q):.2f}" if q else ""
    pic2 = compose([(panel_a, f"degraded {flight}/{tile_id}{q_txt}"),
                    (panel_b, "satellite grid/satellite.tif"),
                    (panel_c, "satellite at 50 % over degraded")],
                   header2, legend2, px2)
    n2, how2 = save_png(pic2, out2, args.max_kb)
    print(f"wrote {out2} ({pic2.width()}x{pic2.height()} px, {n2 / 1024:.0f} KiB, {how2})")
    print("all checks passed")
    return 0


def extent_point(geom: QgsGeometry, layer: QgsVectorLayer,
                 dest: QgsCoordinateReferenceSystem):
    """Centroid of ``geom`` (in ``layer``'s CRS) as a point in ``dest``."""
    c = geom.centroid().asPoint()
    if layer.crs() == dest:
        return c
    return QgsCoordinateTransform(layer.crs(), dest, QgsProject.instance()).transform(c)


if __name__ == "__main__":
    sys.exit(main())
