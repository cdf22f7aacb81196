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


def _moved_objects_scene(noise_var_dn2: float, seed: int = 3):
    """A textured scene in which 14 dark cattle-sized ellipses (the generator's
    ``paste_objects``, no geosim code) sit at other places in the real scene than in the
    model, spread over every 32-px block of an 80 px scene; Gaussian noise of a known
    variance in the real scene only. Returns (real, model, mask of unchanged pixels)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import diagnose_generator as gen

    rng = np.random.default_rng(seed)
    n, phi = 80, 10
    ground = np.stack([100 + ndimage.gaussian_filter(rng.normal(0, 300, (n * phi, n * phi)), 12)
                       * f for f in (1.0, 0.9, 0.8)])
    cols = rng.uniform(20, 60, (14, 1)) * np.array([[1.0, 0.9, 0.8]])
    where = [rng.integers(40, n * phi - 40, (14, 2)) for _ in range(2)]
    horiz = rng.integers(0, 2, 14)
    fine_model = gen.paste_objects(ground, where[0], horiz, cols)
    fine_real = gen.paste_objects(ground, where[1], horiz, cols)

    def sample(img):
        return img.reshape(3, n, phi, n, phi).mean(axis=(2, 4))

    model, real = sample(fine_model), sample(fine_real)
    real = real + rng.normal(0, np.sqrt(noise_var_dn2), real.shape)
    changed = sample(np.abs(fine_model - fine_real).sum(axis=0)[None].repeat(3, 0))[0] > 0
    return real, model, ~ndimage.binary_dilation(changed, iterations=2)


def test_moved_objects_in_every_block_do_not_hide_the_noise_or_make_it():
    """Moved objects in every Welch block: their incoherent power rises towards low
    frequencies and, inside the windows, read as 'not white' (the noise was missed) or, with
    no noise, as noise. With the windows tapered by the mask of unchanged pixels the noise
    (8 DN² per band) is recovered and white, and without noise nothing is claimed."""
    real, model, mask = _moved_objects_scene(8.0)
    org = block_origins(real.shape[-2:], block_px=32)
    assert all(not mask[r:r + 32, c:c + 32].all() for r, c in org)   # objects everywhere
    est = estimate_noise(real, model, mask, origins=org, block_px=32, quantized=False)
    assert est.claimed, (est.white_var_dn2, est.whiteness)
    assert 0.7 * 8.0 < est.white_var_dn2 < 1.4 * 8.0, est.white_var_dn2
    quiet, model_q, mask_q = _moved_objects_scene(0.0)
    est0 = estimate_noise(quiet, model_q, mask_q, origins=org, block_px=32, quantized=False)
    assert not est0.claimed, (est0.white_var_dn2, est0.whiteness)
