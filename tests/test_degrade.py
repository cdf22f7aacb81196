"""Degradation: blur physics, reference vs fast path, masks, and exact geotransforms on disk."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
import scipy.fft
import scipy.signal
from affine import Affine
from click.testing import CliRunner
from rasterio.windows import from_bounds

from geosim.cli.main import cli
from geosim.config import FlightConfig, Parameters, SatelliteConfig, SiteConfig
from geosim.degrade import core
from geosim.degrade.steps import degrade_tile, degraded_transform, run_degrade
from geosim.errors import CalibrationError, ConfigError, InputFileError, RasterError
from geosim.io.raster import write_geotiff
from geosim.physics import psf
from tests.helpers import textured_rgb, write_raster

UAV_TF = Affine(0.05, 0.0, 250012.35, 0.0, -0.05, 6190003.7)


# --------------------------------------------------------------------------- kernels

@pytest.mark.parametrize(("n", "phi"), [(400, 10), (37, 3), (120, 4), (1003, 10)])
def test_cubic_taps_reproduce_cv2_resize(n: int, phi: int) -> None:
    rng = np.random.default_rng(n)
    src = rng.uniform(0, 255, (5, n))
    m = n // phi
    expected = cv2.resize(src[:, :m * phi], (m, 5), interpolation=cv2.INTER_CUBIC)
    index, weight = core.cv2_cubic_taps(m * phi, m)
    np.testing.assert_allclose((src[:, index] * weight).sum(-1), expected, atol=1e-9)


@pytest.mark.parametrize("q", [0.5, 2.0, 6.0])
def test_blur_conserves_flux_exactly(q: float) -> None:
    rng = np.random.default_rng(3)
    image = rng.uniform(0, 255, (3, 90, 130))
    blurred = core.blur(image, q=q, phi=10)
    np.testing.assert_allclose(blurred.mean(axis=(1, 2)), image.mean(axis=(1, 2)), rtol=1e-13)
    assert blurred.std() < image.std()
    flat = np.full((50, 60), 97.25)
    np.testing.assert_allclose(core.blur(flat, q=q, phi=10), 97.25, rtol=1e-13)


def test_blur_is_convolution_with_the_airy_kernel() -> None:
    """Against a literal spatial convolution (symmetric padding) with the paper's kernel."""
    q, phi = 1.0, 4
    image = textured_rgb(150, 170, seed=7)[1].astype(float)
    kernel = psf.pupil_psf(q, phi=phi, size_px=2 * 150 + 1)  # covers the whole image
    h = kernel.shape[0] // 2
    padded = np.pad(image, h, mode="symmetric")  # … c b a | a b c … (cv2 BORDER_REFLECT)
    literal = scipy.signal.fftconvolve(padded, kernel, mode="valid")
    held = psf.encircled_energy(h, q=q, phi=phi)
    # Only the Airy wings beyond the kernel (1 − EE of the energy) can differ.
    assert np.abs(core.blur(image, q=q, phi=phi) - literal).max() < (1 - held) * 255


@pytest.mark.parametrize("q", [0.5, 1.0, 4.34, 8.0])
def test_fast_agrees_with_reference_within_one_dn(q: float) -> None:
    image = textured_rgb(400, 400, seed=1)
    ref, vref = core.degrade_array(image, q=q, method="reference")
    fast, vfast = core.degrade_array(image, q=q, method="fast")
    assert ref.shape == fast.shape == (3, 40, 40)
    assert np.abs(ref - fast).max() < 1e-3  # same numbers before rounding
    diff = np.abs(core.to_dtype(ref, np.uint8).astype(int) - core.to_dtype(fast, np.uint8))
    assert diff.max() <= 1
    assert vref.all() and vfast.all()


