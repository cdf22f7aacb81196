"""``geosim grid``, ``geosim align``, ``geosim tile`` and ``geosim prepare``.

Each parses ``SITE.toml --out DIR`` and runs the matching pipeline steps
(:mod:`geosim.prepare.steps`) through :func:`geosim.pipeline.run_pipeline`, so
``DIR/run.json`` records what ran.
"""

from __future__ import annotations

from pathlib import Path

import click

from geosim.cli.common import ANCHOR_OPTION, OUT_OPTION, SITE_ARG, engine_options, run_steps


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
def grid(site_file: Path, out: Path) -> None:
    """Reproject flights and satellite onto the shared grid; trace footprints.

    Writes DIR/grid/ (grid.json, <flight>.tif, satellite.tif), footprints.geojson
    and common_extent.geojson.
    """
    run_steps(site_file, out, ("grid", "footprints"))


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
@ANCHOR_OPTION
def align(site_file: Path, out: Path, anchor: str | None) -> None:
    """Register flights to the reference flight (needs 'geosim grid').

    Writes DIR/alignment.json (each flight's correction and composed warp) and
    alignment_check.geojson; DIR/aligned/<flight>.tif only with keep_intermediates = true.
    """
    run_steps(site_file, out, ("align",), anchor=anchor)


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
def tile(site_file: Path, out: Path) -> None:
    """Resample aligned tiles once from the flights and list patch pairs (needs 'geosim align').

    Writes DIR/tiles/<flight>/<tile_id>.tif, tiles/index.geojson and pairs.csv.
    """
    run_steps(site_file, out, ("tiles", "pairs"))


@click.command()
@engine_options
@SITE_ARG
@OUT_OPTION
@ANCHOR_OPTION
def prepare(site_file: Path, out: Path, anchor: str | None) -> None:
    """Grid, footprints, alignment, tiles and pairs in one go."""
    run_steps(site_file, out, ("grid", "footprints", "align", "tiles", "pairs"), anchor=anchor)
