"""Noise under JPEG from the censored DCT coefficients (geosim.diagnose.jpeg_noise).

Truth is independent of the code under test: a smooth real image (the Brazil pasture,
area-averaged to 0.64 m) gets Gaussian noise of a known σ per band, is rounded to whole
DN and JPEG-compressed with Pillow (libjpeg, its standard tables); the quantisation steps
are compared with the JPEG standard's luminance table (ITU-T T.81, Annex K.1) scaled
as libjpeg scales it.
"""

from __future__ import annotations

import numpy as np
import pytest

from geosim.diagnose.jpeg_noise import block_dct, jpeg_noise_variance, lattice_steps
from geosim.diagnose.noise import estimate_noise
from geosim.diagnose.spectra import block_origins
from tests.helpers import area_averaged_rgb, pillow_jpeg

LUMA = np.array([0.299, 0.587, 0.114])
#: ITU-T T.81 Annex K.1, Table K.1 (luminance), row-major
T81_LUMA = np.array([
    16, 11, 10, 16, 24, 40, 51, 61, 12, 12, 14, 19, 26, 58, 60, 55,
    14, 13, 16, 24, 40, 57, 69, 56, 14, 17, 22, 29, 51, 87, 80, 62,
    18, 22, 37, 56, 68, 109, 103, 77, 24, 35, 55, 64, 81, 104, 113, 92,
    49, 64, 78, 87, 103, 121, 120, 101, 72, 92, 95, 98, 112, 100, 103, 99]).reshape(8, 8)


