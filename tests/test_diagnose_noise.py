"""Noise from the white, incoherent part of the residual (geosim.diagnose.noise)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from geosim.diagnose.noise import estimate_noise
from geosim.diagnose.spectra import block_origins


def _texture(n: int = 192, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.normal(0, 40, (n, n)), 1.2)
    return np.stack([100 + base, 110 + 0.9 * base, 90 + 0.8 * base])


def _run(real: np.ndarray, model: np.ndarray):
    mask = np.ones(real.shape[-2:], bool)
    org = block_origins(real.shape[-2:], block_px=32)
    return estimate_noise(real, model, mask, origins=org, block_px=32, quantized=False)


def test_white_noise_variance_recovered_and_claimed():
    model = _texture()
    rng = np.random.default_rng(1)
    real = model + rng.normal(0, np.sqrt(6.0), model.shape)
    est = _run(real, model)
    assert est.claimed
    assert 0.8 * 6.0 < est.white_var_dn2 < 1.25 * 6.0, est.white_var_dn2
    assert est.whiteness < 1.5


def test_blur_shape_misfit_is_not_noise():
    """A residual that is a linear filter of the model (a blur the model lacks) is fully
    coherent: no noise floor, nothing claimed, although its per-pixel variance is large."""
    model = _texture()
    real = np.stack([ndimage.gaussian_filter(b, 0.8) for b in model])
    assert float(np.var(real - model)) > 3.0   # would pass a per-pixel variance test
    est = _run(real, model)
    assert not est.claimed
    assert est.white_var_dn2 < 0.5


def test_brightness_dependence_follows_shot_noise():
    model = _texture()
    rng = np.random.default_rng(2)
    var = 0.2 * model + 2.0
    real = model + rng.normal(0, 1, model.shape) * np.sqrt(var)
    est = _run(real, model)
    assert est.claimed and est.gain_dn > 0.05


def test_expected_spectrum_of_realisations_beats_one_realisation():
    """spectral_error of a list averages the realisations' Welch power: of the same image
    twice it equals the single image's; for white noise of the real scene's own level the
    mean of 8 realisations matches the scene's spectrum better than one realisation does
    (a single periodogram scatters, the expected one does not)."""
    from geosim.diagnose.spectra import spectral_error

    model = _texture(128)[0]
    rng = np.random.default_rng(3)
    real = model + rng.normal(0, 4.0, model.shape)
    one = model + rng.normal(0, 4.0, model.shape)
    assert spectral_error([one, one], real) == spectral_error(one, real)
    many = [model + rng.normal(0, 4.0, model.shape) for _ in range(8)]
    singles = [spectral_error(m, real) for m in many]
    assert spectral_error(many, real) < np.median(singles), (spectral_error(many, real), singles)