@pytest.mark.parametrize("dtype, shape, q_phi", [
    (np.uint8, (1024, 768), 43.4),      # two levels, the first exact in int16
    (np.uint8, (512, 1000), 20.0),      # float levels only (cutoff too high for int16's)
    (np.float32, (768, 640), 43.4),     # a filled (float) band
    (np.uint8, (515, 640), 43.4),       # odd rows: no level at all
    (np.float64, (512, 512), 1.4),      # cutoff above Nyquist (Q φ < 2): no level at all
])
def test_reduction_keeps_the_low_dct_coefficients(dtype, shape: tuple[int, int],
                                                  q_phi: float) -> None:
    # truth: the full-resolution orthonormal DCT-II of the band (scipy), below the cutoff,
    # of a texture with strong content near Nyquist (the worst case for aliasing)
    rng = np.random.default_rng(7)
    band = rng.integers(0, 256, shape).astype(dtype)
    reduced, g_r, g_c = core.reduce_band_limited(band, q_phi)
    k_r = core.n_coefficients(shape[0], q=q_phi, phi=1)
    k_c = core.n_coefficients(shape[1], q=q_phi, phi=1)
    truth = scipy.fft.dctn(band.astype(np.float64), type=2, norm="ortho")[:k_r, :k_c]
    if shape[0] % 2 or q_phi < 4:
        assert reduced is band
        return
    assert reduced.shape[0] < shape[0]
    got = scipy.fft.dctn(reduced.astype(np.float64), type=2, norm="ortho")[:k_r, :k_c]
    got /= np.outer(g_r[:k_r], g_c[:k_c])
    # white noise: every coefficient ~ 74 DN; the alias leak is ≤ ALIAS_TOLERANCE of one
    # (per axis and level), so the error is a small fraction of a coefficient
    assert np.abs(got - truth).max() < 0.02 * np.abs(truth[1:, 1:]).mean()
    assert abs(got[0, 0] - truth[0, 0]) < 1e-3 * abs(truth[0, 0])


