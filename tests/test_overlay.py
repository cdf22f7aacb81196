"""geosim overlay-check against known transforms: b is made from a by moving its
georeference (known shift), by warping it with rasterio/GDAL (rotation, another CRS),
and the measured shifts must be those transforms, whatever the CRS."""

from __future__ import annotations

import json
import math
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
import scipy.ndimage as ndi
from affine import Affine
from click.testing import CliRunner
from rasterio.warp import Resampling, calculate_default_transform, reproject

from geosim.cli.main import cli
from geosim.overlay import overlay_check

GSD_M = 1.0
ORIGIN = (300000.0, 6200000.0)
N_PX = 600
IDENTITY = Affine.identity()


def _texture(seed: int = 1) -> np.ndarray:
    img = ndi.gaussian_filter(np.random.default_rng(seed).normal(size=(N_PX, N_PX)), 2.0)
    return ((img - img.min()) / (img.max() - img.min()) * 250).astype(np.float32)


def _write(path: Path, img: np.ndarray, transform: Affine, crs: str = "EPSG:32756",
           nodata: float | None = None) -> Path:
    with rasterio.open(path, "w", driver="GTiff", width=img.shape[1], height=img.shape[0],
                       count=1, dtype="float32", crs=crs, transform=transform,
                       nodata=nodata) as dst:
        dst.write(img, 1)
    return path


@pytest.fixture(scope="module")
def a_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("overlay")
    return _write(d / "a.tif", _texture(), Affine(GSD_M, 0, ORIGIN[0], 0, -GSD_M, ORIGIN[1]))


def _warp(src: Path, dst: Path, crs: str, extra: Affine = IDENTITY) -> Path:
    """Reproject ``src`` to ``crs`` (cubic), after moving its georeference by ``extra``."""
    with rasterio.open(src) as s:
        st = extra * s.transform
        bounds = rasterio.transform.array_bounds(s.height, s.width, st)
        t, w, h = calculate_default_transform(s.crs, crs, s.width, s.height, *bounds)
        out = np.full((h, w), np.nan, np.float32)
        reproject(s.read(1), out, src_transform=st, src_crs=s.crs, dst_transform=t,
                  dst_crs=crs, resampling=Resampling.cubic, dst_nodata=np.nan)
    return _write(dst, out, t, crs, nodata=float("nan"))


@pytest.mark.parametrize("shift_m", [(3.3, 1.7), (-2.25, 0.6), (0.0, -4.4)])
def test_known_shift_same_crs(a_tif: Path, tmp_path: Path, shift_m: tuple[float, float]
                              ) -> None:
    """The same pixels georeferenced (dx, dy) metres away: content moves by (dx, dy)."""
    with rasterio.open(a_tif) as s:
        t = s.transform
        img = s.read(1)
    b = _write(tmp_path / "b.tif", img, Affine.translation(*shift_m) * t)
    s = overlay_check(a_tif, b).summary()
    assert s["n_confident"] >= 0.9 * s["n_windows"] > 0
    # 128-px windows: the shared phase-correlation kernel is within ~0.05 px here
    assert s["median_shift_m"] == pytest.approx(list(shift_m), abs=0.08)
    assert s["consensus_shift_m"] == pytest.approx(list(shift_m), abs=0.08)
    assert s["p95_m"] == pytest.approx(math.hypot(*shift_m), abs=0.15)


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:3857", "EPSG:32755"])
def test_known_shift_other_crs(a_tif: Path, tmp_path: Path, crs: str) -> None:
    """b warped by GDAL into another CRS (geographic, Web Mercator, the next UTM zone)
    after a known shift: the shift is recovered in a's metres."""
    shift = (2.6, -1.9)
    b = _warp(a_tif, tmp_path / "b.tif", crs, Affine.translation(*shift))
    s = overlay_check(a_tif, b).summary()
    assert s["crs"] == "EPSG:32756"
    assert s["n_confident"] > 10
    assert s["median_shift_m"] == pytest.approx(list(shift), abs=0.12)


