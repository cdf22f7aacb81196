"""``geosim run`` and ``geosim demo``: the whole pipeline on a site."""

from __future__ import annotations

from pathlib import Path

import click

from geosim.config import load_site
from geosim.pipeline import STEP_NAMES, format_summary, run_pipeline
from geosim.samples_location import bundled_site

_ONLY = click.option("--only", "only", multiple=True, type=click.Choice(STEP_NAMES),
                     help="Run only these steps (repeatable); earlier outputs must exist.")


def _run(site_path: Path, out: Path, only: tuple[str, ...]) -> None:
    site = load_site(site_path)  # validated before anything is written
    record = run_pipeline(site, out, only=only or None,
                          echo=lambda s: click.echo(s, err=True))
    click.echo(format_summary(record))
    click.echo(f"outputs in {out}/ (run.json records inputs, parameters and timings)")


@click.command()
@click.argument("site_file", type=click.Path(path_type=Path))
@click.option("--out", "out", required=True, type=click.Path(path_type=Path),
              help="Output folder (created if needed).")
@_ONLY
def run(site_file: Path, out: Path, only: tuple[str, ...]) -> None:
    """Run the whole pipeline on SITE_FILE (a site TOML) into --out."""
    _run(site_file, out, only)


@click.command()
@click.option("--out", "out", default=Path("demo_out"), show_default=True,
              type=click.Path(path_type=Path), help="Output folder (created if needed).")
@_ONLY
def demo(out: Path, only: tuple[str, ...]) -> None:
    """Run the whole pipeline on the bundled sample site."""
    site_path = bundled_site(out / "sample_site", echo=lambda s: click.echo(s, err=True))
    click.echo(f"sample site: {site_path}", err=True)
    _run(site_path, out, only)
    comparison = out / "diagnosis" / "truth_comparison.txt"
    if comparison.is_file():  # the sample site ships its truth: show what diagnose found
        click.echo("\ndiagnosis of the sample satellite scene, fitted vs truth.json:")
        click.echo(comparison.read_text().rstrip())
