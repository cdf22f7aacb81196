"""Photometric kernels against independent truth (the standard library's colorsys)."""

from __future__ import annotations

import colorsys

import numpy as np
import pytest
from scipy import stats

from geosim.augment import photometric as ph
from geosim.augment.resample import interleave, planar


def _rgb(values: list[tuple[int, int, int]]) -> np.ndarray:
    """One row of pixels, interleaved ``(rows, cols, bands)`` as the kernels take them."""
    return np.array(values, np.float32).reshape(1, -1, 3)


def _colorsys_hsv_shift(rgb, dh_deg=0.0, ds=0.0, dv=0.0):
    h, s, v = colorsys.rgb_to_hsv(*(c / 255.0 for c in rgb))
    h = (h + dh_deg / 360.0) % 1.0
    s = min(max(s + ds / 255.0, 0.0), 1.0)
    v = min(max(v + dv / 255.0, 0.0), 1.0)
    return [255.0 * c for c in colorsys.hsv_to_rgb(h, s, v)]


COLOURS = [(200, 30, 30), (10, 180, 90), (40, 60, 220), (128, 128, 128), (250, 240, 5),
           (3, 2, 1), (255, 0, 255)]


@pytest.mark.parametrize("dh, ds, dv", [(30.0, 0, 0), (-50.0, 0, 0), (170.0, 0, 0),
                                        (0, 40.0, 0), (0, -60.0, 0), (0, 0, 25.0),
                                        (0, 0, -90.0), (12.0, 20.0, -10.0)])
def test_hsv_shift_matches_colorsys(dh, ds, dv) -> None:
    out = ph.hsv_shift(_rgb(COLOURS), hue_deg=dh, saturation_dn=ds, value_dn=dv)
    expect = np.array([_colorsys_hsv_shift(c, dh, ds, dv) for c in COLOURS])
    assert np.allclose(out.reshape(-1, 3), expect, atol=0.02)


def test_hue_wraps_cyclically_beyond_opencv_8bit_range() -> None:
    red = _rgb([(255, 0, 0)])
    # +120° turns red into green, -120° into blue; 360° is the identity (no 0-179 clipping).
    assert np.allclose(ph.hsv_shift(red, hue_deg=120.0).ravel(), [0, 255, 0], atol=1e-3)
    assert np.allclose(ph.hsv_shift(red, hue_deg=-120.0).ravel(), [0, 0, 255], atol=1e-3)
    img = _rgb(COLOURS)
    assert np.allclose(ph.hsv_shift(img, hue_deg=360.0), img, atol=1e-3)
    # a hue of 5° shifted by -10° wraps to 355°, not to 0
    h5 = np.array(colorsys.hsv_to_rgb(5 / 360, 1.0, 1.0)) * 255
    out = ph.hsv_shift(h5.astype(np.float32).reshape(1, 1, 3), hue_deg=-10.0).ravel()
    assert np.isclose(colorsys.rgb_to_hsv(*(out / 255))[0] * 360, 355.0, atol=0.05)


def test_colour_shift_adds_per_band_and_clips() -> None:
    img = _rgb([(10, 100, 250)])
    out = ph.colour_shift(img, np.array([-20.0, 5.0, 10.0]))
    assert np.allclose(out.ravel(), [0.0, 105.0, 255.0])


def test_uint16_scaling_keeps_relative_change() -> None:
    img8 = _rgb([(100, 50, 20)])
    img16 = img8 * 257.0
    out8 = ph.colour_shift(img8, np.array([10.0, 10.0, 10.0]))
    out16 = ph.colour_shift(img16, np.array([10.0, 10.0, 10.0]), dn_max=65535.0)
    assert np.allclose(out16, out8 * 257.0)
    assert ph.dn_max_for(np.uint16) == 65535.0 and ph.dn_max_for(np.uint8) == 255.0


def test_noise_is_zero_mean_gaussian_per_pixel_and_band() -> None:
    work = np.full((100, 100, 3), 128.0, np.float32)
    out = ph.add_noise(work, sigma_dn=7.0, rng=np.random.default_rng(0))
    d = (out - work).ravel()
    assert stats.kstest(d, "norm", args=(0.0, 7.0)).pvalue > 0.01
    assert stats.kstest(d, "norm", args=(0.0, 7.5)).pvalue < 0.01  # the test can fail
    # independent between bands and between neighbouring pixels: correlation ~ 0
    n = out - work
    assert abs(np.corrcoef(n[..., 0].ravel(), n[..., 1].ravel())[0, 1]) < 0.05
    assert abs(np.corrcoef(n[:, :-1, 0].ravel(), n[:, 1:, 0].ravel())[0, 1]) < 0.05
    assert np.array_equal(work, np.full((100, 100, 3), 128.0, np.float32))  # input untouched


def test_noise_is_reproducible_from_the_generator_and_differs_between_seeds() -> None:
    work = np.full((50, 60, 3), 100.0, np.float32)
    a = ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(5))
    assert np.array_equal(a, ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(5)))
    assert not np.array_equal(a, ph.add_noise(work, sigma_dn=3.0,
                                              rng=np.random.default_rng(6)))


def test_value_shift_on_single_band_adds() -> None:
    out = ph.hsv_shift(np.full((2, 2, 1), 100.0, np.float32), value_dn=-30.0, hue_deg=40.0)
    assert np.allclose(out, 70.0)


def test_round_trip_back_to_dtype() -> None:
    w = np.array([[[-3.2, 12.5, 254.6, 300.0, 13.5]]], np.float32)
    assert ph.from_work(w, np.uint8).tolist() == [[[0, 12, 255, 255, 14]]]  # ties to even
    assert ph.from_work(w * 300, np.uint16).tolist() == [[[0, 3750, 65535, 65535, 4050]]]
    assert ph.from_work(w, np.float32).dtype == np.float32


def test_work_layout_round_trip() -> None:
    planes = np.random.default_rng(1).integers(0, 255, (4, 5, 6), dtype=np.uint8)
    hwc = interleave(planes)
    assert hwc.shape == (5, 6, 4) and np.array_equal(hwc, np.moveaxis(planes, 0, -1))
    assert np.array_equal(planar(hwc), planes)
    assert np.array_equal(planar(interleave(planes[:1])), planes[:1])
    work = ph.to_work(hwc)
    assert work.dtype == np.float32 and np.array_equal(work, hwc)
    # from_work writes into a given output block (the pipeline's image rows)
    dest = np.zeros((9, 6, 4), np.uint8)
    ph.from_work(work + 0.4, np.uint8, out=dest[2:7])
    assert np.array_equal(dest[2:7], hwc) and not dest[:2].any() and not dest[7:].any()
