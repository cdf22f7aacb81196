"""``geosim run`` and ``geosim demo``: the whole pipeline on a site."""

from __future__ import annotations

from pathlib import Path

import click

from geosim.cli.common import ANCHOR_OPTION, OUT_OPTION, SITE_ARG, engine_options, run_steps
from geosim.log import info as log_info
from geosim.pipeline import STEP_NAMES
from geosim.rundir import RunDir
from geosim.samples_location import bundled_site

_ONLY = click.option("--only", "only", multiple=True, type=click.Choice(STEP_NAMES),
                     help="Run only these steps (repeatable); earlier outputs must exist.")


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
@_ONLY
@ANCHOR_OPTION
def run(site_file: Path, out: Path, only: tuple[str, ...], anchor: str | None) -> None:
    """Run the whole pipeline on SITE_FILE (a site TOML) into --out."""
    run_steps(site_file, out, only, anchor=anchor)
    click.echo(f"outputs in {out}/ (run.json records inputs, parameters and timings)")


@click.command()
@engine_options
@click.option("--out", "out", default=Path("demo_out"), show_default=True,
              type=click.Path(path_type=Path), help="Output folder (created if needed).")
@_ONLY
@ANCHOR_OPTION
def demo(out: Path, only: tuple[str, ...], anchor: str | None) -> None:
    """Run the whole pipeline on the bundled sample site."""
    # beside --out, not in it: a run folder never holds its own inputs
    site_path = bundled_site(out.with_name(f"{out.name}_sample_site"))
    log_info(f"sample site: {site_path}")
    run_steps(site_path, out, only, anchor=anchor)
    click.echo(f"outputs in {out}/ (run.json records inputs, parameters and timings)")
    comparison = RunDir(out).diagnosis_dir / "truth_comparison.txt"
    if comparison.is_file():  # the sample site ships its truth: show what diagnose found
        click.echo("\ndiagnosis of the sample satellite scene, fitted vs truth.json:")
        click.echo(comparison.read_text().rstrip())
