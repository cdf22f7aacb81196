"""``geosim degrade`` and ``geosim calibrate``: parse and run the step through the runner."""

from __future__ import annotations

from pathlib import Path

import click

from geosim.cli.common import OUT_OPTION, SITE_ARG, engine_options, run_steps


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
@click.option("--q", "q", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Q = λf/(Dp) of the simulated optics (default: the mean calibrated Q "
                   "from DIR/calibration.json).")
@click.option("--method", type=click.Choice(["fast", "reference"]), default="fast",
              show_default=True,
              help="'reference' is literally the paper (full-resolution blur, then "
                   "cv2.resize bicubic); 'fast' gives the same numbers within 1 DN, reading "
                   "whole tiles at their first overview (the pyramid level it needs).")
def degrade(site_file: Path, out: Path, q: float | None, method: str) -> None:
    """Degrade every UAV tile to the satellite grid (needs 'geosim tile').

    Writes DIR/degraded/<flight>/<tile_id>.tif: the tile convolved with the Airy
    PSF of Q and downsampled bicubically by φ = sat_gsd / uav_gsd, with the
    tile's transform scaled by φ (same origin) and its valid mask.

    Example: geosim degrade site.toml --out run --q 4.34
    """
    run_steps(site_file, out, ("degrade",), options={"degrade": {"q": q, "method": method}})


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
def calibrate(site_file: Path, out: Path) -> None:
    """Calibrate Q against the satellite scene by Laplacian variance (needs 'geosim align').

    For each flight, over its common extent with the satellite, finds the Q
    whose degraded imagery has the satellite's Laplacian variance. Writes
    DIR/calibration.json (per-flight Q, LV curves, mean Q) and DIR/calibration.png.

    Example: geosim calibrate site.toml --out run
    """
    record = run_steps(site_file, out, ("calibrate",), satellite_required=True)
    summary = record["steps"]["calibrate"]["summary"]
    for fid, q in summary["q"].items():
        click.echo(f"  {fid:<12} Q = {q:6.3f}   satellite LV = {summary['lv_satellite'][fid]:.4g}")
    click.echo(f"wrote {out / 'calibration.json'} and {out / 'calibration.png'}")
