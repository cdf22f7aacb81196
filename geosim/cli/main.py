"""The ``geosim`` command group. Subcommands live in sibling modules."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any

import click

from geosim import __version__
from geosim.errors import GeosimError
from geosim.io.atomic import write_failure
from geosim.io.raster import read_failure

# (module, attribute) of each subcommand; every module only parses and calls.
SUBCOMMANDS: list[tuple[str, str]] = [
    ("geosim.cli.run", "run"),
    ("geosim.cli.run", "demo"),
    ("geosim.cli.samples", "samples"),
    ("geosim.cli.prepare", "grid"),
    ("geosim.cli.prepare", "align"),
    ("geosim.cli.prepare", "tile"),
    ("geosim.cli.prepare", "prepare"),
    ("geosim.cli.labels", "labels"),
    ("geosim.cli.labels", "cattle_per_paddock"),
    ("geosim.cli.labels", "movement"),
    ("geosim.cli.degrade", "degrade"),
    ("geosim.cli.degrade", "calibrate"),
    ("geosim.cli.augment", "augment"),
    ("geosim.cli.diagnose", "diagnose"),
    ("geosim.cli.overlay", "deliver"),
    ("geosim.cli.overlay", "overlay_check"),
]


class GeosimGroup(click.Group):
    """Turns :class:`GeosimError` into one line on stderr and exit code 2, and an
    interruption (Ctrl-C, SIGTERM; recorded in run.json) into one line and exit 130."""

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except GeosimError as exc:
            if ctx.obj and ctx.obj.get("debug"):
                raise
            click.echo(f"geosim: error: {exc}", err=True)
            sys.exit(2)
        except OSError as exc:  # a write outside geosim.io (disk full, permission, …)
            failure = write_failure(exc, exc.filename or "an output") or read_failure(exc)
            if failure is None or (ctx.obj and ctx.obj.get("debug")):
                raise
            click.echo(f"geosim: error: {failure}", err=True)
            sys.exit(2)
        except KeyboardInterrupt as exc:
            if ctx.obj and ctx.obj.get("debug"):
                raise
            click.echo(f"geosim: interrupted ({exc or 'Ctrl-C'}); run.json records it; "
                       "run the command again to redo it", err=True)
            sys.exit(130)


@click.group(cls=GeosimGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="geosim")
@click.option("--debug", is_flag=True, help="Show full tracebacks instead of one-line errors.")
@click.option("-v", "--verbose", count=True, help="More messages (debug level, logger names).")
@click.option("-q", "--quiet", is_flag=True,
              help="Only warnings and errors on stderr; no progress bars.")
@click.pass_context
def cli(ctx: click.Context, debug: bool, verbose: int, quiet: bool) -> None:
    """geosim: UAV surveys of cattle paddocks to aligned, labelled patch pairs and
    calibrated 0.5 m satellite simulations, in map coordinates."""
    from geosim.log import configure

    ctx.ensure_object(dict)
    ctx.obj["debug"] = debug
    ctx.call_on_close(configure(verbose=verbose, quiet=quiet))


def _register(group: click.Group, entries: list[tuple[str, str]]) -> None:
    for module_name, attr in entries:
        command: Callable[..., Any] = getattr(importlib.import_module(module_name), attr)
        group.add_command(command)  # type: ignore[arg-type]


_register(cli, SUBCOMMANDS)
