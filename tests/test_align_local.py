"""Local (non-rigid) co-registration: ``parameters.align_model = "local"``.

Truth comes from known warps (analytic fields applied to real or synthetic imagery), never
from the code under test; the image-level check uses scikit-image's phase correlation.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine

from geosim.align.field import (
    ACCEPTED,
    LOW_CONFIDENCE,
    NEIGHBOUR_OUTLIER,
    UNMEASURED,
    DisplacementField,
    fit_field,
    measure_window_shifts,
    reject_outliers,
)
from geosim.config import Parameters
from geosim.errors import ConfigError
from tests.helpers import textured_rgb

PX_T = Affine(0.05, 0, 500_000.0, 0, -0.05, 6_200_000.0)  # a north-up 0.05 m grid


def smooth_field_px(x: np.ndarray, y: np.ndarray, amp: float = 2.5, size: float = 1024.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A known stitching-like field in pixels (reference (x, y) ~ moving (x + u, y + v))."""
    k = 2 * np.pi / size
    return (amp * np.sin(k * x / 0.7 + 0.3) * np.cos(k * y / 0.85),
            0.8 * amp * np.cos(k * x / 0.55) * np.sin(k * y / 0.65 + 0.5))


def warp_by(image: np.ndarray, fn, **kw) -> np.ndarray:
    """``moving(q) = image(p)`` with ``q = p + u(p)`` (inverted by fixed-point iteration)."""
    h, w = image.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = xx.copy(), yy.copy()
    for _ in range(6):
        ux, uy = fn(px, py, **kw)
        px, py = xx - ux, yy - uy
    return cv2.remap(image, px.astype(np.float32), py.astype(np.float32), cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_REFLECT)


@pytest.fixture(scope="module")
def synthetic_pair():
    grey = textured_rgb(1024, 1024, seed=3).astype(np.float32).mean(axis=0)
    # wavelengths 1100–1700 px (55–85 m at 0.05 m): stitching-warp scale
    return grey, warp_by(grey, smooth_field_px, size=2048.0)


# --------------------------------------------------------------------------- config


def test_align_model_parameter():
    assert Parameters().align_model == "similarity"          # the paper's, by default
    assert Parameters(align_model="local").align_model == "local"
    with pytest.raises(ConfigError, match="align_model"):
        Parameters(align_model="elastic")


def test_align_model_in_site_file(tmp_path):
    from geosim.config import _parameters

    assert _parameters({"align_model": "local"}, tmp_path / "s.toml").align_model == "local"
    with pytest.raises(ConfigError, match="must be of type str"):
        _parameters({"align_model": 1}, tmp_path / "s.toml")


# --------------------------------------------------------------------------- kernel


def test_field_recovers_known_warp(synthetic_pair):
    ref, mov = synthetic_pair
    shifts = reject_outliers(measure_window_shifts(ref, mov, window_px=256, step_px=128))
    assert shifts.accepted.all()
    field = fit_field(shifts, PX_T, ref.shape)
    r, c = np.mgrid[0:1024:8, 0:1024:8].astype(float)
    x, y = PX_T * (c + 0.5, r + 0.5)
    dx_m, dy_m = field.displacement_m(x, y)
    u, v = smooth_field_px(c, r, size=2048.0)
    err = np.hypot(dx_m / 0.05 - u, -dy_m / 0.05 - v)
    assert np.median(err) < 0.1
    inner = err[16:-16, 16:-16]  # ≥ 128 px from the edge: interpolation, not extrapolation
    assert inner.max() < 0.3
    assert field.stats["supported_fraction"] == 1.0


def test_apply_and_invert_round_trip(synthetic_pair):
    ref, mov = synthetic_pair
    field = fit_field(reject_outliers(measure_window_shifts(ref, mov, window_px=256,
                                                            step_px=128)), PX_T, ref.shape)
    rng = np.random.default_rng(1)
    x = PX_T.c + rng.uniform(0, 51.2, 200)
    y = PX_T.f - rng.uniform(0, 51.2, 200)
    qx, qy = field.apply(x, y)
    assert np.abs(np.hypot(qx - x, qy - y)).max() > 0.05        # it does move points
    px, py = field.invert(qx, qy)
    assert np.abs(px - x).max() < 1e-6 and np.abs(py - y).max() < 1e-6


