"""``geosim diagnose``: name the physics the paper's model leaves out."""

from __future__ import annotations

from pathlib import Path

import click

from geosim.cli.common import engine_options
from geosim.errors import ConfigError


@click.command()
@engine_options
@click.argument("site_file", required=False, type=click.Path(path_type=Path))
@click.option("--uav", "uav", multiple=True, type=click.Path(path_type=Path),
              help="UAV orthomosaic GeoTIFF (any CRS); repeatable. Every one that overlaps the "
                   "satellite is diagnosed; the first is the reference.")
@click.option("--satellite", "satellite", type=click.Path(path_type=Path),
              help="Real satellite scene GeoTIFF (any CRS).")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output folder (with SITE_FILE: the run folder; diagnosis/ is written in it).")
@click.option("--uav-gsd", "uav_gsd_m", default=0.05, show_default=True, type=float,
              help="UAV grid pixel size, metres (standalone mode).")
@click.option("--sat-gsd", "sat_gsd_m", default=0.5, show_default=True, type=float,
              help="Satellite grid pixel size, metres (standalone mode).")
@click.option("--dpi", default=100, show_default=True, type=click.IntRange(min=10, max=1200),
              help="Resolution of the diagnosis figures (PNG dots per inch; their pixel size "
                   "scales with it).")
@click.option("--seed", default=0, show_default=True, type=int,
              help="Seed of the noise realisation in the refined simulation.")
def diagnose(site_file: Path | None, uav: tuple[Path, ...], satellite: Path | None, out: Path,
             uav_gsd_m: float, sat_gsd_m: float, dpi: int, seed: int) -> None:
    """Locate where simulation and the real satellite scene differ, name the missing physics,
    model it and refit.

    Either SITE_FILE (a run folder --out made by `geosim run` must exist) or
    --uav ... --satellite ... (standalone).
    """
    if site_file is not None:
        if uav or satellite:
            raise ConfigError("give either SITE_FILE or --uav/--satellite, not both")
        from geosim.cli.common import run_steps

        record = run_steps(site_file, out, ("diagnose",), satellite_required=True,
                           options={"diagnose": {"dpi": dpi}})
        summary = record["steps"]["diagnose"]["summary"]
    else:
        if not uav or satellite is None:
            raise ConfigError("geosim diagnose needs SITE_FILE or at least one --uav and "
                              "--satellite; see geosim diagnose --help")
        from geosim.config import site_from_images
        from geosim.pipeline import format_summary, run_pipeline

        # tile_px is not used here; a multiple of φ keeps the site valid for any whole φ
        site = site_from_images(list(uav), satellite, uav_gsd_m=uav_gsd_m, sat_gsd_m=sat_gsd_m,
                                tile_px=max(1, round(sat_gsd_m / uav_gsd_m)) * 500)
        record = run_pipeline(site, out, only=["diagnose_images"],
                              options={"diagnose_images": {"seed": seed, "dpi": dpi}})
        click.echo(format_summary(record))
        summary = record["steps"]["diagnose_images"]["summary"]
    flights = summary.get("flights", {})
    if len(flights) > 1:
        click.echo(f"{len(flights)} flights diagnosed; combined (majority) verdict:")
    click.echo(f"baseline Q {summary['q_base']:.2f} -> refined Q {summary['q_refined']:.2f}")
    for name, params in summary["effects"].items():
        click.echo(f"  {name}: {params}")
    click.echo(f"RMSE {summary['rmse'][0]:.2f} -> {summary['rmse'][1]:.2f} DN; spectral error "
               f"{summary['spectral_error'][0]:.3f} -> {summary['spectral_error'][1]:.3f}")
    if len(flights) > 1:
        for f, d in flights.items():
            click.echo(f"  flight {f}: Q {d['q_base']:.2f} -> {d['q_refined']:.2f}; claimed "
                       + (", ".join(d["claimed"]) or "none"))
    for f, why in summary.get("flights_skipped", {}).items():
        click.echo(f"  flight {f} skipped: {why}")
    click.echo(f"outputs in {summary['out']}/ (diagnosis.json, report.md; per flight in "
               "<flight>/)")
