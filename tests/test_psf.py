"""PSF from Q: the paper's |DFT(pupil)|² against the analytic Airy pattern and the OTF."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special

from geosim.physics import psf
from geosim.physics.otf import frequency_grid, optics_otf

# x of the first zero of J1, from scipy's Bessel-zero table (not from the module under test).
J1_FIRST_ZERO = scipy.special.jn_zeros(1, 1)[0]


def _unit_energy_airy(r_px: np.ndarray, q: float, phi: float, eps: float = 0.0) -> np.ndarray:
    """Airy intensity normalised to unit integral: peak π/(4 (Qφ)²) · (1 − ε²) (analytic)."""
    return psf.airy_intensity(r_px, q=q, phi=phi, obscuration=eps) * (
        math.pi * (1 - eps**2) / (4 * (q * phi) ** 2))


@pytest.mark.parametrize("q", [0.5, 1.0, 2.0, 4.34, 6.0])
def test_pupil_psf_matches_analytic_airy(q: float) -> None:
    size = int(8 * q * 10) | 1
    airy = psf.airy_psf(q, phi=10, size_px=size)
    pupil = psf.pupil_psf(q, phi=10, size_px=size)
    assert airy.shape == pupil.shape == (size, size)
    assert np.abs(pupil - airy).max() <= 1e-3 * airy.max()
    assert airy.sum() == pytest.approx(1.0, abs=1e-12)
    assert pupil.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.unravel_index(pupil.argmax(), pupil.shape) == (size // 2, size // 2)


@pytest.mark.parametrize("q", [1.0, 2.0, 4.34])
def test_first_dark_ring_at_1_22_q_phi(q: float) -> None:
    phi = 10
    expected = J1_FIRST_ZERO / math.pi * q * phi  # 1.2197 Q φ
    assert expected == pytest.approx(1.2197 * q * phi, rel=1e-4)
    assert psf.first_zero_px(q, phi=phi) == pytest.approx(expected, rel=1e-12)
    size = int(3 * q * phi) | 1
    kernel = psf.pupil_psf(q, phi=phi, size_px=size)
    profile = kernel[size // 2, size // 2:]  # along +x from the centre, r = 0, 1, 2, ...
    i = int(np.argmax(np.diff(profile) > 0))  # first sample after which it rises again
    y0, y1, y2 = profile[i - 1], profile[i], profile[i + 1]
    vertex = i + 0.5 * (y0 - y2) / (y0 - 2 * y1 + y2)  # parabola through the minimum
    assert vertex == pytest.approx(expected, abs=0.02 * q * phi)
    assert profile[i] < 1e-3 * profile[0]  # a dark ring, not just a dip
    assert psf.airy_intensity(expected, q=q, phi=phi) < 1e-20


def test_pupil_psf_is_the_fft_of_the_pupil() -> None:
    """The matrix DFT equals numpy's FFT of the zero-padded pupil grid."""
    q, phi, size, radius = 1.0, 4, 41, 8.0
    kernel = psf.pupil_psf(q, phi=phi, size_px=size, pupil_radius_px=radius)
    n = max(math.ceil(2 * radius * q * phi), size)
    r = n / (2 * q * phi)
    u = np.fft.fftfreq(n) * n  # pupil sample coordinates, centred on frequency 0
    sub = (np.arange(16) + 0.5) / 16 - 0.5
    uu = u[:, None, None, None] + sub[None, None, :, None]
    vv = u[None, :, None, None] + sub[None, None, None, :]
    pupil = (np.hypot(uu, vv) <= r).mean(axis=(2, 3))  # 16×16 sub-sampled coverage
    full = np.fft.fftshift(np.abs(np.fft.fft2(pupil)) ** 2)
    c, h = n // 2, size // 2
    expected = full[c - h:c + h + 1, c - h:c + h + 1]
    expected /= expected.sum()
    assert np.abs(kernel - expected).max() < 1e-12


@pytest.mark.parametrize("eps", [0.0, 0.3])
def test_psf_is_the_inverse_transform_of_the_otf(eps: float) -> None:
    """Poisson summation: the inverse DFT of the OTF on an N grid is the periodised PSF."""
    q, phi, n = 1.0, 4, 256
    fy, fx = frequency_grid((n, n))
    from_otf = np.fft.fftshift(np.real(np.fft.ifft2(optics_otf(fy, fx, q=q, phi=phi,
                                                                 obscuration=eps))))
    offsets = np.arange(n) - n // 2
    r = np.hypot(offsets[:, None], offsets[None, :])
    analytic = _unit_energy_airy(r, q, phi, eps)
    assert from_otf.sum() == pytest.approx(1.0, abs=1e-12)
    assert np.abs(from_otf - analytic).max() < 1e-3 * analytic.max()


@pytest.mark.parametrize("eps", [0.0, 0.3])
def test_encircled_energy_against_sampled_sum(eps: float) -> None:
    q, phi = 1.0, 4.0
    h = 200
    offsets = np.arange(-h, h + 1)
    r = np.hypot(offsets[:, None], offsets[None, :])
    samples = _unit_energy_airy(r, q, phi, eps)  # band-limited: Σ samples = ∫ (Qφ > 2)
    for radius in (3.0, 10.0, 60.0, 150.0):
        numeric = samples[r <= radius].sum()
        assert psf.encircled_energy(radius, q=q, phi=phi, obscuration=eps) == pytest.approx(
            numeric, abs=3e-3)
    assert psf.encircled_energy(1e5, q=q, phi=phi, obscuration=eps) == pytest.approx(1, abs=1e-4)


def test_psf_size_holds_the_energy() -> None:
    q, phi = 0.5, 2.0  # small kernel: ~81 Qφ = 81 px
    size = psf.psf_size_px(q, phi=phi)
    assert size % 2 == 1
    radius = psf.energy_radius_px(q, phi=phi)
    assert radius == pytest.approx(40.5 * q * phi, rel=0.02)  # 1 − EE ≈ 2/(πx) asymptotics
    h = size // 2
    offsets = np.arange(-h, h + 1)
    inside = _unit_energy_airy(np.hypot(offsets[:, None], offsets[None, :]), q, phi).sum()
    assert inside >= 0.995
    r = np.hypot(offsets[:, None], offsets[None, :])
    samples = _unit_energy_airy(r, q, phi)
    assert samples[r <= radius + 0.5].sum() >= 0.995 - 1e-4  # the circle is tight
    assert samples[r <= 0.9 * radius].sum() < 0.995
    assert psf.airy_psf(q, phi=phi).shape == (size, size)


def test_obscuration_moves_energy_to_the_rings() -> None:
    clear = psf.airy_psf(2.0, phi=10, size_px=201)
    annular = psf.airy_psf(2.0, phi=10, size_px=201, obscuration=0.4)
    assert annular.sum() == pytest.approx(1.0)
    assert annular.max() < clear.max()  # less energy in the core
    assert np.abs(psf.pupil_psf(2.0, phi=10, size_px=201, obscuration=0.4)
                  - annular).max() <= 1e-3 * annular.max()


@pytest.mark.parametrize("kwargs", [
    {"q": 0.0}, {"q": -1.0}, {"q": float("nan")}, {"q": 1.0, "phi": 0},
    {"q": 1.0, "obscuration": 1.0}, {"q": 1.0, "size_px": 10}, {"q": 1.0, "size_px": 0},
])
def test_bad_parameters_raise(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        psf.airy_psf(**kwargs)
    with pytest.raises(ValueError):
        psf.pupil_psf(**kwargs)