def test_outliers_low_confidence_and_neighbours(synthetic_pair):
    ref, mov = synthetic_pair
    mov = mov.copy()
    other = textured_rgb(256, 256, seed=11).astype(np.float32).mean(axis=0)
    mov[384:640, 384:640] = other                     # changed ground (other texture)
    mov[0:256, 768:1024] = np.float32(mov.mean())     # featureless
    s = measure_window_shifts(ref, mov, window_px=256, step_px=128)
    dx = s.dx_px.copy()
    dx[1, 5] += 3.0                                   # one window measured 3 px wrong
    s = type(s)(s.x_px, s.y_px, dx, s.dy_px, s.confidence, s.status, s.window_px, s.step_px)
    s = reject_outliers(s, min_confidence=0.1)
    assert s.status[3, 3] == LOW_CONFIDENCE            # window fully inside the changed square
    assert s.status[0, 6] == UNMEASURED                # flat: nothing to correlate
    assert s.status[1, 5] == NEIGHBOUR_OUTLIER
    assert s.counts()["accepted"] == int(np.count_nonzero(s.status == ACCEPTED))
    assert s.counts()["accepted"] >= 38                # most of the 49 windows survive


def test_fallback_beyond_measurements_no_blow_up(synthetic_pair):
    ref, mov = synthetic_pair
    valid = np.zeros(ref.shape, bool)
    valid[:, :400] = True                              # only the west part can be measured
    s = reject_outliers(measure_window_shifts(ref, mov, valid=valid, window_px=256,
                                              step_px=128))
    field = fit_field(s, PX_T, ref.shape)
    acc_max = float(np.hypot(s.dx_px, s.dy_px)[s.accepted].max())
    assert field.magnitude_m().max() / 0.05 <= acc_max + 1e-9
    # nodes far east of every measurement keep the global model (0) and say so
    east = field.support[:, -2:]
    assert (east == 0).all() and (field.magnitude_m()[:, -2:] == 0).all()
    assert 0 < field.stats["supported_fraction"] < 0.7


def test_too_few_windows_is_global_everywhere():
    grey = textured_rgb(300, 300, seed=2).astype(np.float32).mean(axis=0)
    s = reject_outliers(measure_window_shifts(grey, grey, window_px=256, step_px=128))
    field = fit_field(s, PX_T, grey.shape)
    assert field.magnitude_m().max() == 0 and field.support.max() == 0
    assert "global model everywhere" in field.stats["note"]


# --------------------------------------------------------------------------- phase correlation


@pytest.mark.parametrize("whitening", [0.5, 1.0])
def test_phase_correlate_agrees_with_skimage(realdata, whitening):
    """Cross-check of geosim's phase correlation with scikit-image's (issue 11), in the
    default (partial whitening) and in diagnose's mode (classical, ``whitening=1``)."""
    from skimage.registration import phase_cross_correlation

    from geosim.align import phase_correlate

    with rasterio.open(realdata / "brazil_pasture_10cm_epsg3395.tif") as ds:
        grey = ds.read(2, window=rasterio.windows.Window(600, 600, 512, 512)).astype(np.float64)
    spec = np.fft.fft2(grey)
    fy = np.fft.fftfreq(512)[:, None]
    fx = np.fft.fftfreq(512)[None, :]
    for dx, dy in ((3.37, -1.81), (-0.42, 0.77), (6.05, 2.5), (5.0, -7.0), (-2.0, 0.0)):
        moved = np.fft.ifft2(spec * np.exp(-2j * np.pi * (fx * dx + fy * dy))).real
        crop_r, crop_m = grey[32:-32, 32:-32].copy(), moved[32:-32, 32:-32].copy()
        before = crop_m.copy()
        ours = phase_correlate(crop_r, crop_m, whitening=whitening).shift_px
        sk, _, _ = phase_cross_correlation(crop_r, crop_m, upsample_factor=100)
        assert np.array_equal(crop_m, before)          # inputs untouched
        # skimage returns the shift that registers moving onto reference: (-dy, -dx)
        assert abs(ours[0] + sk[1]) < 0.05 and abs(ours[1] + sk[0]) < 0.05
        assert abs(ours[0] - dx) < 0.05 and abs(ours[1] - dy) < 0.05
        # whole-pixel mode (diagnose's integer_shift: upsample 1, search within ±8 px)
        whole = phase_correlate(crop_r, crop_m, whitening=whitening, upsample_factor=1,
                                max_shift_px=8).shift_px
        sk1, _, _ = phase_cross_correlation(crop_r, crop_m, upsample_factor=1)
        assert whole == (-float(sk1[1]), -float(sk1[0]))
        assert abs(whole[0] - dx) <= 0.5 + 1e-9 and abs(whole[1] - dy) <= 0.5 + 1e-9


