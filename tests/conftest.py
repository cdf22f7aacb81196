"""Shared fixtures. Real imagery lives beside the project in ../shared/realdata
and is never committed; tests that need it skip with a reason when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

PROJECT_ROOT = Path(__file__).resolve().parents[1]
SAMPLES_DIR = PROJECT_ROOT / "data" / "samples"
REALDATA_DIR = Path(os.environ.get("GEOSIM_REALDATA",
                                   PROJECT_ROOT.parent / "shared" / "realdata"))
# Commands run in-process in the tests unless a test asks for a cluster (--workers N):
# a Dask cluster per CLI call would only slow the suite (tests/test_engine*.py cover it).
os.environ.setdefault("GEOSIM_WORKERS", "1")


@pytest.fixture(scope="session")
def realdata() -> Path:
    """Path to ../shared/realdata; skips the test when it is not there."""
    if not REALDATA_DIR.is_dir():
        pytest.skip(f"real imagery not found at {REALDATA_DIR} (../shared/realdata is absent; "
                    "set GEOSIM_REALDATA to its location to run this test)")
    return REALDATA_DIR


@pytest.fixture(scope="session")
def samples_dir() -> Path:
    """The bundled sample site."""
    if not (SAMPLES_DIR / "site.toml").is_file():
        pytest.skip(f"sample site not generated yet at {SAMPLES_DIR}")
    return SAMPLES_DIR
