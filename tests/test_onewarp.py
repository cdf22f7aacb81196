"""The one composed warp (original flight → site grid → alignment correction)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import Transformer
from rasterio.crs import CRS

from geosim.io.raster import write_geotiff
from geosim.prepare.onewarp import (
    ComposedWarp,
    WarpRasterTask,
    read_warped,
    remap_window,
    warp_raster_task,
)

SITE = CRS.from_epsg(28356)
SRC = CRS.from_epsg(32755)          # the neighbouring UTM zone: grid rotated by ~3°
X0, Y0 = 300000.0, 6200000.0
GRID = Affine(0.05, 0, X0, 0, -0.05, Y0)


def _ramp(x_m, y_m):
    """A smooth ground function (a plane is reproduced exactly by bicubic)."""
    return 60.0 + 0.8 * (x_m - X0) / 0.05 * 0.1 + 0.5 * (Y0 - y_m) / 0.05 * 0.1


def _flight(path, n=400, crs=SRC, fn=_ramp, dtype="float32"):
    to_src = Transformer.from_crs(SITE, crs, always_xy=True)
    sx, sy = to_src.transform(X0 - 1.0, Y0 + 1.0)
    t = Affine(0.047, 0, sx + 0.01, 0, -0.047, sy - 0.02)
    c, r = np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5)
    xs, ys = t * (c, r)
    gx, gy = Transformer.from_crs(crs, SITE, always_xy=True).transform(xs, ys)
    img = fn(gx, gy).astype(dtype)
    valid = np.ones((n, n), bool)
    valid[:, :20] = False                               # a no-data strip
    write_geotiff(path, np.stack([img, img * 0.5]), transform=t, crs=crs, mask=valid)
    return t


def _rotation(deg: float, cx: float, cy: float) -> Affine:
    th = math.radians(deg)
    lin = Affine(math.cos(th), -math.sin(th), 0, math.sin(th), math.cos(th), 0)
    return Affine.translation(cx + 0.11, cy - 0.07) @ lin @ Affine.translation(-cx, -cy)


def test_source_coords_match_exact_projection(tmp_path):
    t = _flight(tmp_path / "f.tif")
    c = _rotation(0.7, X0 + 8, Y0 - 8)
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID, aligned_to_stated=~c)
    wt = GRID @ Affine.translation(37, 51)
    col, row = w.source_coords(wt, (90, 70))
    cc, rr = np.meshgrid(np.arange(70) + 0.5, np.arange(90) + 0.5)
    x, y = (~c) * (wt * (cc, rr))
    px, py = Transformer.from_crs(SITE, SRC, always_xy=True).transform(x, y)
    ec, er = (~t) * (px, py)
    assert np.abs(col - (ec - 0.5)).max() < 1e-5
    assert np.abs(row - (er - 0.5)).max() < 1e-5


def test_windows_do_not_change_the_bits(tmp_path):
    """Any split of the destination into windows gives the same pixels and mask."""
    _flight(tmp_path / "f.tif", fn=lambda x, y: 100 + 40 * np.sin((x - X0) * 9.0)
            * np.cos((y - Y0) * 7.0), dtype="uint8")
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID,
                                aligned_to_stated=~_rotation(0.3, X0 + 5, Y0 - 5))
    at = GRID @ Affine.translation(10, 10)
    whole = read_warped(w, at, (300, 300))
    for block in (37, 128):
        task = WarpRasterTask(w, str(tmp_path / f"b{block}.tif"), tuple(at)[:6], (300, 300),
                              block_px=block)
        rec = warp_raster_task(task)
        with rasterio.open(task.dst_path) as ds:
            assert np.array_equal(ds.read(), whole[0])
            assert np.array_equal(ds.read_masks(1) > 0, whole[1])
        assert rec.valid_px == int(whole[1].sum()) > 0


def test_known_transform_recovers_the_ground(tmp_path):
    """A plane on the ground, seen through a wrong stated georeference and another CRS,
    lands on the aligned grid where it belongs once C⁻¹ is given (bicubic is exact on a
    plane); no-data stays out."""
    c = _rotation(0.5, X0 + 8, Y0 - 8)
    # the flight's pixels show the ground at C(stated position)
    _flight(tmp_path / "f.tif", fn=lambda x, y: _ramp(*(c * (x, y))))
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID, aligned_to_stated=~c)
    at = GRID @ Affine.translation(20, 20)
    img, ok = read_warped(w, at, (300, 300))
    cc, rr = np.meshgrid(np.arange(300) + 0.5, np.arange(300) + 0.5)
    truth = _ramp(*(at * (cc, rr)))
    assert ok.mean() > 0.8 and not ok.all()            # the no-data strip is masked
    assert np.abs(img[0][ok] - truth[ok]).max() < 0.02
    assert np.abs(img[1][ok] - 0.5 * truth[ok]).max() < 0.01


def test_field_hook_moves_the_sampling(tmp_path):
    """A non-rigid field (here a constant 1 m shift east) is applied before C⁻¹."""
    _flight(tmp_path / "f.tif")
    w0 = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID)
    w1 = w0.with_correction(Affine.identity(), field=_shift_east_1m)
    at = GRID @ Affine.translation(40, 40)
    c0, r0 = w0.source_coords(at, (10, 10))
    c1, r1 = w1.source_coords(at, (10, 10))
    # sampling 1 m further east = where the identity warp samples 20 site px to the right
    c20, r20 = w0.source_coords(GRID @ Affine.translation(60, 40), (10, 10))
    assert np.abs(c1 - c20).max() < 1e-6 and np.abs(r1 - r20).max() < 1e-6
    assert np.hypot(c1 - c0, r1 - r0).mean() * 0.047 == pytest.approx(1.0, rel=2e-3)


def _shift_east_1m(x, y):
    return x + 1.0, y


def test_remap_window_mask_is_conservative():
    img = np.full((1, 20, 20), 200, np.uint8)
    valid = np.ones((20, 20), bool)
    valid[:, 10:] = False
    yy, xx = np.mgrid[0:20, 0:20].astype(float)
    out, ok = remap_window(img, valid, xx, yy)
    assert ok[:, :9].all() and not ok[:, 9:].any()
    assert (out[0][ok] == 200).all() and (out[0][~ok] == 0).all()


def test_keep_intermediates_grid_copy_matches_the_aligned_reference(samples_dir, tmp_path):
    """Sample site: grid/<flight>.tif only with keep_intermediates; the reference flight's
    aligned raster (identity correction) is bit for bit that grid copy's window, because
    both are the same warp evaluated on the same global lattice."""
    import re

    from rasterio.windows import Window

    from geosim.config import load_site
    from geosim.pipeline import run_pipeline

    text = (samples_dir / "site.toml").read_text()
    text = re.sub(r'^(image|labels|path) = "([^"]+)"',
                  lambda m: f'{m[1]} = "{(samples_dir / m[2]).resolve().as_posix()}"',
                  text, flags=re.M)
    plain = tmp_path / "plain.toml"
    plain.write_text(text)
    kept = tmp_path / "kept.toml"
    kept.write_text(text.replace("[parameters]\n", "[parameters]\nkeep_intermediates = true\n"))
    run_pipeline(load_site(plain), tmp_path / "a", only=["grid"], echo=lambda s: None)
    assert not list((tmp_path / "a" / "grid").glob("PA*.tif"))
    site = load_site(kept)
    assert site.parameters.keep_intermediates
    out = tmp_path / "b"
    run_pipeline(site, out, only=["grid", "footprints", "align"], echo=lambda s: None)
    import json

    doc = json.loads((out / "alignment.json").read_text())
    w = doc["aligned_grid"]["window_px"]
    with rasterio.open(out / "grid" / "PA1.tif") as g, \
            rasterio.open(out / "aligned" / "PA1.tif") as al:
        win = Window(w["col_off"], w["row_off"], w["width"], w["height"])
        assert np.array_equal(g.read(window=win), al.read())
        assert np.array_equal(g.read_masks(1, window=win), al.read_masks(1))


def test_thread_count_does_not_change_the_file(tmp_path, monkeypatch):
    """The task's thread budget (OpenCV/GDAL threads) changes speed, never the bytes written."""
    import hashlib

    from geosim.engine import task_limits

    _flight(tmp_path / "f.tif", dtype="uint8", fn=lambda x, y: 90 + 30 * np.sin(x * 3.0))
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID,
                                aligned_to_stated=~_rotation(0.2, X0 + 5, Y0 - 5))
    digests = []
    for n in ("1", "2"):
        path = tmp_path / f"t{n}.tif"
        with task_limits(int(n)):
            warp_raster_task(WarpRasterTask(w, str(path), tuple(GRID)[:6], (300, 300),
                                            block_px=128))
        digests.append(hashlib.sha256(path.read_bytes()).hexdigest())
    assert digests[0] == digests[1]