def test_phase_correlate_whitening_is_checked():
    from geosim.align import phase_correlate

    grey = textured_rgb(64, 64, seed=1).astype(np.float32).mean(axis=0)
    with pytest.raises(ValueError, match="whitening"):
        phase_correlate(grey, grey, whitening=1.5)


# --------------------------------------------------------------------------- seasonal pair


@pytest.mark.parametrize("tile", ["SJER_004", "SJER_021", "SJER_048", "SJER_054"])
def test_seasonal_pair_known_field(realdata, tile):
    """SJER 2017 (green) vs 2018 (dry): a known field added to 2018 is recovered where
    windows are accepted; seasonal change shows up as rejected windows, not wrong ones."""
    from geosim.align.phasecorr import as_grey

    def load(path: Path):
        with rasterio.open(path) as ds:
            a = ds.read([1, 2, 3])
        return as_grey(a), ~(a == 255).all(axis=0)

    a, va = load(realdata / "sjer_2017" / f"{tile}.tif")
    b, vb = load(realdata / "sjer_2018" / f"{tile}.tif")
    bw = warp_by(b, smooth_field_px, size=800.0)
    vw = warp_by(vb.astype(np.float32), smooth_field_px, size=800.0) > 0.999
    kw = {"window_px": 128, "step_px": 64}
    s0 = reject_outliers(measure_window_shifts(a, b, valid=va & vb, **kw))   # the years' own
    s1 = reject_outliers(measure_window_shifts(a, bw, valid=va & vw, **kw))
    ok = s0.accepted & s1.accepted
    u, v = smooth_field_px(s1.x_px, s1.y_px, size=800.0)
    err = np.hypot(s1.dx_px - s0.dx_px - u, s1.dy_px - s0.dy_px - v)[ok]
    assert ok.sum() >= 8
    assert np.median(err) < 0.3
    assert s1.counts()["low_confidence"] >= 1      # seasonal change is refused, and counted


# --------------------------------------------------------------------------- pipeline


def _run(case, out: Path) -> None:
    from geosim.config import load_site
    from geosim.prepare.steps import run_align, run_footprints, run_grid

    site = load_site(case.site_path)
    for step in (run_grid, run_footprints, run_align):
        step(site, out)


@pytest.fixture(scope="module")
def warp_runs(realdata, tmp_path_factory):
    from tests.warp_case import evaluate, make_case

    res = {}
    for model in ("similarity", "local"):
        folder = tmp_path_factory.mktemp(f"warp_{model}")
        case = make_case(realdata, folder, align_model=model)
        _run(case, folder / "run")
        res[model] = (case, folder / "run", evaluate(case, folder / "run"))
    return res


def test_local_model_meets_acceptance(warp_runs):
    """±2.5 px smooth warp + similarity error, flight in EPSG:4326, reference in EPSG:3395."""
    _, _, glob = warp_runs["similarity"]
    _, _, loc = warp_runs["local"]
    assert glob.median_px > 1.0                       # the similarity cannot absorb the warp
    assert loc.median_px <= 0.3 and loc.worst_window_px <= 1.0
    assert loc.image_median_px <= 0.3 and loc.image_worst_px <= 1.0   # scikit-image's view
    # beyond the reference footprint the field fades to the global model: no blow-up
    assert loc.beyond_reference_max_px is not None
    assert loc.beyond_reference_max_px <= glob.beyond_reference_max_px + 0.5


