"""Options and the one call shared by the commands that run pipeline steps."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import click

from geosim.config import ANCHORS, load_site
from geosim.engine import default_workers, open_engine
from geosim.errors import ConfigError
from geosim.pipeline import format_summary, run_pipeline

SITE_ARG = click.argument("site_file", type=click.Path(path_type=Path))
OUT_OPTION = click.option("--out", "out", required=True, type=click.Path(path_type=Path),
                          help="Run folder (created if needed).")
ANCHOR_OPTION = click.option(
    "--anchor", type=click.Choice(ANCHORS), default=None,
    help="Frame of the aligned flights, overriding [site] anchor: the reference flight's "
         "georeference (the paper) or the satellite scene's.")


def engine_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add ``--workers`` and ``--scheduler`` to a command and run it on that engine.

    Put it right under ``@click.command()``. The command's own function does not see the
    two options: its body runs with the chosen engine active
    (:func:`geosim.engine.open_engine`), which is closed (cluster stopped) afterwards.
    """

    @functools.wraps(command)
    def wrapper(*args: Any, workers: int | None, scheduler: str | None, **kwargs: Any) -> Any:
        with open_engine(workers, scheduler):
            return command(*args, **kwargs)

    wrapper = click.option(
        "--scheduler", "scheduler", default=None, envvar="GEOSIM_SCHEDULER",
        metavar="ADDRESS",
        help="Run the tasks on an existing Dask cluster (e.g. tcp://HOST:8786, started with "
             "'dask scheduler' and 'dask worker ADDRESS' on machines sharing --out); "
             "overrides --workers.")(wrapper)
    wrapper = click.option(
        "--workers", "workers", type=click.IntRange(min=1), default=None,
        envvar="GEOSIM_WORKERS", show_envvar=True,
        help="Worker processes of a local Dask cluster (default: the machine's cores, "
             f"{default_workers()} here); 1 runs every task in this process, on one core.")(wrapper)
    return wrapper


def run_steps(site_file: Path, out: Path, steps: Sequence[str] | None, *,
              anchor: str | None = None,
              options: Mapping[str, Mapping[str, Any]] | None = None,
              satellite_required: bool = False) -> dict[str, Any]:
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
    options
        Keyword options per step name (``{"degrade": {"q": 4.34}}``).
    satellite_required
        Refuse (ConfigError) a site without a satellite scene instead of skipping the
        steps that need one (for commands that run only such a step).

    Returns
    -------
    dict
        The run record (run.json). Progress and warnings go to stderr, the summary to
        stdout.
    """
    site = load_site(site_file)
    if anchor is not None:
        site = dataclasses.replace(site, anchor=anchor)
    if satellite_required and site.satellite is None:
        raise ConfigError(f"{site_file}: site {site.name!r} has no [satellite] scene; "
                          f"'geosim {' '.join(steps or ())}' needs one (add a [satellite] "
                          "table with the image path)")
    record = run_pipeline(site, out, only=steps or None, options=options)
    click.echo(format_summary(record))
    return record
