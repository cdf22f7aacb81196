"""``geosim samples``: the bundled synthetic sample site."""

from __future__ import annotations

from pathlib import Path

import click


@click.group()
def samples() -> None:
    """The synthetic sample site (flights, satellite scene, labels, truth)."""


@samples.command("make")
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output folder (created if needed; files of the same names are replaced).")
@click.option("--seed", default=0, show_default=True, type=int,
              help="Seed of every random choice; 0 reproduces data/samples exactly.")
def make(out: Path, seed: int) -> None:
    """Generate the sample site into --out."""
    from geosim.samples.generate import make_sample_site

    summary = make_sample_site(out, seed=seed)
    cattle = ", ".join(f"{k} {v}" for k, v in summary["cattle_per_flight"].items())
    click.echo(f"sample site written to {out}/ in {summary['seconds']} s")
    click.echo(f"cattle per flight: {cattle}; satellite: {summary['satellite_cattle']}")
    click.echo("satellite effects: " + "; ".join(
        f"{name} {params}" for name, params in summary["satellite_effects"].items()))
    click.echo(f"truth: {out / 'truth.json'}; site file: {out / 'site.toml'}")
