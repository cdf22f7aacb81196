"""Files of the overlay check: overlay.json, overlay_arrows.geojson and one PNG per pair."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from geosim.io.atomic import atomic_path, write_json
from geosim.io.paths import safe_name
from geosim.overlay.check import OverlayResult, read_on_grid

#: Arrows in the GeoJSON and the PNG are drawn this many times longer than the shift.
ARROW_SCALE = 10.0


def arrows_geodataframe(results: Sequence[OverlayResult], *, arrow_scale: float = ARROW_SCALE):
    """One arrow (LineString, EPSG:4326) per measured window of every pair.

    Properties: ``pair``, ``dx_m``, ``dy_m`` (east, north), ``magnitude_m``,
    ``confidence``, ``confident`` and ``arrow_scale`` (the drawn length over the shift).
    """
    import geopandas as gpd
    from shapely.geometry import LineString

    frames = []
    for r in results:
        east, north = r.shifts_m()
        x, y = r.centres_xy()
        ok = np.isfinite(east)
        geoms = [LineString([(x0, y0), (x0 + arrow_scale * e, y0 + arrow_scale * n)])
                 for x0, y0, e, n in zip(x[ok], y[ok], east[ok], north[ok], strict=True)]
        if not geoms:
            continue
        frames.append(gpd.GeoDataFrame({
            "pair": r.name, "dx_m": east[ok], "dy_m": north[ok],
            "magnitude_m": np.hypot(east[ok], north[ok]),
            "confidence": r.field.confidence[ok], "confident": r.field.valid[ok],
            "arrow_scale": arrow_scale}, geometry=geoms, crs=r.grid.crs).to_crs("EPSG:4326"))
    if not frames:
        return gpd.GeoDataFrame({"pair": []}, geometry=[], crs="EPSG:4326")
    import pandas as pd

    return gpd.GeoDataFrame(pd.concat(frames, ignore_index=True), crs="EPSG:4326")


def nice_length(span_m: float) -> float:
    """A round scale-bar length (1, 2 or 5 × 10^k m) near a fifth of ``span_m``."""
    target = span_m / 5.0
    k = 10 ** np.floor(np.log10(target))
    return float(min((1, 2, 5, 10), key=lambda m: abs(m * k - target)) * k)


def plot_pair(result: OverlayResult, path: Path, *, dpi: int = 120,
              arrow_scale: float = ARROW_SCALE) -> Path:
    """PNG: b's image on the common grid with the shift arrows, map axes and a scale bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from geosim.io.raster import open_raster

    with open_raster(result.b, what="overlay raster b") as ds:
        on_grid = read_on_grid(ds, result.grid)
    grey, valid = on_grid.array[0], on_grid.valid
    t, (rows, cols) = on_grid.transform, on_grid.shape
    extent = (t.c, t.c + cols * t.a, t.f + rows * t.e, t.f)
    fig, ax = plt.subplots(figsize=(7, 7 * rows / cols + 0.6))
    ax.imshow(np.where(valid, grey, np.nan), cmap="gray", extent=extent, interpolation="nearest")
    east, north = result.shifts_m()
    x, y = result.centres_xy()
    ok = result.field.valid
    ax.quiver(x[ok], y[ok], east[ok], north[ok], color="yellow", angles="xy",
              scale_units="xy", scale=1.0 / arrow_scale, width=0.004)
    weak = np.isfinite(east) & ~ok
    ax.quiver(x[weak], y[weak], east[weak], north[weak], color="red", angles="xy",
              scale_units="xy", scale=1.0 / arrow_scale, width=0.003, alpha=0.6)
    s = result.summary()
    ms = s["median_shift_m"]
    head = (f"median shift {ms[0]:+.2f} m E, {ms[1]:+.2f} m N; p95 {s['p95_m']:.2f} m"
            if ms else "no confident window")
    ax.set_title(f"{result.name}\n{head} (arrows ×{arrow_scale:g}; red: low confidence)",
                 fontsize=9)
    crs = result.grid.crs.to_string()
    ax.set_xlabel(f"easting (m, {crs})")
    ax.set_ylabel(f"northing (m, {crs})")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    bar = nice_length(extent[1] - extent[0])
    ax.add_artist(AnchoredSizeBar(ax.transData, bar, f"{bar:g} m", "lower right", pad=0.4,
                                  color="white", frameon=False, size_vertical=bar / 30))
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    plt.close(fig)
    return path


def write_overlay_outputs(results: Sequence[OverlayResult], out_dir: Path, *,
                          max_shift_m: float | None = None, dpi: int = 120) -> dict:
    """Write ``overlay.json``, ``overlay_arrows.geojson`` and ``overlay_<pair>.png``.

    Returns the content of overlay.json; ``ok`` is False when a pair's median shift
    magnitude exceeds ``max_shift_m`` or no window was confident.
    """
    from geosim.io.vector import write_geojson

    pairs = []
    for r in results:
        s = r.summary()
        png = out_dir / f"overlay_{safe_name(r.name, default='pair')}.png"
        plot_pair(r, png, dpi=dpi)
        s["png"] = png.name
        mag = s["median_shift_magnitude_m"]
        s["ok"] = (mag is not None) and (max_shift_m is None or mag <= max_shift_m)
        pairs.append(s)
    write_geojson(arrows_geodataframe(results), out_dir / "overlay_arrows.geojson")
    doc = {"convention": "median_shift_m = [east, north] metres that carry a's content onto "
                         "b's (ground at (x, y) in a is at (x + dx, y + dy) in b); magnitudes "
                         "over confident windows",
           "max_shift_m": max_shift_m, "arrow_scale": ARROW_SCALE,
           "ok": all(p["ok"] for p in pairs), "pairs": pairs}
    write_json(out_dir / "overlay.json", doc)
    return doc


__all__ = ["ARROW_SCALE", "arrows_geodataframe", "plot_pair", "write_overlay_outputs"]
