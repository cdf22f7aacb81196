"""``geosim grid``, ``geosim align``, ``geosim tile`` and ``geosim prepare``.

Each parses ``SITE.toml --out DIR`` and runs the matching pipeline steps
(:mod:`geosim.prepare.steps`) through :func:`geosim.pipeline.run_pipeline`, so
``DIR/run.json`` records what ran.
"""

from __future__ import annotations

from pathlib import Path

import click

from geosim.config import load_site
from geosim.pipeline import format_summary, run_pipeline

_SITE = click.argument("site_file", type=click.Path(path_type=Path))
_OUT = click.option("--out", "out", required=True, type=click.Path(path_type=Path),
                    help="Run folder (created if needed).")


def _run(site_file: Path, out: Path, steps: tuple[str, ...]) -> None:
    site = load_site(site_file)
    record = run_pipeline(site, out, only=steps, echo=lambda s: click.echo(s, err=True))
    click.echo(format_summary(record))


@click.command()
@_SITE
@_OUT
def grid(site_file: Path, out: Path) -> None:
    """Reproject flights and satellite onto the shared grid; trace footprints.

    Writes DIR/grid/ (grid.json, <flight>.tif, satellite.tif), footprints.geojson
    and common_extent.geojson.
    """
    _run(site_file, out, ("grid", "footprints"))


@click.command()
@_SITE
@_OUT
def align(site_file: Path, out: Path) -> None:
    """Register flights to the reference flight and resample them (needs 'geosim grid').

    Writes DIR/alignment.json, DIR/aligned/<flight>.tif and alignment_check.geojson.
    """
    _run(site_file, out, ("align",))


@click.command()
@_SITE
@_OUT
def tile(site_file: Path, out: Path) -> None:
    """Cut aligned flights into tiles and list patch pairs (needs 'geosim align').

    Writes DIR/tiles/<flight>/<tile_id>.tif, tiles/index.geojson and pairs.csv.
    """
    _run(site_file, out, ("tiles", "pairs"))


@click.command()
@_SITE
@_OUT
def prepare(site_file: Path, out: Path) -> None:
    """Grid, footprints, alignment, tiles and pairs in one go."""
    _run(site_file, out, ("grid", "footprints", "align", "tiles", "pairs"))
