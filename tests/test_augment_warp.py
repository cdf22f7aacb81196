"""The local-warp field: maximum, smoothness, inverse mapping of points, folding guard."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geosim.augment import geometry as geo
from geosim.augment.resample import affine_resample, remap_resample
from geosim.augment.warp import smooth_field
from geosim.errors import ConfigError


@pytest.mark.parametrize("shape, max_px, sigma", [((64, 80), 2.0, 6.0), ((300, 260), 12.0, 40.0),
                                                  ((1000, 900), 25.0, 160.0)])
def test_field_reaches_exactly_its_maximum(shape, max_px, sigma) -> None:
    f = smooth_field(shape, max_px=max_px, filter_sigma_px=sigma, rng=np.random.default_rng(3))
    assert f.u_px.shape == shape and f.u_px.dtype == np.float32
    assert np.isclose(np.hypot(f.u_px, f.v_px).max(), max_px, rtol=1e-5)


def test_filter_width_sets_the_correlation_length() -> None:
    # A Gaussian-filtered white noise has autocorrelation exp(-d² / (4σ²)):
    # correlation at lag σ is exp(-1/4) ≈ 0.78 and at lag 3σ exp(-9/4) ≈ 0.105.
    sigma = 12.0
    corr1, corr3 = [], []
    for seed in range(6):
        f = smooth_field((400, 400), max_px=3.0, filter_sigma_px=sigma,
                         rng=np.random.default_rng(seed))
        u = f.u_px.astype(float) - f.u_px.mean()
        for lag, acc in ((int(sigma), corr1), (int(3 * sigma), corr3)):
            acc.append((u[:, :-lag] * u[:, lag:]).mean() / u.var())
    assert abs(np.mean(corr1) - np.exp(-0.25)) < 0.05
    assert abs(np.mean(corr3) - np.exp(-2.25)) < 0.08


def test_fine_gradient_matches_reported_bound() -> None:
    f = smooth_field((400, 300), max_px=8.0, filter_sigma_px=30.0, rng=np.random.default_rng(4))
    gy_u, gx_u = np.gradient(f.u_px.astype(float))
    gy_v, gx_v = np.gradient(f.v_px.astype(float))
    fine = np.sqrt(gx_u**2 + gy_u**2 + gx_v**2 + gy_v**2).max()
    assert abs(fine - f.max_gradient) / fine < 0.05


def test_forward_points_invert_the_backward_map() -> None:
    f = smooth_field((200, 240), max_px=6.0, filter_sigma_px=20.0, rng=np.random.default_rng(5))
    p = np.random.default_rng(6).uniform(0, 200, (500, 2))
    x = f.forward_points(p)
    u, v = f.sample(x[:, 0], x[:, 1])
    assert np.abs(x + np.stack([u, v], 1) - p).max() < 1e-3
    assert np.abs(x - p).max() <= 6.0 + 1e-6


def test_warped_spot_lands_where_forward_points_say() -> None:
    shape = (120, 120)
    f = smooth_field(shape, max_px=5.0, filter_sigma_px=18.0, rng=np.random.default_rng(7))
    img = np.zeros((1, *shape), np.float32)
    img[0, 59:62, 39:42] = 1.0  # 3 x 3 spot centred on (x, y) = (40.5, 60.5)
    out, _ = remap_resample(img, np.ones(shape, bool), f.u_px, f.v_px, interpolation="linear")
    rows, cols = np.indices(shape)
    w = np.clip(out[0], 0, None) / np.clip(out[0], 0, None).sum()
    centroid = [(w * (cols + 0.5)).sum(), (w * (rows + 0.5)).sum()]
    expect = f.forward_points(np.array([[40.5, 60.5]]))[0]
    assert np.allclose(centroid, expect, atol=0.15)


def test_zero_maximum_gives_zero_field() -> None:
    f = smooth_field((50, 50), max_px=0.0, filter_sigma_px=10.0, rng=np.random.default_rng(0))
    assert not f.u_px.any() and not f.v_px.any()


def test_folding_field_is_refused() -> None:
    with pytest.raises(ConfigError, match="fold"):
        smooth_field((200, 200), max_px=30.0, filter_sigma_px=10.0,
                     rng=np.random.default_rng(0))


def test_same_generator_state_gives_the_same_field() -> None:
    a = smooth_field((90, 70), max_px=3.0, filter_sigma_px=9.0, rng=np.random.default_rng(11))
    b = smooth_field((90, 70), max_px=3.0, filter_sigma_px=9.0, rng=np.random.default_rng(11))
    assert np.array_equal(a.u_px, b.u_px) and np.array_equal(a.v_px, b.v_px)


def test_affine_then_warp_in_one_remap_matches_the_analytic_composition() -> None:
    # A smooth analytic image resampled through a known affine then a known field: the
    # one-remap result must sample the image at A^-1 (x + d(x)) (the exact composition),
    # at least as accurately as the two separate resamplings it replaces.
    shape = (300, 340)
    rows, cols = np.indices(shape)

    def fn(x, y):
        return 100 * np.sin(0.11 * x + 0.3) + 80 * np.cos(0.09 * y) + 30 * np.sin(0.05 * (x + y))

    img = fn(cols + 0.5, rows + 0.5).astype(np.float32)[np.newaxis]
    m = (geo.rotation_matrix(13.0, shape) @ geo.shift_matrix(3.3, -7.1)
         @ geo.scale_matrix(1.07, shape))
    f = smooth_field(shape, max_px=6.0, filter_sigma_px=40.0, rng=np.random.default_rng(0))
    mask = np.ones(shape, bool)
    one, one_mask = remap_resample(img, mask, f.u_px, f.v_px, matrix=m)
    mid, mid_mask = affine_resample(img, mask, m)
    two, two_mask = remap_resample(mid, mid_mask, f.u_px, f.v_px)
    back = np.linalg.inv(m)
    x, y = cols + 0.5 + f.u_px, rows + 0.5 + f.v_px  # pixel-edge frame of the intermediate
    truth = fn(back[0, 0] * x + back[0, 1] * y + back[0, 2],
               back[1, 0] * x + back[1, 1] * y + back[1, 2])
    # the valid footprint is the same as after two steps (up to nearest-neighbour ties)
    assert (one_mask != two_mask).mean() < 0.002 and 0.9 < one_mask.mean() < 1.0
    inner = cv2.erode((one_mask & two_mask).astype(np.uint8), np.ones((9, 9))).astype(bool)
    err_one = np.abs(one[0] - truth)[inner]
    err_two = np.abs(two[0] - truth)[inner]
    assert err_one.max() < 2.0 and np.sqrt((err_one**2).mean()) < 0.5  # of a ±210 signal
    assert np.sqrt((err_one**2).mean()) <= np.sqrt((err_two**2).mean())
    # a wrong composition (the affine applied after the field) is far off
    wrong = fn(back[0, 0] * (cols + 0.5) + back[0, 1] * (rows + 0.5) + back[0, 2] + f.u_px,
               back[1, 0] * (cols + 0.5) + back[1, 1] * (rows + 0.5) + back[1, 2] + f.v_px)
    assert np.abs(one[0] - wrong)[inner].max() > 5.0
