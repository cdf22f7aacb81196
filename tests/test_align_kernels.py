"""Known-answer tests of the registration kernels (geosim.align).

Truth never comes from the code under test: images are moved with OpenCV
(``cv2.warpAffine`` / ``cv2.getRotationMatrix2D`` / ``cv2.remap``), NumPy
(``np.roll``, ``np.rot90``) or an exact Fourier shift, and the known transform
must be recovered.
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
from rasterio.windows import Window
from scipy import ndimage

from geosim.align import (
    DEFAULT_MIN_CONFIDENCE,
    SimilarityTransform,
    local_shift_field,
    phase_correlate,
    register_similarity,
    similarity_matrix,
)
from geosim.errors import AlignmentError, GeosimError, RasterError

# --------------------------------------------------------------------------- helpers


def texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Multi-scale filtered Gaussian noise in 20..220 grey levels (float32)."""
    rng = np.random.default_rng(seed)
    out = np.zeros(shape)
    for sigma in (1, 2, 4, 8, 16, 32):
        out += cv2.GaussianBlur(rng.normal(size=shape), (0, 0), sigma) * sigma
    out -= out.min()
    return (20 + 200 * out / out.max()).astype(np.float32)


BIG = 900                      # source texture side (px)
WIN = 512                      # registered window side (px)
OFF = (BIG - WIN) // 2         # window offset inside the source
CENTRE = ((WIN - 1) / 2.0, (WIN - 1) / 2.0)


@pytest.fixture(scope="module")
def source() -> np.ndarray:
    return texture((BIG, BIG), seed=1)


