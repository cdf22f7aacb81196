"""``python -m geosim`` runs the CLI."""

from geosim.cli.main import cli

cli(prog_name="geosim")
