"""Write docs/cli.md, the CLI reference, from the commands' own ``--help`` texts.

Usage: ``python tools/cli_reference.py`` (rewrites docs/cli.md); ``--check`` exits 1 when
docs/cli.md is not what the current commands print (tests/test_cli_reference.py runs it).
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DOC = ROOT / "docs" / "cli.md"


def _help(command: click.Command, name: str) -> str:
    ctx = click.Context(command, info_name=name, terminal_width=100, max_content_width=100)
    return command.get_help(ctx)


def reference() -> str:
    """The markdown page: the group's help, then every command's, in name order."""
    from geosim.cli.main import cli

    parts = ["# Command-line reference", "",
             "Generated from the commands' own `--help` by `python tools/cli_reference.py`;",
             "`tests/test_cli_reference.py` fails when this page and the commands disagree.", "",
             "```", _help(cli, "geosim"), "```", ""]
    for name in sorted(cli.commands):
        command = cli.commands[name]
        parts += [f"## geosim {name}", "", "```", _help(command, f"geosim {name}"), "```", ""]
        if isinstance(command, click.Group):
            for sub in sorted(command.commands):
                parts += [f"### geosim {name} {sub}", "", "```",
                          _help(command.commands[sub], f"geosim {name} {sub}"), "```", ""]
    parts.append("[Back to the README](../README.md)")
    return "\n".join(parts) + "\n"


def main(argv: list[str]) -> int:
    text = reference()
    if "--check" in argv:
        if not DOC.is_file() or DOC.read_text() != text:
            print(f"{DOC} is out of date: run python tools/cli_reference.py", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(text)
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