@pytest.mark.parametrize("shape", [(16, 16), (18, 30), (130, 258), (300, 202), (1024, 768)])
def test_first_level_equals_opencv_filter_then_decimation(shape: tuple[int, int]) -> None:
    # truth: OpenCV's full-resolution separable filter [1, 3, 3, 1] (anchor 1, reflected
    # border), kept at every other row and column; the level evaluates only those, in
    # strips of rows (shapes above span several strips and a partial last one)
    kernel = np.array([1, 3, 3, 1], np.float32)
    rng = np.random.default_rng(11)
    for band in (rng.integers(0, 256, shape, dtype=np.uint8), np.full(shape, 255, np.uint8)):
        full = cv2.sepFilter2D(band.astype(np.float64), cv2.CV_64F, kernel, kernel,
                               anchor=(1, 1), borderType=cv2.BORDER_REFLECT)
        got = core.halve_binomial4_uint8(band)
        assert got.dtype == np.float32 and got.shape == (shape[0] // 2, shape[1] // 2)
        np.testing.assert_array_equal(got, full[::2, ::2] / 64)


def test_reference_is_the_paper_operation() -> None:
    """method="reference" = blur then cv2.resize(INTER_CUBIC), literally."""
    image = textured_rgb(200, 230, seed=2)
    out, _ = core.degrade_array(image, q=2.0, phi=10, method="reference")
    blurred = core.blur(image, q=2.0, phi=10)
    for b in range(3):
        expected = cv2.resize(blurred[b, :200, :230], (23, 20), interpolation=cv2.INTER_CUBIC)
        np.testing.assert_allclose(out[b], expected, atol=1e-9)


def test_partial_sizes_masks_and_obscuration() -> None:
    image = textured_rgb(233, 318, seed=3)  # not multiples of phi: trailing pixels dropped
    valid = np.ones((233, 318), bool)
    valid[:57, :121] = False
    valid[150, 200] = False  # one UAV pixel invalidates exactly its 0.5 m pixel
    ref, vref = core.degrade_array(image, q=1.5, valid=valid, method="reference",
                                   obscuration=0.3)
    fast, vfast = core.degrade_array(image, q=1.5, valid=valid, method="fast",
                                     obscuration=0.3)
    assert ref.shape == (3, 23, 31)
    np.testing.assert_array_equal(vref, vfast)
    expected = np.ones((23, 31), bool)
    expected[:6, :13] = False
    expected[15, 20] = False
    np.testing.assert_array_equal(vfast, expected)
    assert np.abs(ref - fast)[:, vfast].max() < 1e-3
    assert (fast[:, ~vfast] == 0).all()


def test_values_under_the_mask_do_not_matter() -> None:
    image = textured_rgb(300, 300, seed=4)
    valid = np.ones((300, 300), bool)
    valid[100:180, 40:260] = False
    dark, bright = image.copy(), image.copy()
    dark[:, ~valid], bright[:, ~valid] = 0, 255
    a, _ = core.degrade_array(dark, q=2.0, valid=valid)
    b, _ = core.degrade_array(bright, q=2.0, valid=valid)
    np.testing.assert_array_equal(a, b)


def test_fill_invalid_keeps_valid_and_stays_in_range() -> None:
    image = textured_rgb(120, 140, seed=5).astype(np.float32)
    valid = np.ones((120, 140), bool)
    valid[30:90, 50:100] = False
    filled = core.fill_invalid(image, valid)
    np.testing.assert_array_equal(filled[:, valid], image[:, valid])
    for b in range(3):
        assert image[b, valid].min() <= filled[b, ~valid].min()
        assert filled[b, ~valid].max() <= image[b, valid].max()
    flat = np.full((40, 50), 42.0)
    mask = np.zeros((40, 50), bool)
    mask[5, 7] = True
    np.testing.assert_allclose(core.fill_invalid(flat, mask), 42.0)


def _fill_invalid_plain(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The pull-push fill written plainly (geosim's implementation before it was made to
    share the weights, skip the full-resolution mean and take level 1 in integers)."""
    stack = (image[None] if image.ndim == 2 else image).astype(np.float32)
    weight = valid.astype(np.float32)
    out = np.empty_like(stack)
    for i, band in enumerate(stack):
        levels = [(band * weight, weight)]
        while max(levels[-1][1].shape) > 1:
            a, w = levels[-1]
            size = (max(1, (a.shape[1] + 1) // 2), max(1, (a.shape[0] + 1) // 2))
            levels.append((cv2.resize(a, size, interpolation=cv2.INTER_AREA),
                           cv2.resize(w, size, interpolation=cv2.INTER_AREA)))
        estimate = None
        for a, w in reversed(levels):
            has = w > 1e-6
            mean = np.divide(a, w, out=np.zeros_like(a), where=has)
            if estimate is None:
                estimate = mean
            else:
                up = cv2.resize(estimate, (a.shape[1], a.shape[0]),
                                interpolation=cv2.INTER_LINEAR)
                estimate = np.where(has, mean, up)
        out[i] = np.where(valid, band, estimate)
    return out[0] if image.ndim == 2 else out


@pytest.mark.parametrize(("shape", "dtype"), [((3, 600, 800), np.uint8), ((3, 601, 800), np.uint8),
                                              ((2, 512, 333), np.uint8),
                                              ((3, 600, 800), np.uint16),
                                              ((600, 800), np.float32), ((1, 1), np.uint8),
                                              ((2, 2), np.uint8)])
def test_fill_invalid_equals_plain_pull_push(shape: tuple[int, ...], dtype: type) -> None:
    """Bit for bit the plain pyramid, for uint8 (integer level 1 on even sizes), odd
    sizes, other dtypes; masks with holes, edges and isolated valid pixels; all-255."""
    rng = np.random.default_rng(sum(shape))
    rows, cols = shape[-2:]
    top = 255 if dtype == np.uint8 else 4000
    image = rng.integers(0, top + 1, shape).astype(dtype)
    if dtype == np.float32:
        image = image + rng.random(shape).astype(np.float32)
    masks = [rng.random((rows, cols)) > 0.3]
    edge = np.ones((rows, cols), bool)
    edge[:, : cols // 3] = False
    edge[: rows // 4] = False
    masks.append(edge)
    sparse = np.zeros((rows, cols), bool)
    sparse[rows // 2, cols // 2] = True
    masks.append(sparse)
    for valid in (m for m in masks if m.any()):
        expected = _fill_invalid_plain(image, valid)
        np.testing.assert_array_equal(core.fill_invalid(image, valid), expected)
        filler = core.InvalidFill(valid, (rows, cols))
        stack = image[None] if image.ndim == 2 else image
        for b, band in enumerate(stack):
            out = np.full((rows, cols), np.nan, np.float32)
            filler.fill(band, out=out)
            np.testing.assert_array_equal(out, expected[b] if image.ndim == 3 else expected)
    full = np.full((rows, cols), top, dtype)
    np.testing.assert_array_equal(core.fill_invalid(full, masks[-1]),
                                  _fill_invalid_plain(full, masks[-1]))


def test_partial_tile_fill_same_on_one_and_two_threads() -> None:
    """The fill (OpenCV resizes) and the fast path give the same bits whatever the task's
    thread budget (one by default, more with ``GEOSIM_THREADS``)."""
    from geosim.engine import task_limits

    image = textured_rgb(640, 480, seed=9)
    valid = np.ones((640, 480), bool)
    valid[:, :130] = False
    valid[:70] = False
    outs = []
    for threads in (1, 2):
        with task_limits(threads):
            outs.append((core.fill_invalid(image, valid),
                         core.degrade_array(image, q=4.34, valid=valid, reuse_buffers=True)[0]))
    for a, b in zip(*outs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_to_dtype_rounds_and_clips() -> None:
    out = core.to_dtype(np.array([-3.0, 0.5, 1.5, 2.49, 254.5, 300.0]), np.uint8)
    np.testing.assert_array_equal(out, [0, 0, 2, 2, 254, 255])
    assert out.dtype == np.uint8
    assert core.to_dtype(np.array([1.25]), np.float32).dtype == np.float32


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"q": 0.0}, "q must"), ({"q": -1.0}, "q must"), ({"q": float("nan")}, "q must"),
    ({"q": 1.0, "phi": 2.5}, "phi"), ({"q": 1.0, "phi": 0}, "phi"),
    ({"q": 1.0, "method": "bilinear"}, "method"), ({"q": 1.0, "obscuration": 1.2}, "obscur"),
    ({"q": 1.0, "valid": np.ones((5, 5), bool)}, "mask shape"),
])
def test_bad_inputs_raise(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        core.degrade_array(np.zeros((3, 40, 40), np.uint8), **kwargs)


def test_bad_image_shapes_raise() -> None:
    with pytest.raises(ValueError, match="smaller than one satellite pixel"):
        core.degrade_array(np.zeros((3, 8, 40)), q=1.0, phi=10)
    with pytest.raises(ValueError, match="bands-first"):
        core.degrade_array(np.zeros((1, 3, 40, 40)), q=1.0)


# --------------------------------------------------------------------------- GeoTIFF step

def _site(tmp_path: Path, flight_images: dict[str, Path], sat: Path | None = None,
          **params: float) -> SiteConfig:
    now = dt.datetime(2021, 7, 15, 13, 10)
    flights = tuple(FlightConfig(id=k, image=v, acquired=now) for k, v in flight_images.items())
    return SiteConfig(path=None, name="synthetic", crs="EPSG:28356",
                      reference_flight=next(iter(flight_images)), flights=flights,
                      satellite=None if sat is None else SatelliteConfig(image=sat, acquired=now),
                      paddocks=None, parameters=Parameters(tile_px=500, **params))


def _write_tiles(out: Path, flight: str, scene: np.ndarray, transform: Affine,
                 tile_px: int = 500, nodata_box: tuple[slice, slice] | None = None) -> list[str]:
    ids = []
    for r in range(0, scene.shape[1] - tile_px + 1, tile_px):
        for c in range(0, scene.shape[2] - tile_px + 1, tile_px):
            tid = f"r{r // tile_px:03d}_c{c // tile_px:03d}"
            tile = scene[:, r:r + tile_px, c:c + tile_px].copy()
            if nodata_box is not None and tid == "r000_c000":
                tile[:, nodata_box[0], nodata_box[1]] = 0
            (out / "tiles" / flight).mkdir(parents=True, exist_ok=True)
            write_raster(out / "tiles" / flight / f"{tid}.tif", tile,
                         transform=transform @ Affine.translation(c, r),
                         nodata=0 if nodata_box is not None else None)
            ids.append(tid)
    return ids


def test_degraded_tiles_have_exact_transforms_masks_and_tags(tmp_path: Path) -> None:
    scene = textured_rgb(500, 1000, seed=8)
    scene[scene == 0] = 1  # 0 is nodata
    out = tmp_path / "run"
    ids = _write_tiles(out, "PA1", scene, UAV_TF, nodata_box=(slice(0, 95), slice(0, 140)))
    site = _site(tmp_path, {"PA1": out / "tiles" / "PA1" / f"{ids[0]}.tif"})
    summary = run_degrade(site, out, q=2.5).record
    assert summary["tiles"] == 2 and summary["q"] == 2.5 and summary["q_source"] == "user"
    for tid in ids:
        src_path = out / "tiles" / "PA1" / f"{tid}.tif"
        with rasterio.open(src_path) as src, \
                rasterio.open(out / "degraded" / "PA1" / f"{tid}.tif") as dst:
            a = src.transform
            # exact: same origin, pixel size × phi (equality of Affine, not approx)
            assert dst.transform == Affine(a.a * 10, a.b * 10, a.c, a.d * 10, a.e * 10, a.f)
            assert dst.transform == degraded_transform(src.transform, 10)
            assert dst.crs == src.crs
            assert (dst.width, dst.height, dst.count) == (50, 50, 3)
            assert dst.dtypes == ("uint8",) * 3
            assert dst.bounds == pytest.approx(src.bounds, abs=1e-9)
            tags = dst.tags()
            assert float(tags["GEOSIM_Q"]) == 2.5 and tags["GEOSIM_METHOD"] == "fast"
            assert tags["GEOSIM_STEP"] == "degrade" and tags["GEOSIM_VERSION"]
            assert json.loads(tags["GEOSIM_PARAMS"])["sat_gsd_m"] == 0.5
            assert json.loads(tags["GEOSIM_SOURCES"]) == [f"tiles/PA1/{tid}.tif"]
            mask = dst.dataset_mask() > 0
            src_valid = src.dataset_mask() > 0
            # a lossless COG holding exactly the kernel's rounded output
            assert dst.tags(ns="IMAGE_STRUCTURE")["LAYOUT"] == "COG"
            assert dst.compression.name == "deflate"
            fast, _ = core.degrade_array(src.read(), q=2.5, phi=10, valid=src_valid)
            np.testing.assert_array_equal(dst.read()[:, mask],
                                          core.to_dtype(fast, np.uint8)[:, mask])
        expected = src_valid.reshape(50, 10, 50, 10).all(axis=(1, 3))
        np.testing.assert_array_equal(mask, expected)
    with rasterio.open(out / "degraded" / "PA1" / "r000_c000.tif") as dst:
        m = dst.dataset_mask() > 0
    assert not m[:9, :14].any() and m[10:, 14:].all()  # 95 × 140 px hole → 9.5 × 14 pixels


def test_internal_mask_of_a_tile_reaches_the_degraded_tile(tmp_path: Path) -> None:
    # a tile as `geosim tile` writes it: a COG with an internal (1-bit) mask
    image = textured_rgb(300, 400, seed=9)
    valid = np.ones((300, 400), bool)
    valid[:37, :122] = False
    valid[205, 318] = False
    src = write_geotiff(tmp_path / "tile.tif", image, transform=UAV_TF, crs="EPSG:28356",
                        mask=valid)
    degrade_tile(src, tmp_path / "out.tif", q=2.0, phi=10)
    with rasterio.open(tmp_path / "out.tif") as dst:
        mask = dst.dataset_mask() > 0
        pixels = dst.read()
    expected = core.block_all(valid, 10)
    assert not expected.all() and expected.sum() == 30 * 40 - 4 * 13 - 1
    np.testing.assert_array_equal(mask, expected)
    fast, _ = core.degrade_array(image, q=2.0, phi=10, valid=valid)
    np.testing.assert_array_equal(pixels[:, mask], core.to_dtype(fast, np.uint8)[:, mask])


def test_degraded_tile_overlays_the_satellite_scene(tmp_path: Path) -> None:
    """Phase correlation between a degraded tile and the satellite at its bounds: < 0.1 px."""
    scene = textured_rgb(1000, 1000, seed=9)
    sat, _ = core.degrade_array(scene, q=2.0)
    sat_path = write_raster(tmp_path / "satellite.tif", core.to_dtype(sat, np.uint8),
                            transform=UAV_TF @ Affine.scale(10))
    out = tmp_path / "run"
    tile = scene[:, 300:800, 200:700].copy()
    (out / "tiles" / "A").mkdir(parents=True)
    write_raster(out / "tiles" / "A" / "r000_c000.tif", tile,
                 transform=UAV_TF @ Affine.translation(200, 300))
    site = _site(tmp_path, {"A": out / "tiles" / "A" / "r000_c000.tif"})
    run_degrade(site, out, q=2.0, method="reference")
    with rasterio.open(out / "degraded" / "A" / "r000_c000.tif") as d, \
            rasterio.open(sat_path) as s:
        degraded = d.read(2).astype(np.float64)
        win = from_bounds(*d.bounds, transform=s.transform)
        assert (round(win.col_off), round(win.row_off)) == (20, 30)
        truth = s.read(2, window=win).astype(np.float64)
        shifted = s.read(2, window=win.__class__(win.col_off + 1, win.row_off, 50, 50))
    hann = cv2.createHanningWindow((50, 50), cv2.CV_64F)
    # OpenCV 5 multiplies its inputs by the window in place: pass copies (reused below)
    (dx, dy), _ = cv2.phaseCorrelate(truth.copy(), degraded.copy(), hann)
    assert abs(dx) < 0.1 and abs(dy) < 0.1
    (dx, dy), _ = cv2.phaseCorrelate(shifted.astype(np.float64), degraded.copy(), hann)
    assert abs(abs(dx) - 1) < 0.2  # the measurement sees a one-pixel error


def _highpass(grey: np.ndarray) -> np.ndarray:
    g = grey.astype(np.float32)
    return g - cv2.GaussianBlur(g, (0, 0), 4)


@pytest.mark.slow
def test_sample_site_degraded_tiles_overlay_satellite(samples_dir: Path, tmp_path: Path) -> None:
    """Sample site: the degraded tiles sit on the satellite scene up to the misregistration
    the sample deliberately contains (satellite shift + the reference flight's georeference
    error, from truth.json), within one 0.5 m pixel. Shadows and cattle differ between the
    dates, so the offset is measured on high-passed images by normalised cross-correlation,
    pooled over all degraded tiles of the reference flight."""
    from geosim.config import load_site
    from geosim.pipeline import run_pipeline

    site = load_site(samples_dir / "site.toml")
    truth = json.loads((samples_dir / "truth.json").read_text())
    out = tmp_path / "run"
    run_pipeline(site, out, only=["grid", "footprints", "align", "tiles"], echo=lambda s: None)
    run_degrade(site, out, q=2.0)
    ref = site.reference_flight
    m = 6
    scores, expected = [], []
    with rasterio.open(out / "grid" / "satellite.tif") as s:
        for path in sorted((out / "degraded" / ref).glob("*.tif")):
            with rasterio.open(path) as d:
                deg = d.read([1, 2, 3]).mean(axis=0)
                win = from_bounds(*d.bounds, transform=s.transform)
                assert win.col_off == round(win.col_off) and win.row_off == round(win.row_off)
                cx, cy = d.xy(d.height / 2, d.width / 2)
            big = rasterio.windows.Window(win.col_off - m, win.row_off - m, d.width + 2 * m,
                                          d.height + 2 * m)
            sat = s.read([1, 2, 3], window=big, boundless=True).mean(axis=0)
            scores.append(cv2.matchTemplate(_highpass(sat), _highpass(deg),
                                            cv2.TM_CCOEFF_NORMED))
            t2s = np.array(truth["flights"][ref]["georef_error"]["true_to_stated"])
            stated = t2s @ [cx, cy, 1.0]
            shift = np.array(truth["satellite"]["effects"]["misregistration"]["shift_m"])
            rel = shift - (stated - [cx, cy])  # satellite relative to the flight, metres
            expected.append((rel[0] / 0.5, -rel[1] / 0.5))  # (columns, rows) in pixels
    assert scores, "no degraded tile of the reference flight"
    res = np.mean(scores, axis=0)
    y, x = np.unravel_index(int(res.argmax()), res.shape)
    assert 0 < x < 2 * m and 0 < y < 2 * m, "no correlation peak inside the search range"

    def vertex(a: float, b: float, c: float) -> float:
        return 0.5 * (a - c) / (a - 2 * b + c)

    dx = x - m + vertex(res[y, x - 1], res[y, x], res[y, x + 1])
    dy = y - m + vertex(res[y - 1, x], res[y, x], res[y + 1, x])
    ex, ey = np.mean(expected, axis=0)
    assert abs(dx - ex) < 1.0 and abs(dy - ey) < 1.0, ((dx, dy), (ex, ey))


def test_run_degrade_uses_calibrated_mean_q(tmp_path: Path) -> None:
    scene = textured_rgb(500, 500, seed=10)
    out = tmp_path / "run"
    _write_tiles(out, "A", scene, UAV_TF)
    site = _site(tmp_path, {"A": out / "tiles" / "A" / "r000_c000.tif"})
    with pytest.raises(InputFileError, match="geosim calibrate"):
        run_degrade(site, out)
    (out / "calibration.json").write_text(json.dumps({"mean_q": None}))
    with pytest.raises(CalibrationError, match="--q"):
        run_degrade(site, out)
    (out / "calibration.json").write_text(json.dumps({"mean_q": 4.34}))
    result = run_degrade(site, out, method="reference")
    assert result.record["q"] == 4.34 and result.record["q_source"] == "calibration.json"
    assert "geosim diagnose" in result.warnings[0]
    with rasterio.open(out / "degraded" / "A" / "r000_c000.tif") as ds:
        assert float(ds.tags()["GEOSIM_Q"]) == 4.34
        got = ds.read()
    expected, _ = core.degrade_array(scene, q=4.34, method="reference")
    np.testing.assert_array_equal(got, core.to_dtype(expected, np.uint8))


def test_run_degrade_bad_inputs(tmp_path: Path) -> None:
    out = tmp_path / "run"
    scene = textured_rgb(500, 500, seed=11)
    site = _site(tmp_path, {"A": tmp_path / "a.tif"})
    with pytest.raises(InputFileError, match="geosim tile"):
        run_degrade(site, out, q=2.0)
    _write_tiles(out, "A", scene, UAV_TF)
    with pytest.raises(ConfigError):
        run_degrade(site, out, q=-1.0)
    with pytest.raises(ConfigError):
        run_degrade(site, out, q=2.0, method="nearest")
    wrong = _site(tmp_path, {"A": tmp_path / "a.tif"}, uav_gsd_m=0.1, sat_gsd_m=1.0)
    with pytest.raises(RasterError, match="uav_gsd_m"):
        run_degrade(wrong, out, q=2.0)
    foreign = out / "degraded" / "A" / "r009_c009.tif"
    foreign.parent.mkdir(parents=True)
    foreign.write_bytes(b"old")
    result = run_degrade(site, out, q=2.0)
    # a file geosim did not write (not in run.json) is never deleted nor listed; stale
    # degraded tiles of an earlier run are removed by the runner (test_run_records.py)
    assert foreign.read_bytes() == b"old"
    assert "degraded/A/r009_c009.tif" not in result.outputs
    assert "degraded/A/r000_c000.tif" in result.outputs


def test_cli_degrade(tmp_path: Path) -> None:
    scene = textured_rgb(500, 500, seed=12)
    out = tmp_path / "run"
    _write_tiles(out, "A", scene, UAV_TF)
    flight = write_raster(tmp_path / "A.tif", scene, transform=UAV_TF)
    toml = tmp_path / "site.toml"
    toml.write_text(f'[parameters]\ntile_px = 500\n\n[[flights]]\nid = "A"\nimage = "{flight}"\n'
                    'acquired = 2021-07-15T13:10:00+10:00\n')
    runner = CliRunner()
    result = runner.invoke(cli, ["degrade", str(toml), "--out", str(out), "--q", "1.5",
                                 "--method", "reference"])
    assert result.exit_code == 0, result.output
    assert "1 tile(s) degraded" in result.output
    assert (out / "degraded" / "A" / "r000_c000.tif").is_file()
    result = runner.invoke(cli, ["degrade", str(toml), "--out", str(out), "--q", "-2"])
    assert result.exit_code == 2
    result = runner.invoke(cli, ["degrade", str(toml), "--out", str(tmp_path / "empty")])
    assert result.exit_code == 2 and "geosim: error:" in result.output


@pytest.mark.parametrize("shape", [(16, 16), (18, 30), (130, 258), (300, 202), (1024, 768)])
def test_float_level_equals_opencv_filter_then_decimation(shape: tuple[int, int]) -> None:
    # truth: OpenCV's separable [1, 5, 10, 10, 5, 1]/32 on the whole band (anchor 2,
    # reflected border), kept at every other row and column; the level filters strips of
    # rows (shapes above span several strips and a partial last one)
    kernel = np.array([1, 5, 10, 10, 5, 1], np.float32) / 32
    rng = np.random.default_rng(13)
    for band in (rng.normal(100, 40, shape).astype(np.float32),
                 rng.integers(0, 256, shape).astype(np.float32)):
        full = cv2.sepFilter2D(band, cv2.CV_32F, kernel, kernel, anchor=(2, 2),
                               borderType=cv2.BORDER_REFLECT)
        got = core.halve_binomial6(band)
        assert got.dtype == np.float32 and got.shape == (shape[0] // 2, shape[1] // 2)
        np.testing.assert_array_equal(got, full[::2, ::2])
    # the first level of a uint8 band (multiples of 1/64): the 5-tap + block-mean form is
    # exact, so it gives the very same numbers
    for band8 in (rng.integers(0, 256, shape, dtype=np.uint8), np.full(shape, 255, np.uint8)):
        if shape[0] < 4 or shape[1] < 4:
            continue
        level1 = core.halve_binomial4_uint8(band8)
        if level1.shape[0] % 2 or level1.shape[1] % 2:
            continue
        full = cv2.sepFilter2D(level1, cv2.CV_32F, kernel, kernel, anchor=(2, 2),
                               borderType=cv2.BORDER_REFLECT)
        out = np.full((level1.shape[0] // 2, level1.shape[1] // 2), np.nan, np.float32)
        got = core.halve_binomial6(level1, out=out, exact_sums=True)
        assert got is out
        np.testing.assert_array_equal(got, full[::2, ::2])


def test_degrade_command_does_not_import_the_q_solver() -> None:
    # `geosim degrade` imports the steps module, which also holds calibration: SciPy's
    # optimizer (≈ 0.15 CPU-s and 25 MB at start-up, docs/degradation.md) and the PSF
    # module's special functions are imported only where calibration uses them. A fresh
    # interpreter, since this test process has imported them already.
    import os
    import subprocess
    import sys

    code = ("import sys, geosim.cli.main, geosim.cli.degrade, geosim.degrade.steps; "
            "print(sorted(m for m in ('scipy.optimize', 'scipy.integrate', "
            "'geosim.physics.psf') if m in sys.modules))")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, cwd=root, env={**os.environ, "PYTHONPATH": str(root)})
    assert out.stdout.strip() == "[]"
    # and calibration still finds them when it solves for Q (its tests run the solver)
    from geosim.degrade.steps import guard_px

    assert guard_px(4.34) == min(24, int(np.ceil(psf.first_zero_px(4.34, phi=1))))
