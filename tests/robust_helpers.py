"""Builders for the robustness tests: copies of the sample site and a CLI runner in a
subprocess (with a timeout, so no test can hang)."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class CliResult:
    """Exit code, output and wall time of one ``python -m geosim`` call."""

    code: int
    stdout: str
    stderr: str


def copy_site(samples_dir: Path, dest: Path) -> Path:
    """A private copy of the sample site; returns its site.toml."""
    shutil.copytree(samples_dir, dest)
    return dest / "site.toml"


def run_cli(*args: str | os.PathLike[str], timeout_s: float = 600,
            preexec_fn: Callable[[], None] | None = None) -> CliResult:
    """``python -m geosim ARGS`` in a subprocess with this checkout first on the path.

    ``timeout_s`` only stops a hung test: generous, because on a loaded 2-core machine
    importing geosim alone can take tens of seconds.
    """
    env = {**os.environ, "PYTHONPATH": str(PROJECT_ROOT)}
    r = subprocess.run([sys.executable, "-m", "geosim", *map(str, args)], env=env,
                       capture_output=True, text=True, timeout=timeout_s,
                       preexec_fn=preexec_fn)
    return CliResult(r.returncode, r.stdout, r.stderr)


def error_lines(stderr: str) -> list[str]:
    """The ``geosim: error:`` lines of stderr (GDAL's own messages are not counted)."""
    return [ln for ln in stderr.splitlines() if ln.startswith("geosim: error:")]


def assert_one_line_error(result: CliResult, *needles: str) -> str:
    """Exit 2, exactly one ``geosim: error:`` line, no traceback; return that line."""
    assert result.code == 2, (result.code, result.stderr[-2000:])
    assert "Traceback" not in result.stderr, result.stderr[-2000:]
    lines = error_lines(result.stderr)
    assert len(lines) == 1, result.stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def tree_digest(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` by relative path."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def set_site_value(site_toml: Path, pattern: str, replacement: str) -> None:
    """Edit the site file with one regular-expression substitution (must match)."""
    text = site_toml.read_text()
    new, n = re.subn(pattern, replacement, text, count=1, flags=re.MULTILINE)
    assert n == 1, pattern
    site_toml.write_text(new)
