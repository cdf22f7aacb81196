"""Cubic convolution with any kernel parameter: against the kernel's defining properties,
a numerical Fourier transform, OpenCV (a = −0.75) and Pillow (a = −0.5)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from PIL import Image

from geosim.diagnose.effects import get_effect
from geosim.physics import radiometry
from geosim.physics.cubic import KEYS_A, OPENCV_A, cubic_mtf, cubic_resize, keys_kernel


@pytest.mark.parametrize("a", [-1.0, OPENCV_A, KEYS_A])
def test_kernel_interpolates_and_sums_to_one(a):
    assert keys_kernel(np.array([0.0]), a)[0] == 1.0
    np.testing.assert_allclose(keys_kernel(np.array([-2.0, -1.0, 1.0, 2.0, 2.5]), a), 0.0,
                               atol=1e-15)
    x = np.linspace(0.0, 1.0, 11)
    total = sum(keys_kernel(x - n, a) for n in range(-3, 5))
    np.testing.assert_allclose(total, 1.0, atol=1e-12)


@pytest.mark.parametrize("a", [-1.0, OPENCV_A, -0.6, KEYS_A])
def test_mtf_is_the_kernels_fourier_transform(a):
    """Against numpy's FFT of the kernel sampled at 1/64 sample (written here)."""
    step = 1.0 / 64
    x = np.arange(-4.0, 4.0, step)
    k = keys_kernel(x, a)
    spec = np.real(np.fft.fft(np.fft.ifftshift(k))) * step
    nu = np.fft.fftfreq(x.size, d=step)
    sel = (nu >= 0) & (nu <= 2.0)
    np.testing.assert_allclose(cubic_mtf(nu[sel], a), spec[sel], atol=2e-3)


def test_mtf_is_linear_in_a():
    nu = np.linspace(0.0, 1.5, 31)
    mid = cubic_mtf(nu, -0.625)
    np.testing.assert_allclose(mid, 0.5 * (cubic_mtf(nu, OPENCV_A) + cubic_mtf(nu, KEYS_A)),
                               atol=1e-12)
    # Keys' a = -0.5 is the softer kernel: 4-5 % less transfer at 0.2-0.3 cycles/sample
    assert 0.03 < cubic_mtf(np.array([0.25]), OPENCV_A)[0] - cubic_mtf(np.array([0.25]),
                                                                      KEYS_A)[0] < 0.06


def test_resize_matches_opencv_and_pillow():
    rng = np.random.default_rng(0)
    band = rng.uniform(0, 255, (85, 90)).astype(np.float32)
    ocv = cv2.resize(band, (128, 120), interpolation=cv2.INTER_CUBIC)
    np.testing.assert_array_equal(cubic_resize(band, (120, 128), OPENCV_A), ocv)
    # the matrix route at OpenCV's a reproduces OpenCV's geometry (float32 rounding)
    np.testing.assert_allclose(cubic_resize(band, (120, 128), OPENCV_A + 1e-12), ocv,
                               atol=1e-3)
    # Pillow's bicubic is Keys a = -0.5; Pillow renormalises the kernel at the edges
    # where OpenCV replicates the edge samples, so compare away from them
    pil = np.asarray(Image.fromarray(band, "F").resize((128, 120), Image.BICUBIC))
    np.testing.assert_allclose(cubic_resize(band, (120, 128), KEYS_A)[3:-3, 3:-3],
                               pil[3:-3, 3:-3], atol=1e-3)


def test_keys_reproduces_quadratics_opencv_does_not():
    n_in, n_out = 40, 64
    x_in = (np.arange(n_in) + 0.5) * n_out / n_in        # input centres, output px units
    x_out = np.arange(n_out) + 0.5
    band = np.repeat((0.01 * x_in ** 2)[np.newaxis], 6, axis=0)
    inner = slice(6, n_out - 6)
    keys = cubic_resize(band, (6, n_out), KEYS_A)[3, inner]
    ocv = cubic_resize(band, (6, n_out), OPENCV_A)[3, inner]
    assert np.max(np.abs(keys - 0.01 * x_out[inner] ** 2)) < 1e-9
    assert np.max(np.abs(ocv - 0.01 * x_out[inner] ** 2)) > 5e-3


@pytest.mark.parametrize("a", [OPENCV_A, KEYS_A])
def test_resampling_effect_transfer_matches_its_render(a):
    """The resampling effect's analytic transfer against the cross-spectrum its own render
    measures on white noise (average over realisations), for both kernels."""
    rng = np.random.default_rng(3)
    n, pitch = 120, 1.5
    eff = get_effect("resampling")
    fy = np.fft.fftfreq(n)[:, None] * np.ones((1, n))
    fx = np.fft.fftfreq(n)[None, :] * np.ones((n, 1))
    num = np.zeros((n, n), complex)
    den = np.zeros((n, n))
    for _ in range(12):
        img = rng.normal(0.0, 1.0, (1, n, n))
        out = radiometry.resample_through_native(img, native_pitch_px=pitch, cubic_a=a)
        fi, fo = np.fft.fft2(img[0]), np.fft.fft2(out[0])
        num += fo * np.conj(fi)
        den += np.abs(fi) ** 2
    measured = np.real(num / den)
    model = eff.transfer(fy, fx, native_pitch_px=pitch, cubic_a=a)
    low = np.hypot(fy, fx) < 0.25          # below the native Nyquist, 1/(2 · 1.5)
    assert np.sqrt(np.mean((measured[low] - model[low]) ** 2)) < 0.06
    other = eff.transfer(fy, fx, native_pitch_px=pitch,
                         cubic_a=KEYS_A if a == OPENCV_A else OPENCV_A)
    assert np.mean(np.abs(measured[low] - model[low])) < np.mean(np.abs(measured[low]
                                                                        - other[low]))