def test_local_outputs(warp_runs):
    case, out, _ = warp_runs["local"]
    doc = json.loads((out / "alignment.json").read_text())
    assert doc["align_model"] == "local"
    rec = doc["flights"]["MOV"]["local_field"]
    assert "local_field" not in doc["flights"]["REF"]
    assert rec["model"] == "local" and rec["before"]["median_shift_px"] > 1.0
    assert 0 < rec["fallback"]["node_fraction"] < 0.5 and rec["fallback"]["bounds_m"]
    assert doc["local_check"]["MOV"]["median_shift_px"] < 0.3      # residual after correction
    with rasterio.open(out / rec["path"]) as ds:                    # the field GeoTIFF
        assert ds.count == 2 and ds.descriptions == ("dx_m", "dy_m")
        assert ds.crs.to_string() == case.site_crs
        assert list(ds.transform)[:6] == rec["node_grid"]["transform"]
        mag = np.hypot(*ds.read())
        assert 0.1 < mag.max() < 0.8                  # metres: 1–8 px at 0.1 m
        assert (ds.read_masks(1) == 0).any()          # the fallback is marked


def test_field_geotiff_opens_in_gdal(warp_runs):
    import shutil
    import subprocess

    if shutil.which("gdalinfo") is None:
        pytest.skip("gdalinfo not installed")
    _, out, _ = warp_runs["local"]
    info = json.loads(subprocess.run(["gdalinfo", "-json", str(out / "alignment_field/MOV.tif")],
                                     check=True, capture_output=True, text=True).stdout)
    assert [b["description"] for b in info["bands"]] == ["dx_m", "dy_m"]
    assert info["bands"][0]["type"] == "Float64"


def test_labels_move_with_the_field(warp_runs):
    """A label on a ground point, stated where the warped flight shows it, lands on it."""
    import geopandas as gpd
    from shapely.affinity import affine_transform
    from shapely.geometry import Point

    from geosim.labels.steps import apply_local_fields
    from geosim.prepare.alignment import correction_affine

    case, out, _ = warp_runs["local"]
    doc = json.loads((out / "alignment.json").read_text())
    corr = correction_affine(doc["flights"]["MOV"])
    cx, cy = case.centre_m
    ground = np.array([[cx - 40, cy + 30], [cx + 25, cy - 35], [cx + 5, cy + 50]])
    stated = ground.copy()                            # invert the truth W numerically
    for _ in range(50):
        tx, ty = case.truth(stated[:, 0], stated[:, 1])
        stated -= np.stack([tx, ty], axis=1) - ground
    geoms = [affine_transform(Point(x, y), [corr.a, corr.b, corr.d, corr.e, corr.c, corr.f])
             for x, y in stated]
    labels = gpd.GeoDataFrame({"flight": ["MOV"] * 3}, geometry=geoms, crs=case.site_crs)
    moved = apply_local_fields(labels, out)
    got = np.array([[g.x, g.y] for g in moved.geometry])
    before = np.hypot(*(np.array([[g.x, g.y] for g in geoms]) - ground).T) / 0.1
    after = np.hypot(*(got - ground).T) / 0.1
    assert before.max() > 0.8                         # the global model leaves them off
    assert after.max() < 0.3                          # the field puts them back


def test_similarity_model_writes_no_field(warp_runs):
    _, out, _ = warp_runs["similarity"]
    doc = json.loads((out / "alignment.json").read_text())
    assert doc["align_model"] == "similarity"
    assert not (out / "alignment_field").exists()
    assert all("local_field" not in e for e in doc["flights"].values())
    assert math.isfinite(doc["local_check"]["MOV"]["median_shift_px"])


