"""The blur metric: Laplacian variance with the paper's kernel, on valid pixels only."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geosim.degrade.blur import (
    PAPER_LAPLACIAN,
    interior_mask,
    laplacian_variance,
    to_grey,
)
from tests.helpers import textured_rgb


def _hand_laplacian(g: np.ndarray) -> np.ndarray:
    """Interior responses by explicit shifts (independent of cv2.filter2D)."""
    c, e = 1 / 6, 2 / 3
    return (c * (g[:-2, :-2] + g[:-2, 2:] + g[2:, :-2] + g[2:, 2:])
            + e * (g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:])
            - 10 / 3 * g[1:-1, 1:-1])


def test_kernel_is_matlab_fspecial_laplacian() -> None:
    alpha = 0.2  # fspecial('laplacian') default
    expected = 4 / (alpha + 1) * np.array([[alpha / 4, (1 - alpha) / 4, alpha / 4],
                                           [(1 - alpha) / 4, -1, (1 - alpha) / 4],
                                           [alpha / 4, (1 - alpha) / 4, alpha / 4]])
    np.testing.assert_allclose(PAPER_LAPLACIAN, expected, rtol=0, atol=1e-15)
    # the paper prints it rounded to two decimals
    np.testing.assert_allclose(PAPER_LAPLACIAN, [[0.17, 0.67, 0.17], [0.67, -3.33, 0.67],
                                                 [0.17, 0.67, 0.17]], atol=0.005)
    assert PAPER_LAPLACIAN.sum() == pytest.approx(0.0, abs=1e-15)


def test_quadratic_surface_has_its_analytic_laplacian() -> None:
    """On f = a x² + b y² + c x y the kernel returns ∇²f = 2a + 2b: LV is 0."""
    y, x = np.mgrid[0:40, 0:50].astype(float)
    f = 0.3 * x**2 + 0.7 * y**2 + 0.2 * x * y + 5
    np.testing.assert_allclose(_hand_laplacian(f), 2 * 0.3 + 2 * 0.7, atol=1e-9)
    assert laplacian_variance(f) == pytest.approx(0.0, abs=1e-9)


def test_white_noise_lv_is_variance_times_kernel_energy() -> None:
    rng = np.random.default_rng(1)
    sigma = 7.0
    noise = 100 + sigma * rng.standard_normal((600, 600))
    expected = sigma**2 * (PAPER_LAPLACIAN**2).sum()  # = 13 σ²
    assert (PAPER_LAPLACIAN**2).sum() == pytest.approx(13.0)
    assert laplacian_variance(noise) == pytest.approx(expected, rel=0.02)


def test_masked_lv_matches_hand_formula_and_ignores_invalid_values() -> None:
    rng = np.random.default_rng(2)
    g = rng.uniform(0, 255, (60, 70))
    valid = np.ones(g.shape, bool)
    valid[10:20, 30:45] = False
    valid[50, 5] = False
    # pixels count when their 3×3 neighbourhood is valid and inside the image
    counts = np.zeros(g.shape, bool)
    for r in range(1, 59):
        for c in range(1, 69):
            counts[r, c] = valid[r - 1:r + 2, c - 1:c + 2].all()
    np.testing.assert_array_equal(interior_mask(valid, g.shape), counts)
    responses = _hand_laplacian(g)[counts[1:-1, 1:-1]]
    assert laplacian_variance(g, valid) == pytest.approx(responses.var(), rel=1e-12)
    spiked = g.copy()
    spiked[~valid] = 1e6  # values under the mask cannot matter
    assert laplacian_variance(spiked, valid) == pytest.approx(laplacian_variance(g, valid),
                                                              rel=1e-12)


def _matlab_uint8_response(rounded: np.ndarray) -> np.ndarray:
    """imfilter(uint8, fspecial('laplacian')) in exact integer arithmetic (interior)."""
    g = rounded.astype(np.int64)
    six = (g[:-2, :-2] + g[:-2, 2:] + g[2:, :-2] + g[2:, 2:]
           + 4 * (g[:-2, 1:-1] + g[2:, 1:-1] + g[1:-1, :-2] + g[1:-1, 2:]) - 20 * g[1:-1, 1:-1])
    return np.clip(np.floor_divide(six + 3, 6), 0, 255)  # round half away from zero, saturate


def test_matlab_compatible_clips_negative_responses() -> None:
    grey = to_grey(textured_rgb(120, 130, seed=4))
    rounded = np.floor(grey + 0.5)  # MATLAB's uint8 conversion
    response = _matlab_uint8_response(np.pad(rounded, 1))  # imfilter's default zero padding
    assert laplacian_variance(grey, matlab_compatible=True) == pytest.approx(response.var(),
                                                                             rel=1e-12)
    default = laplacian_variance(grey)
    matlab = laplacian_variance(grey, valid=np.ones(grey.shape, bool), matlab_compatible=True)
    assert matlab == pytest.approx(_matlab_uint8_response(rounded).var(), rel=1e-12)
    # Responses are symmetric about 0 on texture, so clipping removes about half the variance.
    assert 0.2 * default < matlab < 0.6 * default


def test_to_grey_is_bt601_luma() -> None:
    rgb = textured_rgb(50, 60, seed=5)
    grey = to_grey(rgb)
    assert grey.dtype == np.float64 and grey.shape == (50, 60)
    cv_grey = cv2.cvtColor(np.ascontiguousarray(np.moveaxis(rgb, 0, -1)), cv2.COLOR_RGB2GRAY)
    assert np.abs(grey - cv_grey).max() <= 0.5 + 1e-9  # OpenCV rounds the same luma
    np.testing.assert_allclose(grey, 0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2])
    rgbn = np.concatenate([rgb, np.full((1, 50, 60), 200, np.uint8)])
    np.testing.assert_array_equal(to_grey(rgbn), grey)  # NIR ignored
    wide = rgb.astype(np.uint16) * 257  # same image on a 16-bit scale
    np.testing.assert_allclose(to_grey(wide), grey, rtol=1e-12)
    np.testing.assert_allclose(to_grey(rgb[0]), rgb[0].astype(float))


def test_bad_inputs() -> None:
    with pytest.raises(ValueError, match="2-band"):
        to_grey(np.zeros((2, 5, 5), np.uint8))
    with pytest.raises(ValueError):
        to_grey(np.zeros((1, 3, 5, 5)))
    with pytest.raises(ValueError):
        laplacian_variance(np.zeros((3, 5, 5)))
    with pytest.raises(ValueError):
        laplacian_variance(np.zeros((5, 5)), np.ones((4, 5), bool))
    assert np.isnan(laplacian_variance(np.zeros((5, 5)), np.zeros((5, 5), bool)))
