"""``geosim overlay-check`` and ``geosim deliver``: parse, then call the library."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from geosim.cli.common import OUT_OPTION, SITE_ARG, run_steps


@click.command("overlay-check")
@click.argument("site_file", required=False, type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Run folder (with SITE_FILE), or where to write (with --a/--b).")
@click.option("--a", "a_path", type=click.Path(path_type=Path),
              help="First raster (any CRS); with --b instead of SITE_FILE.")
@click.option("--b", "b_path", type=click.Path(path_type=Path),
              help="Second raster (any CRS): shifts carry a's content onto b's.")
@click.option("--max-shift-m", type=click.FloatRange(min=0), default=None,
              help="Exit with status 1 when a pair's median shift is longer than this (m).")
@click.option("--window-px", type=click.IntRange(min=32), default=128, show_default=True,
              help="Phase-correlation window on the common grid (shrunk to fit 3 per side).")
@click.option("--gsd-m", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Pixel size of the common grid (default: the coarser raster's).")
@click.option("--dpi", type=click.IntRange(min=30), default=120, show_default=True,
              help="Resolution of the PNGs.")
def overlay_check(site_file: Path | None, out: Path, a_path: Path | None, b_path: Path | None,
                  max_shift_m: float | None, window_px: int, gsd_m: float | None,
                  dpi: int) -> None:
    """Check how well two rasters overlay: local shifts by phase correlation.

    With SITE_FILE: the satellite scene vs each flight's degraded mosaic in the run
    folder --out. With --a X.tif --b Y.tif: any two overlapping rasters in any CRS.
    Writes OUT/overlay.json (per pair: median_shift_m = [east, north] metres carrying
    a's content onto b's, median/p95/max magnitude, windows), OUT/overlay_arrows.geojson
    and OUT/overlay_<pair>.png.

    Example: geosim overlay-check site.toml --out run --max-shift-m 1
    """
    from geosim.config import load_site
    from geosim.errors import ConfigError
    from geosim.overlay import overlay_check as check
    from geosim.overlay import run_pairs
    from geosim.overlay.outputs import write_overlay_outputs

    if (a_path is None) != (b_path is None):
        raise ConfigError("overlay-check: give both --a and --b, or a SITE_FILE alone")
    if a_path is not None and site_file is not None:
        raise ConfigError("overlay-check: give either SITE_FILE or --a/--b, not both")
    if a_path is None and site_file is None:
        raise ConfigError("overlay-check: give a SITE_FILE (with its run folder --out) or "
                          "--a X.tif --b Y.tif")
    from geosim.record import command_record, record_path

    if site_file is not None:
        pairs = run_pairs(out, load_site(site_file).flight_ids)
    else:
        pairs = [(None, a_path, b_path)]
    # in a site's run folder the step record joins the pipeline's run.json
    inputs = {"site": site_file, **{f"{name or 'a_b'}.{k}": p for name, a, b in pairs
                                    for k, p in (("a", a), ("b", b))}}
    with command_record("overlay-check", record_path(out, folder=True), inputs=inputs,
                        options={"max_shift_m": max_shift_m, "window_px": window_px,
                                 "gsd_m": gsd_m, "dpi": dpi}) as rec:
        results = [check(a, b, name=name, window_px=window_px, gsd_m=gsd_m)
                   for name, a, b in pairs]
        doc = write_overlay_outputs(results, out, max_shift_m=max_shift_m, dpi=dpi)
        rec.summary = (f"{len(doc['pairs'])} pair(s), "
                       f"{'ok' if doc['ok'] else 'NOT OK (shift above --max-shift-m)'}")
    for p in doc["pairs"]:
        ms = p["median_shift_m"]
        mag = p["median_shift_magnitude_m"]
        shift = (f"median shift {ms[0]:+.3f} m E {ms[1]:+.3f} m N ({mag:.3f} m), "
                 f"p95 {p['p95_m']:.3f} m, {p['n_confident']}/{p['n_windows']} windows"
                 if ms else f"no confident window of {p['n_windows']}")
        click.echo(f"{p['name']}: {shift}{'' if p['ok'] else '  [NOT OK]'}")
    click.echo(f"wrote {out / 'overlay.json'}, overlay_arrows.geojson and "
               f"{len(doc['pairs'])} PNG(s)")
    if not doc["ok"]:
        sys.exit(1)


@click.command()
@SITE_ARG
@OUT_OPTION
def deliver(site_file: Path, out: Path) -> None:
    """VRT mosaics, STAC catalogue, YOLO datasets and a QGIS project for a run folder.

    Writes DIR/tiles/<flight>.vrt, DIR/degraded/<flight>.vrt, DIR/stac/catalog.json,
    DIR/yolo/ and DIR/yolo_0.5m/ (images/ and labels/ split by tile, data.yaml) and
    DIR/geosim.qgs.

    Example: geosim deliver site.toml --out run
    """
    run_steps(site_file, out, ["deliver"])