def warped_pair(source: np.ndarray, rotation_deg: float, scale: float, dx: float, dy: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference window and moving window whose content is the reference rotated
    (cv2 sign: counter-clockwise as displayed) and scaled about the window centre
    and moved by (dx, dy) px; returns (reference, moving, cv2 2×3 truth in window px)."""
    big_centre = (OFF + CENTRE[0], OFF + CENTRE[1])
    a_big = cv2.getRotationMatrix2D(big_centre, rotation_deg, scale)
    a_big[:, 2] += (dx, dy)
    moved = cv2.warpAffine(source, a_big, (BIG, BIG), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    sl = (slice(OFF, OFF + WIN), slice(OFF, OFF + WIN))
    truth = cv2.getRotationMatrix2D(CENTRE, rotation_deg, scale)
    truth[:, 2] += (dx, dy)
    return source[sl].copy(), moved[sl].copy(), truth


def fourier_shift(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Exact (band-limited, circular) shift of the content by (+dx, +dy) px."""
    spec = ndimage.fourier_shift(np.fft.fft2(image), (dy, dx))
    return np.fft.ifft2(spec).real.astype(np.float32)


# --------------------------------------------------------------------------- phase_correlate


def test_shift_sign_integer_roll() -> None:
    ref = texture((256, 256), seed=2)
    mov = np.roll(ref, shift=(5, -3), axis=(0, 1))  # content 3 px left, 5 px down
    pc = phase_correlate(ref, mov)
    assert pc.shift_px == pytest.approx((-3.0, 5.0), abs=0.02)
    assert pc.confidence > 0.5
    # the documented use: sampling moving at (x + dx, y + dy) aligns it onto reference
    dx, dy = pc.shift_px
    back = ndimage.shift(mov, (-dy, -dx), order=3, mode="wrap")
    assert np.abs(back - ref)[8:-8, 8:-8].max() < 1.0


@pytest.mark.parametrize(("dx", "dy"), [(3.37, -7.81), (-12.25, 4.75), (0.5, 0.5), (0.1, -0.9)])
def test_subpixel_translation_fourier_shift(dx: float, dy: float) -> None:
    full = texture((768, 768), seed=3)
    mov = fourier_shift(full, dx, dy)
    sl = (slice(128, 640), slice(128, 640))
    pc = phase_correlate(full[sl], mov[sl])
    assert pc.shift_px == pytest.approx((dx, dy), abs=0.05)
    assert 0.5 < pc.confidence <= 1.0
    assert 0.0 < pc.peak <= 1.0


@pytest.mark.parametrize(("dx", "dy"), [(3.37, -7.81), (-5.62, 9.13)])
def test_subpixel_translation_warpaffine_noise_and_masks(source: np.ndarray, dx: float,
                                                         dy: float) -> None:
    ref, mov, _ = warped_pair(source, 0.0, 1.0, dx, dy)
    rng = np.random.default_rng(4)
    noisy_ref = ref + rng.normal(0, 6, ref.shape).astype(np.float32)
    noisy_mov = mov + rng.normal(0, 6, mov.shape).astype(np.float32)
    assert phase_correlate(ref, mov).shift_px == pytest.approx((dx, dy), abs=0.05)
    assert phase_correlate(noisy_ref, noisy_mov).shift_px == pytest.approx((dx, dy), abs=0.05)
    # nodata (255) blocks in both images, flagged invalid; bands-first RGB input
    valid_mov = np.ones(mov.shape, bool)
    valid_mov[:, :140] = False
    valid_mov[380:, 300:] = False
    valid_ref = np.ones(ref.shape, bool)
    valid_ref[:90, 200:420] = False
    mov_nd = np.where(valid_mov, noisy_mov, 255).astype(np.float32)
    ref_nd = np.where(valid_ref, noisy_ref, 255).astype(np.float32)
    pc = phase_correlate(np.stack([ref_nd] * 3), np.stack([mov_nd] * 3),
                         valid_reference=valid_ref, valid_moving=valid_mov)
    assert pc.shift_px == pytest.approx((dx, dy), abs=0.05)
    assert pc.confidence > 0.5


def test_flat_small_and_mismatched_inputs() -> None:
    tex = texture((128, 128), seed=5)
    with pytest.raises(AlignmentError, match="flat"):
        phase_correlate(tex, np.full((128, 128), 7.0))
    with pytest.raises(AlignmentError, match="too small"):
        phase_correlate(tex[:20, :20], tex[:20, :20])
    with pytest.raises(RasterError, match="differ in shape"):
        phase_correlate(tex, tex[:100])
    with pytest.raises(AlignmentError, match="valid"):
        phase_correlate(tex, tex, valid_moving=np.zeros((128, 128), bool))
    assert issubclass(AlignmentError, GeosimError)


def test_unrelated_images_have_low_confidence() -> None:
    confs = [phase_correlate(texture((256, 256), seed=10 + k),
                             texture((256, 256), seed=40 + k)).confidence for k in range(6)]
    assert max(confs) < DEFAULT_MIN_CONFIDENCE
    rng = np.random.default_rng(6)
    noise = phase_correlate(rng.normal(size=(256, 256)), rng.normal(size=(256, 256)))
    assert noise.confidence < DEFAULT_MIN_CONFIDENCE


# --------------------------------------------------------------------------- register_similarity


def test_similarity_matrix_matches_opencv() -> None:
    m = similarity_matrix(12.5, 1.07, (3.0, -4.0), (100.0, 60.0))
    want = cv2.getRotationMatrix2D((100.0, 60.0), 12.5, 1.07)
    want[:, 2] += (3.0, -4.0)
    np.testing.assert_allclose(m, want, atol=1e-12)
    t = SimilarityTransform.from_matrix(want, (100.0, 60.0))
    assert (t.rotation_deg, t.scale) == pytest.approx((12.5, 1.07), abs=1e-12)
    assert t.shift_px == pytest.approx((3.0, -4.0), abs=1e-9)


CASES = [  # rotation_deg, scale, dx, dy
    (-0.5, 0.995, 3.37, -7.81),
    (5.0, 1.05, 2.5, 1.5),
    (30.0, 0.92, -10.2, 6.6),
    (-120.0, 1.1, 4.0, -3.3),   # beyond 90°: the 180° ambiguity must be resolved
]


@pytest.mark.parametrize(("rotation_deg", "scale", "dx", "dy"), CASES)
def test_register_similarity_known_transform(source: np.ndarray, rotation_deg: float,
                                             scale: float, dx: float, dy: float) -> None:
    ref, mov, truth = warped_pair(source, rotation_deg, scale, dx, dy)
    rng = np.random.default_rng(7)
    t = register_similarity(ref + rng.normal(0, 4, ref.shape).astype(np.float32),
                            mov + rng.normal(0, 4, mov.shape).astype(np.float32))
    assert t.rotation_deg == pytest.approx(rotation_deg, abs=0.02)
    assert t.scale == pytest.approx(scale, rel=2e-4)
    assert t.shift_px == pytest.approx((dx, dy), abs=0.05)
    assert t.centre_px == CENTRE
    np.testing.assert_allclose(t.matrix, truth, atol=0.05)
    assert t.confidence > 0.5
    # the documented use of the matrix puts moving onto the reference grid
    back = cv2.warpAffine(mov, t.matrix, (WIN, WIN),
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP)
    inner = (slice(150, WIN - 150), slice(150, WIN - 150))
    assert np.corrcoef(back[inner].ravel(), ref[inner].ravel())[0, 1] > 0.99


def test_register_similarity_with_masks(source: np.ndarray) -> None:
    ref, mov, truth = warped_pair(source, -0.4, 1.004, 6.3, -2.9)
    valid_mov = np.ones(mov.shape, bool)
    valid_mov[:, 400:] = False           # a strip of nodata
    valid_mov[:60, :] = False
    valid_ref = np.ones(ref.shape, bool)
    valid_ref[300:420, 50:250] = False   # a hole
    t = register_similarity(np.where(valid_ref, ref, 0), np.where(valid_mov, mov, 255),
                            valid_reference=valid_ref, valid_moving=valid_mov,
                            max_rotation_deg=10, scale_range=(0.9, 1.1))
    assert t.rotation_deg == pytest.approx(-0.4, abs=0.02)
    assert t.scale == pytest.approx(1.004, rel=2e-4)
    assert t.shift_px == pytest.approx((6.3, -2.9), abs=0.05)


def test_rotation_sign_and_centre_with_numpy_rot90() -> None:
    """np.rot90 turns the displayed image 90° counter-clockwise about its centre
    (no interpolation): rotation_deg must be +90 and the centre must not move."""
    ref = texture((384, 384), seed=8)
    t = register_similarity(ref, np.rot90(ref))
    assert t.rotation_deg == pytest.approx(90.0, abs=0.01)
    assert t.scale == pytest.approx(1.0, abs=1e-4)
    assert t.shift_px == pytest.approx((0.0, 0.0), abs=0.02)
    # clockwise as displayed is negative
    t = register_similarity(ref, np.rot90(ref, k=-1))
    assert t.rotation_deg == pytest.approx(-90.0, abs=0.01)


def test_scale_sign_zoomed_moving_is_larger() -> None:
    """Moving content magnified 1.25× (the central 80 % blown up to full size)."""
    src = texture((500, 500), seed=9)
    crop = src[50:450, 50:450]
    mov = cv2.resize(crop, (500, 500), interpolation=cv2.INTER_CUBIC)
    t = register_similarity(src, mov, scale_range=(0.8, 1.5))
    assert t.scale == pytest.approx(1.25, rel=1e-3)
    assert abs(t.rotation_deg) < 0.02


def test_register_similarity_refuses_flat_unrelated_and_tiny() -> None:
    tex = texture((256, 256), seed=11)
    with pytest.raises(AlignmentError, match="flat"):
        register_similarity(tex, np.full_like(tex, 100.0))
    with pytest.raises(AlignmentError, match="confidence"):
        register_similarity(tex, texture((256, 256), seed=12))
    with pytest.raises(AlignmentError, match="too small"):
        register_similarity(tex[:48, :48], tex[:48, :48])
    rng = np.random.default_rng(13)
    textureless = 100 + rng.normal(0, 2, (256, 256))  # independent sensor noise only
    with pytest.raises(AlignmentError, match="confidence"):
        register_similarity(textureless, 100 + rng.normal(0, 2, (256, 256)))


def test_map_matrix_and_shift_m() -> None:
    """Map-unit conversion on a north-up 0.05 m grid: a shift of (+4, +2) px
    (right, down) is (+0.2, -0.1) m; a CCW-as-displayed rotation is CCW on the map."""
    grid = Affine(0.05, 0.0, 500000.0, 0.0, -0.05, 6000000.0)
    t = SimilarityTransform(rotation_deg=0.0, scale=1.0, shift_px=(4.0, 2.0), confidence=1.0,
                            centre_px=(99.5, 99.5))
    assert t.shift_m(grid) == pytest.approx((0.2, -0.1))
    m = t.map_matrix(grid)
    np.testing.assert_allclose(m @ [500001.0, 5999999.0, 1.0], [500001.2, 5999998.9, 1.0])
    # 90° CCW about the window centre: a point 1 m east of the centre goes 1 m north
    t = SimilarityTransform(rotation_deg=90.0, scale=1.0, shift_px=(0.0, 0.0), confidence=1.0,
                            centre_px=(99.5, 99.5))
    cx, cy = grid * (100.0, 100.0)   # map position of pixel centre (99.5, 99.5)
    np.testing.assert_allclose(t.map_matrix(grid) @ [cx + 1.0, cy, 1.0], [cx, cy + 1.0, 1.0],
                               atol=1e-6)


@pytest.mark.parametrize("flight", ["PA2", "PA3"])
def test_sample_site_flights_match_truth(samples_dir: Path, flight: str) -> None:
    """Kernel-level check on the generated sample site: a 1024 px window around the
    site centre, cut from PA1 and from another flight at the same *stated*
    coordinates, must register to the generator's truth (truth.json
    ``relative_to_reference``) within the acceptance limits: 0.05°, 0.05 %, 0.10 m."""
    n, gsd = 1024, 0.05
    doc = json.loads((samples_dir / "truth.json").read_text())
    truth = doc["flights"]
    cx, cy = doc["site"]["centre_xy"]        # flights' CRS (EPSG:28356), stated frame

    def read(fid: str) -> tuple[np.ndarray, np.ndarray, Affine]:
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            col, row = ~ds.transform * (cx - n * gsd / 2, cy + n * gsd / 2)
            win = Window(math.floor(col), math.floor(row), n, n)
            img = ds.read([1, 2, 3], window=win, boundless=True, fill_value=0)
            valid = ds.read_masks(1, window=win, boundless=True) > 0
            return img.astype(np.float32), valid, ds.window_transform(win)

    ref, valid_ref, t_ref = read("PA1")
    mov, valid_mov, t_mov = read(flight)
    s = truth[flight]["relative_to_reference"]["stated_to_reference_stated"]
    stated_to_ref = Affine(*s[0], *s[1])
    half = Affine.translation(0.5, 0.5)            # pixel centre -> rasterio corner coords
    m = ~half * ~t_mov * ~stated_to_ref * t_ref * half  # reference px -> moving px
    want = SimilarityTransform.from_matrix(np.array([[m.a, m.b, m.c], [m.d, m.e, m.f]]),
                                           ((n - 1) / 2, (n - 1) / 2))
    got = register_similarity(ref, mov, valid_reference=valid_ref, valid_moving=valid_mov,
                              max_rotation_deg=10, scale_range=(0.9, 1.1))
    assert got.rotation_deg == pytest.approx(want.rotation_deg, abs=0.05)
    assert got.scale == pytest.approx(want.scale, rel=5e-4)
    shift_err_m = gsd * math.hypot(got.shift_px[0] - want.shift_px[0],
                                   got.shift_px[1] - want.shift_px[1])
    assert shift_err_m <= 0.10
    assert got.confidence > 0.5


# --------------------------------------------------------------------------- local_shift_field


def test_local_shift_field_recovers_smooth_warp() -> None:
    n = 768
    ref = texture((n, n), seed=14)
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    ux = 2.5 * np.sin(2 * np.pi * xx / 1400 + 0.3) * np.cos(2 * np.pi * yy / 1800)
    uy = -1.8 * np.cos(2 * np.pi * xx / 1600) + 0.7
    # moving(p) = reference(p - u(p)): content near p is displaced by u(p)
    mov = cv2.remap(ref, xx - ux, yy - uy, interpolation=cv2.INTER_CUBIC,
                    borderMode=cv2.BORDER_REFLECT)
    valid = np.ones((n, n), bool)
    valid[:, :40] = False
    field = local_shift_field(ref, mov, valid=valid, window_px=192, step_px=96)
    assert field.dx_px.shape == field.centres.shape[:2] == (7, 7)
    rows = field.centres[..., 0].round().astype(int)
    cols = field.centres[..., 1].round().astype(int)
    assert field.centres[0, 0].tolist() == [95.5, 95.5]
    assert field.valid.all()
    np.testing.assert_allclose(field.dx_px, ux[rows, cols], atol=0.3)
    np.testing.assert_allclose(field.dy_px, uy[rows, cols], atol=0.3)
    s = field.summary()
    mags = np.hypot(ux[rows, cols], uy[rows, cols])
    assert s["n_windows"] == s["n_confident"] == 49
    assert s["max_px"] == pytest.approx(mags.max(), abs=0.3)
    assert s["median_px"] == pytest.approx(np.median(mags), abs=0.3)


def test_local_shift_field_flags_flat_and_invalid_windows() -> None:
    ref = texture((384, 384), seed=15)
    mov = np.roll(ref, 2, axis=1)
    ref[:128, :128] = 50.0     # flat in both
    mov[:128, :128] = 50.0
    valid = np.ones(ref.shape, bool)
    valid[256:, 256:] = False  # nodata
    f = local_shift_field(ref, mov, valid=valid, window_px=128, step_px=128)
    assert f.valid.tolist() == [[False, True, True], [True, True, True], [True, True, False]]
    assert np.isnan(f.dx_px[0, 0]) and np.isnan(f.dx_px[2, 2]) and f.confidence[0, 0] == 0
    np.testing.assert_allclose(f.dx_px[f.valid], 2.0, atol=0.05)
    np.testing.assert_allclose(f.dy_px[f.valid], 0.0, atol=0.05)
    s = f.summary()
    assert s["n_confident"] == 7 and s["median_px"] == pytest.approx(2.0, abs=0.05)
    with pytest.raises(AlignmentError, match="larger than the image"):
        local_shift_field(ref, mov, window_px=512)


def test_local_shift_fields_of_several_flights_equal_one_at_a_time() -> None:
    """Several moving images in one pass (the reference window prepared once for those
    sharing its valid pixels) give the same fields, bit for bit, as one call per image:
    known shifts recovered, a flight with its own nodata (re-prepared reference), a flat
    corner and a flight with no valid pixel in a window."""
    from geosim.align.local import local_shift_fields

    ref = texture((384, 384), seed=17)
    ref[:128, :128] = 50.0                                   # flat in the reference
    movs = [(np.roll(ref, 2, axis=1), None),
            (np.roll(ref, -3, axis=0), np.ones(ref.shape, bool)),
            (np.roll(ref, (1, 1), axis=(0, 1)), np.ones(ref.shape, bool))]
    movs[1][1][200:, 200:] = False                            # its own nodata
    movs[2][1][:, :200] = False
    many = local_shift_fields(ref, movs, window_px=128, step_px=96)
    for (mov, valid), got in zip(movs, many, strict=True):
        one = local_shift_field(ref, mov, valid=valid, window_px=128, step_px=96)
        for name in ("centres", "dx_px", "dy_px", "confidence", "valid"):
            np.testing.assert_array_equal(getattr(got, name), getattr(one, name))
    np.testing.assert_allclose(many[0].dx_px[many[0].valid], 2.0, atol=0.05)
    np.testing.assert_allclose(many[1].dy_px[many[1].valid], -3.0, atol=0.05)
    assert not many[1].valid[-1, -1] and many[0].valid[-1, -1]
    assert not many[2].valid[:, 0].any() and many[2].valid[:, -1].all()


def test_no_confident_window_summary_is_json_safe() -> None:
    rng = np.random.default_rng(16)
    f = local_shift_field(rng.normal(size=(128, 128)), rng.normal(size=(128, 128)),
                          window_px=64, step_px=64)
    s = f.summary()
    assert s["n_confident"] == 0 and s["median_px"] is None and s["max_px"] is None
    assert not math.isnan(float(f.confidence.max()))


def test_as_grey_in_strips_is_bt601_luma_in_float32(monkeypatch):
    """as_grey's strips give BT.601 luma (float64 oracle, to float32 rounding) and the
    same bits whatever the strip height (uint8 RGBA and float RGB)."""
    from geosim.align import phasecorr as pc

    rng = np.random.default_rng(3)
    for img in (rng.integers(0, 256, (4, 37, 29), dtype=np.uint8),
                rng.normal(100, 30, (3, 41, 23))):
        oracle = 0.299 * img[0].astype(np.float64) + 0.587 * img[1] + 0.114 * img[2]
        outs = []
        for strip_px in (1, 29 * 5, 1 << 16):
            monkeypatch.setattr(pc, "GREY_STRIP_PX", strip_px)
            g = pc.as_grey(img)
            assert g.dtype == np.float32 and g.shape == img.shape[1:]
            np.testing.assert_allclose(g, oracle, rtol=2e-6, atol=1e-4)
            outs.append(g)
        assert all(np.array_equal(outs[0], o) for o in outs[1:])


def test_cross_power_sqrt_whitening_equals_power():
    """The default whitening (0.5) takes sqrt; the spectrum equals the |X| ** 0.5 form and
    the cached taper is read-only."""
    from geosim.align import phasecorr as pc

    rng = np.random.default_rng(5)
    a = rng.normal(size=(64, 48)).astype(np.float32)
    b = np.roll(a, (3, -2), axis=(0, 1))
    r = pc.cross_power(a, b)
    fr, fm = np.fft.fft2(a), np.fft.fft2(b)
    x = fm * np.conj(fr)
    mag = np.abs(x)
    ref = x / np.maximum(mag, 1e-12 * mag.max()) ** 0.5 * pc.spectral_taper((64, 48))
    ref /= np.abs(ref).mean()
    np.testing.assert_allclose(r, ref, rtol=1e-4, atol=1e-5)
    assert not pc.spectral_taper((64, 48)).flags.writeable