def test_local_model_resamples_once_from_the_original(warp_runs):
    """aligned/MOV.tif is one bicubic remap of the original flight through
    the composed mapping (a second interpolation, as from grid/<flight>.tif, differed from
    this oracle by 0.78 grey levels on average and up to 10.5)."""
    from rasterio.windows import Window

    from tests.warp_case import single_remap_oracle

    case, out, _ = warp_runs["local"]
    n = 512
    with rasterio.open(out / "aligned" / "MOV.tif") as ds:
        # made from the original file (and the field), not from the grid/ copy that
        # keep_intermediates also writes
        assert json.loads(ds.tags()["GEOSIM_SOURCES"]) == [
            str(case.mov_path), "alignment_field/MOV.tif"]
        r0, c0 = ds.height // 2 - n // 2, ds.width // 2 - n // 2 - 300
        got = ds.read([1, 2, 3], window=Window(c0, r0, n, n)).astype(np.float32).mean(axis=0)
        ok = ds.read_masks(1, window=Window(c0, r0, n, n)) > 0
    oracle = single_remap_oracle(case, out, r0, c0, n)
    assert ok.mean() > 0.99
    diff = np.abs(got - oracle)[ok]
    # what is left: 8-bit rounding, OpenCV's 1/32 px positions, the 16 px lattice
    assert diff.mean() < 0.35 and diff.max() < 3.0


def test_tiles_resampled_once_equal_the_aligned_rasters(warp_runs):
    """The tiles step resamples each tile once from the original flight, through the warp it
    rebuilds from alignment.json and alignment_field/<flight>.tif (the field read back from
    its file): the same pixels and masks, bit for bit, as the windows of the whole-flight
    aligned rasters the align step wrote (keep_intermediates), for both models."""
    from rasterio.windows import Window

    from geosim.config import load_site
    from geosim.prepare.steps import run_tiles

    for model in ("similarity", "local"):
        case, out, _ = warp_runs[model]
        run_tiles(load_site(case.site_path), out)
        n = 0
        for rec in json.loads((out / "tiles" / "index.json").read_text())["tiles"]:
            for fid in ("REF", "MOV"):
                path = out / "tiles" / fid / f"{rec['tile_id']}.tif"
                with rasterio.open(path) as t, rasterio.open(out / "aligned" / f"{fid}.tif") as a:
                    win = Window(rec["col"] * rec["tile_px"], rec["row"] * rec["tile_px"],
                                 t.width, t.height)
                    assert t.transform == a.window_transform(win)
                    assert np.array_equal(t.read(), a.read(window=win))
                    assert np.array_equal(t.read_masks(1), a.read_masks(1, window=win))
                n += 1
        assert n >= 4, model


def _smooth_field(origin_x: float, origin_y: float) -> DisplacementField:
    """A known smooth field (±0.1 m = ±2 px at 0.05 m) on a 3.2 m node grid."""
    yy, xx = np.mgrid[0:12, 0:12].astype(float)
    t = Affine(3.2, 0, origin_x - 3.2, 0, -3.2, origin_y + 3.2)
    return DisplacementField(t, 0.1 * np.sin(xx / 3.0) * np.cos(yy / 4.0),
                             -0.08 * np.cos(xx / 5.0 + 0.3) * np.sin(yy / 2.5),
                             np.ones((12, 12)))