def test_geographic_a_uses_utm(a_tif: Path, tmp_path: Path) -> None:
    """With a in lon/lat, the check works in the UTM zone of its centre (metres)."""
    a4326 = _warp(a_tif, tmp_path / "a4326.tif", "EPSG:4326")
    s = overlay_check(a4326, a_tif).summary()
    assert s["crs"] == "EPSG:32756"
    assert s["median_shift_m"] == pytest.approx([0.0, 0.0], abs=0.12)


def test_rotation_gives_the_rotation_field(a_tif: Path, tmp_path: Path) -> None:
    """b = a rotated by 1° about its centre: each window's shift is R·(p − c) − (p − c)."""
    theta = math.radians(1.0)
    cx, cy = ORIGIN[0] + N_PX * GSD_M / 2, ORIGIN[1] - N_PX * GSD_M / 2
    rot = Affine.translation(cx, cy) * Affine.rotation(1.0) * Affine.translation(-cx, -cy)
    b = _warp(a_tif, tmp_path / "b.tif", "EPSG:32756", rot)
    r = overlay_check(a_tif, b, window_px=96)
    east, north = r.shifts_m()
    x, y = r.centres_xy()
    exp_e = math.cos(theta) * (x - cx) - math.sin(theta) * (y - cy) - (x - cx)
    exp_n = math.sin(theta) * (x - cx) + math.cos(theta) * (y - cy) - (y - cy)
    ok = r.field.valid
    assert ok.sum() >= 20
    err = np.hypot(east - exp_e, north - exp_n)[ok]
    assert np.median(err) < 0.1
    s = r.summary()
    # the largest expected shift among the windows is θ·r of the farthest centre
    assert s["max_m"] == pytest.approx(float(np.hypot(exp_e, exp_n)[ok].max()), abs=0.25)
    assert s["median_shift_m"] == pytest.approx([0.0, 0.0], abs=0.3)


def test_cli_outputs_and_exit_status(a_tif: Path, tmp_path: Path) -> None:
    with rasterio.open(a_tif) as s:
        b = _write(tmp_path / "b.tif", s.read(1), Affine.translation(1.5, -2.0) * s.transform)
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["overlay-check", "--a", str(a_tif), "--b", str(b),
                                   "--out", str(out), "--max-shift-m", "5"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "overlay.json").read_text())
    (pair,) = doc["pairs"]
    assert pair["median_shift_m"] == pytest.approx([1.5, -2.0], abs=0.08)
    assert pair["n_windows"] > 0 and pair["ok"] and doc["ok"]
    png = out / pair["png"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    arrows = gpd.read_file(out / "overlay_arrows.geojson")
    assert arrows.crs.to_epsg() == 4326 and len(arrows) == pair["n_windows"]
    assert arrows["dx_m"].median() == pytest.approx(1.5, abs=0.08)
    # an arrow is arrow_scale × the shift long, from the window centre (metres in UTM)
    first = arrows.to_crs("EPSG:32756").iloc[0]
    (x0, y0), (x1, y1) = first.geometry.coords
    assert (x1 - x0, y1 - y0) == pytest.approx((first.dx_m * first.arrow_scale,
                                                first.dy_m * first.arrow_scale), abs=1e-3)
    worse = CliRunner().invoke(cli, ["overlay-check", "--a", str(a_tif), "--b", str(b),
                                     "--out", str(out), "--max-shift-m", "2"])
    assert worse.exit_code == 1, worse.output
    assert "NOT OK" in worse.output


def test_disjoint_rasters_are_a_clear_error(a_tif: Path, tmp_path: Path) -> None:
    with rasterio.open(a_tif) as s:
        b = _write(tmp_path / "b.tif", s.read(1),
                   Affine.translation(10 * N_PX, 0) * s.transform)
    res = CliRunner().invoke(cli, ["overlay-check", "--a", str(a_tif), "--b", str(b),
                                   "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "common extent" in res.output
