"""A native grid of any pitch and phase (``geosim.physics.native_grid``) against OpenCV's
own area and cubic resizes, analytic transfers and the band-limited image's inverse DCT."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import scipy.fft
from scipy import ndimage

from geosim.physics.native_grid import (
    native_area,
    native_area_dct,
    native_edges,
    native_to_product,
    render_through_native,
)

PHI = 10


def _smooth_fine(n_px: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (n_px * PHI, n_px * PHI)), 4.0)
    return 100.0 + 40.0 * img / img.std()


def test_edges_cover_the_scene_at_any_phase():
    for pitch, phase in [(1.5, 0.0), (1.37, 0.4), (1.63, 1.62), (1.63, -0.3), (2.0, 4.5)]:
        e = native_edges(64, pitch, phase)
        assert e[0] <= 0 < e[1] and e[-2] < 64 <= e[-1], (pitch, phase, e[:2], e[-2:])
        assert np.allclose(np.diff(e), pitch)
        assert np.isclose((e[1] - phase) % pitch, 0) or np.isclose((e[1] - phase) % pitch,
                                                                      pitch)
    with pytest.raises(ValueError, match="native_pitch_px"):
        native_edges(64, 0.0, 0.0)


@pytest.mark.parametrize("n_native", [48, 40, 37])
def test_phase_zero_is_opencv_area_then_opencv_cubic(n_native):
    """At phase 0 and a pitch that divides the scene into whole native pixels, the area
    step is OpenCV's INTER_AREA and the cubic step (a = −0.75) OpenCV's INTER_CUBIC."""
    n_px = 64
    fine = _smooth_fine(n_px).astype(np.float32)
    pitch = n_px / n_native
    nat, cr, cc = native_area(fine, PHI, pitch)
    ref = cv2.resize(fine, (n_native, n_native), interpolation=cv2.INTER_AREA)
    assert nat.shape == ref.shape
    assert np.abs(nat - ref).max() < 1e-3
    prod = native_to_product(nat, cr, cc, (n_px, n_px), -0.75)
    ref_prod = cv2.resize(ref, (n_px, n_px), interpolation=cv2.INTER_CUBIC)
    assert np.abs(prod - ref_prod).max() < 1e-3


def test_a_whole_pitch_of_phase_is_no_change_and_a_constant_stays_constant():
    fine = _smooth_fine(48)
    a = render_through_native(fine, PHI, 1.43, phase_px=(0.3, 0.9))
    b = render_through_native(fine, PHI, 1.43, phase_px=(0.3 + 1.43, 0.9 - 2 * 1.43))
    assert np.allclose(a, b)
    flat = render_through_native(np.full((480, 480), 37.0), PHI, 1.63, phase_px=(0.7, 0.2),
                                 cubic_a=-0.5)
    assert np.allclose(flat, 37.0)


def test_box_average_of_a_cosine_is_the_sinc_transfer():
    """A cosine along the columns below the native Nyquist: each native sample is its mean
    over the detector, amplitude sinc(p f) (analytic), at any phase."""
    n_px, pitch, f = 64, 1.6, 0.125            # f in cycles per product pixel
    x = (np.arange(n_px * PHI) + 0.5) / PHI
    fine = np.tile(np.cos(2 * np.pi * f * x), (n_px * PHI, 1))
    for phase in (0.0, 0.55):
        nat, _, cc = native_area(fine, PHI, pitch, (0.0, phase))
        inner = slice(2, -2)                   # detectors cut by the scene's edge aside
        expect = np.sinc(pitch * f) * np.cos(2 * np.pi * f * cc[inner])
        assert np.abs(nat[5, inner] - expect).max() < 2e-3


def test_dct_form_is_the_band_limited_image_averaged():
    """native_area_dct of truncated DCT coefficients equals native_area of their inverse
    transform (the same band-limited image, sampled on the fine grid) to well under the
    fine pixels' own piecewise-constant approximation."""
    fine = _smooth_fine(48, seed=3)
    coef = scipy.fft.dctn(fine, type=2, norm="ortho")
    k = 120                                    # past the optics' cut-off of Q ≈ 0.8
    coef[k:, :] = 0.0
    coef[:, k:] = 0.0
    band_limited = scipy.fft.idctn(coef, type=2, norm="ortho")
    for pitch, phase in [(1.37, (0.0, 0.0)), (1.63, (0.4, 1.1))]:
        a, ar, ac = native_area(band_limited, PHI, pitch, phase)
        b, br, bc = native_area_dct(coef[:k, :k], band_limited.shape, PHI, pitch, phase)
        assert np.allclose(ar, br) and np.allclose(ac, bc)
        assert np.abs(a - b).max() < 0.02 * a.std(), (pitch, np.abs(a - b).max(), a.std())