def _libjpeg_table(quality: int) -> np.ndarray:
    scale = 5000 // quality if quality < 50 else 200 - 2 * quality
    return np.clip((T81_LUMA * scale + 50) // 100, 1, 255)


@pytest.fixture(scope="module")
def smooth(realdata) -> np.ndarray:
    return area_averaged_rgb(realdata / "brazil_pasture_10cm_epsg3395.tif", start_px=1000,
                             size_px=1280, side_px=128)


@pytest.mark.parametrize("quality", [30, 50, 75])
def test_steps_are_the_standard_table(smooth, quality):
    rng = np.random.default_rng(0)
    real = pillow_jpeg(smooth + rng.normal(0, 2.0, smooth.shape), quality)
    steps = lattice_steps(block_dct(np.tensordot(LUMA, real, 1), (0, 0))).reshape(8, 8)
    table = _libjpeg_table(quality)
    # low frequencies (u + v <= 3) hold enough non-zero coefficients to show their lattice
    u, v = np.mgrid[0:8, 0:8]
    low = ((u + v) <= 3) & ((u + v) > 0)
    assert np.array_equal(steps[low], table[low]), (steps[low], table[low])


@pytest.mark.parametrize("quality", [30, 50, 75])
@pytest.mark.parametrize("sigma", [0.0, 2.0, 3.0, 5.0])
def test_noise_variance_under_jpeg(smooth, quality, sigma):
    """Estimated luma noise variance within 25 % (+0.3 DN²) of σ²·Σw² + rounding."""
    rng = np.random.default_rng(int(10 * sigma) + quality)
    noisy = np.clip(np.rint(smooth + rng.normal(0, sigma, smooth.shape)), 0, 255)
    real = pillow_jpeg(noisy, quality)
    fit = jpeg_noise_variance(np.tensordot(LUMA, real, 1), np.tensordot(LUMA, smooth, 1),
                              (0, 0), np.ones(real.shape[-2:], bool))
    true_var = float(np.sum(LUMA**2)) * (sigma**2 + 1.0 / 12.0)
    assert abs(fit.var_dn2 - true_var) <= 0.25 * true_var + 0.3, (fit.var_dn2, true_var)


def test_estimate_noise_under_jpeg_per_band_and_claim(smooth):
    """Through estimate_noise: per-band variance of the noise (rounding removed), claimed
    for σ = 3 DN at quality 40, not claimed without noise. The spectral white floor alone
    (the path without ``uncompressed``) does not claim it: the JPEG removed the floor's
    high-frequency part, so the incoherent power is far from white."""
    rng = np.random.default_rng(5)
    mask = np.ones(smooth.shape[-2:], bool)
    org = block_origins(smooth.shape[-2:], block_px=32)
    for sigma, claimed in ((3.0, True), (0.0, False)):
        noisy = np.clip(np.rint(smooth + rng.normal(0, sigma, smooth.shape)), 0, 255)
        real = pillow_jpeg(noisy, 40)
        model_jpeg = pillow_jpeg(smooth, 40)
        est = estimate_noise(real, model_jpeg, mask, origins=org, block_px=32, quantized=True,
                             uncompressed=smooth, block_offset_px=(0, 0))
        assert est.claimed is claimed, (sigma, est.white_var_dn2, est.whiteness)
        if claimed:
            assert abs(est.white_var_dn2 - sigma**2) < 0.25 * sigma**2, est.white_var_dn2
            spectral = estimate_noise(real, model_jpeg, mask, origins=org, block_px=32,
                                      quantized=True)
            assert not spectral.claimed, (spectral.white_var_dn2, spectral.whiteness)
        else:
            assert est.white_var_dn2 < 1.0


def test_block_offset_is_respected(smooth):
    """A JPEG grid starting at (3, 5): steps found on that grid, not on (0, 0)."""
    rng = np.random.default_rng(2)
    noisy = np.clip(np.rint(smooth + rng.normal(0, 2.0, smooth.shape)), 0, 255)
    pad = np.pad(noisy, ((0, 0), (5, 0), (3, 0)), mode="edge")   # grid at row 5, col 3
    real = pillow_jpeg(pad, 50)[:, 5:, 3:]
    # in the cropped image block edges lie at rows 3, 11, ... and cols 5, 13, ...
    grey = np.tensordot(LUMA, real, 1)
    right = lattice_steps(block_dct(grey, (3, 5))).reshape(8, 8)
    wrong = lattice_steps(block_dct(grey, (0, 0))).reshape(8, 8)
    table = _libjpeg_table(50)
    assert right[0, 1] == table[0, 1] and right[1, 0] == table[1, 0]
    assert not (wrong[0, 1] == table[0, 1] and wrong[1, 0] == table[1, 0])


def test_small_noise_under_jpeg_measured_but_not_claimed(smooth):
    """Under JPEG the claim needs a white variance of MIN_NOISE_VAR_COMPRESSED_DN2 (4 DN²):
    σ = 1.5 DN (2.25 DN², read as ≈ 1.4 by the censored estimate, above the 1 DN² floor
    used without JPEG) is not claimed; σ = 2.5 DN is, near its variance."""
    from geosim.diagnose.noise import MIN_NOISE_VAR_COMPRESSED_DN2

    assert MIN_NOISE_VAR_COMPRESSED_DN2 == 4.0
    rng = np.random.default_rng(7)
    mask = np.ones(smooth.shape[-2:], bool)
    org = block_origins(smooth.shape[-2:], block_px=32)
    for sigma, claimed in ((1.5, False), (2.5, True)):
        noisy = np.clip(np.rint(smooth + rng.normal(0, sigma, smooth.shape)), 0, 255)
        est = estimate_noise(pillow_jpeg(noisy, 40), pillow_jpeg(smooth, 40), mask, origins=org,
                             block_px=32, quantized=True, uncompressed=smooth,
                             block_offset_px=(0, 0))
        assert est.white_var_dn2 > 1.0, (sigma, est.white_var_dn2)
        assert est.claimed is claimed, (sigma, est.white_var_dn2, est.whiteness)
        if claimed:
            assert abs(est.white_var_dn2 - sigma**2) < 0.3 * sigma**2, est.white_var_dn2


def test_brightness_dependent_noise_under_jpeg(smooth):
    """Noise whose variance grows with brightness (numpy: var = a·s + b per band, a
    0.5 DN²/DN or 0, b 2 or 30 DN²) on the pasture spread over 14–222 DN by a ramp, then
    Pillow's JPEG at quality 50: the censored DCT likelihood by brightness class gives a
    variance rising with brightness for a > 0 and flat for a = 0; the gain comes out
    within 25 % of a, and no gain where there is none."""
    ramp = np.linspace(0.3, 1.7, smooth.shape[-1])[None, None, :]
    scene = np.clip((smooth - smooth.mean()) * 0.5 + smooth.mean() * ramp, 5, 250)
    mask = np.ones(scene.shape[-2:], bool)
    org = block_origins(scene.shape[-2:], block_px=32)
    for gain, read in ((0.5, 2.0), (0.0, 30.0)):
        rng = np.random.default_rng(1)
        noisy = np.rint(scene + rng.normal(0, 1, scene.shape) * np.sqrt(gain * scene + read))
        real = pillow_jpeg(np.clip(noisy, 0, 255), 50)
        est = estimate_noise(real, pillow_jpeg(scene, 50), mask, origins=org, block_px=32,
                             quantized=True, uncompressed=scene, block_offset_px=(0, 0))
        assert est.claimed and est.estimator == "jpeg_dct_censored"
        assert est.brightness_dn.size == 3 and np.all(np.diff(est.brightness_dn) > 0)
        v = est.variance_dn2
        if gain > 0:
            assert v[2] > 2.0 * v[0], v   # a·s + b: 36 → 91 DN², first class to last
            assert abs(est.gain_dn - gain) < 0.25 * gain, (est.gain_dn, est.gain_sigma)
        else:
            assert v.max() < 1.3 * v.min(), v
            assert est.gain_dn < 2.0 * est.gain_sigma + 0.02, (est.gain_dn, est.gain_sigma)