def _whole_window_maps(warp, t, shape, src):
    """The former path: whole-window float coordinates, then cv2.convertMaps."""
    from geosim.prepare.onewarp import _fixed_maps, _window_coords

    found = _window_coords(warp, t, shape, src)
    return None if found is None else (found[0], *_fixed_maps(found[1], found[2]))


def _holes(x_m, y_m):
    """A field that cannot be evaluated at some nodes (NaN), elsewhere a small shift."""
    x, y = x_m + 0.013, y_m - 0.021
    hole = ((x_m - X0) // 0.8 + (Y0 - y_m) // 0.8) % 7 == 0
    return np.where(hole, np.nan, x), np.where(hole, np.nan, y)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # NaN nodes
@pytest.mark.parametrize("field", [None, _holes])
@pytest.mark.parametrize("rotation_deg", [0.0, 0.7])
def test_strip_maps_equal_whole_window_maps(tmp_path, monkeypatch, field, rotation_deg):
    """The strip-wise coordinates and fixed-point maps are, bit for bit, OpenCV's
    convertMaps of the whole-window float32 coordinates (another CRS, rotation, a field
    with NaN nodes, windows inside, across the edge of and outside the flight, strips
    that do not divide the window)."""
    from geosim.prepare import onewarp

    _flight(tmp_path / "f.tif")
    c = _rotation(rotation_deg, X0 + 8, Y0 - 8)
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID, aligned_to_stated=~c,
                                field=field)
    monkeypatch.setattr(onewarp, "STRIP_ROWS", 7)
    seen_nan = False
    with rasterio.open(tmp_path / "f.tif") as src:
        for r0, c0, h, wd in [(0, 0, 64, 64), (-30, -40, 120, 90), (300, 350, 200, 150),
                              (10, 10, 1, 1), (5000, 5000, 20, 20), (33, 17, 129, 257)]:
            t = GRID @ Affine.translation(c0, r0)
            old = _whole_window_maps(w, t, (h, wd), src)
            new = onewarp._window_maps(w, t, (h, wd), src)
            assert (old is None) == (new is None)
            if old is None:
                continue
            assert old[0] == new[0]
            assert np.array_equal(old[1], new[1]) and np.array_equal(old[2], new[2])
            seen_nan |= bool(np.isnan(w.source_coords(t, (h, wd))[0]).any())
    assert seen_nan == (field is not None)


def test_strip_maps_fall_back_beyond_their_range(tmp_path, monkeypatch):
    """Coordinates too large for the int32 strip path take the whole-window path (same
    maps)."""
    from geosim.prepare import onewarp

    _flight(tmp_path / "f.tif")
    w = ComposedWarp.for_flight(tmp_path / "f.tif", SITE, GRID)
    calls = []
    real = onewarp._window_coords
    monkeypatch.setattr(onewarp, "_window_coords", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(onewarp, "_STRIP_MAX_PX", 100.0)
    with rasterio.open(tmp_path / "f.tif") as src:
        t = GRID @ Affine.translation(150, 150)
        new = onewarp._window_maps(w, t, (60, 60), src)
        assert calls
        monkeypatch.setattr(onewarp, "_STRIP_MAX_PX", 2.0 ** 18)
        old = _whole_window_maps(w, t, (60, 60), src)
    assert old[0] == new[0] and np.array_equal(old[1], new[1]) and np.array_equal(old[2], new[2])