def test_field_warp_is_exact_picklable_and_window_independent(tmp_path):
    """The local field inside the one composed warp: source coordinates equal the exact
    per-pixel composition; the bits do not depend on the window size nor on pickling (an
    engine task on another worker)."""
    import pickle

    from pyproj import Transformer
    from rasterio.crs import CRS

    from geosim.prepare.local_align import with_field
    from geosim.prepare.onewarp import (
        ComposedWarp,
        WarpRasterTask,
        read_warped,
        warp_raster_task,
    )
    from tests.helpers import write_raster

    site, src_crs = CRS.from_epsg(28356), "EPSG:32755"      # neighbouring UTM zone
    x0, y0 = 300_000.0, 6_200_000.0
    grid = Affine(0.05, 0, x0, 0, -0.05, y0)
    sx, sy = Transformer.from_crs(site, src_crs, always_xy=True).transform(x0 - 1.0, y0 + 1.0)
    src_t = Affine(0.047, 0, sx, 0, -0.047, sy)
    write_raster(tmp_path / "f.tif", textured_rgb(500, 500, seed=11), crs=src_crs,
                 transform=src_t)
    c_inv = Affine.translation(0.13, -0.09) @ Affine.rotation(0.4, pivot=(x0 + 8, y0 - 8))
    field = _smooth_field(x0, y0)
    warp = with_field(ComposedWarp.for_flight(tmp_path / "f.tif", site, grid,
                                              aligned_to_stated=c_inv), field)
    at = grid @ Affine.translation(12, 9)
    col, row = warp.source_coords(at, (300, 280))
    cc, rr = np.meshgrid(np.arange(280) + 0.5, np.arange(300) + 0.5)
    px, py = Transformer.from_crs(site, src_crs, always_xy=True).transform(
        *(c_inv * field.apply(*(at * (cc, rr)))))
    ec, er = ~src_t * (px, py)
    # the field is evaluated exactly on the 16 px lattice, bilinear between: error ≤ h²/8·|D''|
    # (here ~0.003 px; for pipeline fields on 128 px nodes far less)
    assert np.abs(col - (ec - 0.5)).max() < 5e-3 and np.abs(row - (er - 0.5)).max() < 5e-3
    assert np.hypot(*field.displacement_m(*(at * (cc, rr)))).max() > 0.05   # ≥ 1 px moved
    whole = read_warped(warp, at, (300, 280))
    assert whole[1].mean() > 0.5
    for block, w in ((37, warp), (128, pickle.loads(pickle.dumps(warp)))):
        task = WarpRasterTask(w, str(tmp_path / f"b{block}.tif"), tuple(at)[:6], (300, 280),
                              block_px=block)
        warp_raster_task(pickle.loads(pickle.dumps(task)))
        with rasterio.open(task.dst_path) as ds:
            assert np.array_equal(ds.read(), whole[0])
            assert np.array_equal(ds.read_masks(1) > 0, whole[1])


def test_phase_correlate_search_radius():
    """``max_shift_px`` limits the peak search."""
    from geosim.align import phase_correlate

    grey = textured_rgb(256, 256, seed=5).astype(np.float32).mean(axis=0)
    moved = np.roll(grey, (-2, 3), axis=(0, 1))       # content 3 px right, 2 px up
    assert [round(v, 2) for v in phase_correlate(grey, moved, max_shift_px=8).shift_px] == \
        [3.0, -2.0]
    far = np.roll(grey, (0, 40), axis=(0, 1))
    assert abs(phase_correlate(grey, far).shift_px[0] - 40) < 0.05
    limited = phase_correlate(grey, far, max_shift_px=8)
    assert max(abs(v) for v in limited.shift_px) <= 9.5 and limited.confidence < 0.2


def test_one_regridder_file_and_array_agree(tmp_path):
    """diagnose's in-memory regridding is prepare's (``reproject_to_array``)."""
    from rasterio.crs import CRS

    from geosim.prepare.reproject import reproject_to_array, reproject_to_grid
    from tests.helpers import write_raster

    src = write_raster(tmp_path / "src.tif", textured_rgb(300, 300, seed=4),
                       crs="EPSG:28356", transform=Affine(0.05, 0, 300000, 0, -0.05, 6200015))
    crs = CRS.from_epsg(32756)
    t = Affine(0.05, 0, 299_990.0, 0, -0.05, 6_200_010.0)  # not the source grid: resampled
    reproject_to_grid(src, tmp_path / "g.tif", crs=crs, transform=t, shape=(256, 256))
    with rasterio.open(tmp_path / "g.tif") as ds:
        file_img = ds.read().astype(np.float32)
        file_ok = ds.read_masks(1) > 0
    data = reproject_to_array(src, crs=crs, transform=t, shape=(256, 256), max_bands=3,
                              what="src")
    arr, ok = data.array, data.valid
    assert data.transform == t and data.crs == crs and data.array.dtype == np.float32
    assert ok.any() and (~ok).any()
    assert np.array_equal(ok, file_ok)
    assert np.abs(arr[:, ok] - file_img[:, ok]).max() <= 0.5   # the file is rounded to uint8


