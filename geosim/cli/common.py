"""Options and the one call shared by the commands that run pipeline steps."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click

from geosim.config import ANCHORS, load_site
from geosim.pipeline import format_summary, run_pipeline

SITE_ARG = click.argument("site_file", type=click.Path(path_type=Path))
OUT_OPTION = click.option("--out", "out", required=True, type=click.Path(path_type=Path),
                          help="Run folder (created if needed).")
ANCHOR_OPTION = click.option(
    "--anchor", type=click.Choice(ANCHORS), default=None,
    help="Frame of the aligned flights, overriding [site] anchor: the reference flight's "
         "georeference (the paper) or the satellite scene's.")


def run_steps(site_file: Path, out: Path, steps: Sequence[str] | None, *,
              anchor: str | None = None) -> dict[str, Any]:
    """Load and validate the site (before anything is written), run steps, print the summary.

    Parameters
    ----------
    site_file
        The site TOML.
    out
        Run folder.
    steps
        Step names, or None for the whole pipeline.
    anchor
        Overrides the site's ``anchor`` when given (validated like the site file's).
    """
    site = load_site(site_file)
    if anchor is not None:
        site = dataclasses.replace(site, anchor=anchor)
    record = run_pipeline(site, out, only=steps or None)
    click.echo(format_summary(record))
    return record
