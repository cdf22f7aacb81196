"""Grey imagery works end to end (issue 12, item 4): 1-band and grey+alpha flights and
satellite scenes. A grey image says nothing about colour, so it is compared with an RGB one
by luma (BT.601)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.enums import ColorInterp

from geosim.diagnose.grids import common_bands
from geosim.physics.radiometry import LUMA_WEIGHTS
from tests.robust_helpers import copy_site, run_cli


def _luma_u8(rgb: np.ndarray) -> np.ndarray:
    w = np.asarray(LUMA_WEIGHTS, float)[:, None, None]
    return np.clip(np.round((rgb[:3].astype(float) * w).sum(axis=0)), 1, 255).astype(np.uint8)


def _to_grey(path: Path, *, alpha: bool) -> None:
    """Rewrite an RGB(A) GeoTIFF as grey (1 band, nodata 0) or grey+alpha (2 bands)."""
    with rasterio.open(path) as ds:
        profile, data = ds.profile, ds.read()
        valid = ds.dataset_mask() > 0
    grey = np.where(valid, _luma_u8(data), 0).astype(np.uint8)
    profile.pop("photometric", None)
    if alpha:
        profile.update(count=2, nodata=None, alpha="YES")  # GTiff: band 2 is alpha
        bands, interp = np.stack([grey, valid.astype(np.uint8) * 255]), \
            [ColorInterp.gray, ColorInterp.alpha]
    else:
        profile.update(count=1, nodata=0)
        bands, interp = grey[np.newaxis], [ColorInterp.gray]
    path.unlink()
    with rasterio.open(path, "w", **profile) as out:
        out.write(bands)
        out.colorinterp = interp


def test_common_bands_compares_grey_with_the_luma_of_rgb() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0, 255, (3, 8, 8)).astype(np.float32)
    grey = rng.uniform(0, 255, (1, 8, 8)).astype(np.float32)
    u, s = common_bands(grey, rgb)
    assert u.shape == s.shape == (1, 8, 8)
    np.testing.assert_allclose(s[0], 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2],
                               rtol=1e-6)
    u, s = common_bands(rgb, grey)
    assert u.shape == (1, 8, 8) and s is grey
    u, s = common_bands(rgb, rgb)
    assert u is rgb and s is rgb


@pytest.mark.slow
def test_grey_and_grey_alpha_flights_and_satellite_run_end_to_end(samples_dir: Path,
                                                                  tmp_path: Path) -> None:
    # On the old main: accepted, then an IndexError traceback in diagnose (exit 1).
    site = copy_site(samples_dir, tmp_path / "site")
    flights = site.parent / "flights"
    _to_grey(flights / "PA1.tif", alpha=False)  # grey, nodata 0
    _to_grey(flights / "PA2.tif", alpha=True)   # grey + alpha
    _to_grey(site.parent / "satellite" / "satellite.tif", alpha=True)  # PA3 stays RGB
    out = tmp_path / "run"
    result = run_cli("run", site, "--out", out)
    assert result.code == 0, result.stderr[-3000:]
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "ok"
    assert all(s["status"] == "ok" for s in run["steps"].values())
    # flights are resampled once, tile by tile (no grid/ or aligned/ copy is kept)
    with rasterio.open(sorted((out / "tiles" / "PA1").glob("*.tif"))[0]) as a, \
            rasterio.open(sorted((out / "tiles" / "PA2").glob("*.tif"))[0]) as b, \
            rasterio.open(out / "grid" / "satellite.tif") as s:
        assert (a.count, b.count, s.count) == (1, 1, 1)  # alpha became the mask
    q = run["steps"]["calibrate"]["summary"]
    diag = json.loads((out / "diagnosis" / "diagnosis.json").read_text())
    assert set(diag["flights"]) == {"PA1", "PA2", "PA3"}
    assert np.isfinite(diag["refined"]["q"]) and q
    degraded = sorted((out / "degraded" / "PA1").glob("*.tif"))
    assert degraded
    with rasterio.open(degraded[0]) as d:
        assert d.count == 1