@pytest.mark.parametrize("model", ["similarity", "auto"])
def test_shared_refinement_recovers_known_similarity(model):
    """The one refinement loop (flights and satellite anchor) on a known similarity."""
    from geosim.align import similarity_matrix
    from geosim.align.local import window_starts
    from geosim.align.refine import refine_with_windows

    grey = textured_rgb(512, 512, seed=6).astype(np.float32).mean(axis=0)
    centre = (255.5, 255.5)
    truth = np.vstack([similarity_matrix(0.4, 1.003, (2.3, -1.7), centre), [0, 0, 1]])
    # moving(q) = reference(truth⁻¹ q): reference pixel p shows at moving pixel truth @ p
    mov = cv2.warpAffine(grey, truth[:2], (512, 512), flags=cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REFLECT)
    ones = np.ones(grey.shape, bool)

    def warp(m):
        out = cv2.warpAffine(mov, m[:2], (512, 512), flags=cv2.INTER_CUBIC
                             | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
        return out, ones

    start = np.array([[1.0, 0, 2.0], [0, 1.0, -2.0], [0, 0, 1.0]])
    s = window_starts(512, 128, 96)
    r = refine_with_windows(grey, ones, warp, start, starts_r=s, starts_c=s, window_px=128,
                            min_confidence=0.1, upsample_factor=20, min_valid_fraction=0.5,
                            support_tolerance_px=1.0, model=model)
    corners = np.array([[0, 0, 1], [511, 0, 1], [0, 511, 1], [511, 511, 1]], float).T
    assert r.model == "similarity" and r.support > 0.9
    assert np.abs((r.matrix - truth) @ corners)[:2].max() < 0.05


def _serial_strips(ref: Path, mov: Path, shape: tuple[int, int], window_px: int,
                   step_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The window shifts strip by strip in one loop, straight from the kernel (the
    measurement before it was split into engine tasks)."""
    from rasterio.windows import Window

    from geosim.align.local import window_starts
    from geosim.prepare.alignment import read_grey_window

    sr = window_starts(shape[0], window_px, step_px)
    sc = window_starts(shape[1], window_px, step_px)
    dx = np.full((len(sr), len(sc)), np.nan)
    dy = np.full((len(sr), len(sc)), np.nan)
    for i, r in enumerate(sr):
        win = Window(0, int(r), int(sc[-1]) + window_px, window_px)
        rg, rv = read_grey_window(ref, win)
        mg, mv = read_grey_window(mov, win)
        s = measure_window_shifts(rg, mg, valid=rv & mv, window_px=window_px, step_px=step_px)
        dx[i], dy[i] = s.dx_px[0], s.dy_px[0]
    return dx, dy


@pytest.mark.parametrize("workers", [1, 2])
def test_local_shifts_in_tasks_equal_one_loop_on_any_engine(synthetic_pair, tmp_path,
                                                            monkeypatch, workers):
    """The local field's strips as engine tasks (rows grouped, columns chunked), in this
    process or on a 2-worker cluster: the same numbers, bit for bit, as one loop over the
    strips, and the known warp recovered."""
    from geosim.engine import open_engine
    from geosim.prepare import local_align as la
    from tests.helpers import write_raster

    ref, mov = synthetic_pair
    paths = [write_raster(tmp_path / f"{n}.tif", np.clip(a, 0, 255).astype(np.uint8),
                          transform=PX_T) for n, a in (("ref", ref), ("mov", mov))]
    monkeypatch.setattr(la, "ROWS_PER_TASK", 3)  # 15 rows of windows: 5 tasks per flight
    with open_engine(workers):
        many = la.measure_local_shifts_many(paths[0], {"B": paths[1], "C": paths[1]},
                                            window_px=128, step_px=64, windows_per_chunk=4)
    want_dx, want_dy = _serial_strips(paths[0], paths[1], ref.shape, 128, 64)
    for got in many.values():
        assert got.dx_px.shape == (15, 15)
        np.testing.assert_array_equal(got.dx_px, want_dx)
        np.testing.assert_array_equal(got.dy_px, want_dy)
    truth_x, _ = smooth_field_px(many["B"].x_px, many["B"].y_px, size=2048.0)
    ok = many["B"].confidence > 0.3
    assert ok.mean() > 0.5 and np.median(np.abs(many["B"].dx_px[ok] - truth_x[ok])) < 0.3
