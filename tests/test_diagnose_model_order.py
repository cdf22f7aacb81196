"""The refined forward model's order of operations and the plausibility limits of blurs."""

from __future__ import annotations

import numpy as np

from geosim.diagnose.coregister import AffineEstimate
from geosim.diagnose.model import CompressionFit, ForwardModel, NoiseEstimate
from geosim.diagnose.select import clearly_present, plausible
from geosim.diagnose.stage_register import field_sigma_px
from tests.helpers import no_registration


def test_compression_acts_last_on_the_noisy_rounded_product():
    rng = np.random.default_rng(3)
    img = np.clip(rng.normal(120, 30, (3, 64, 64)), 0, 255)
    comp = CompressionFit(quality=40, offset_px=(0, 0), test={})
    noise = NoiseEstimate(gain_dn=0.0, read_var_dn2=9.0, gain_sigma=0.0, read_sigma=0.0,
                          white_var_dn2=9.0, whiteness=1.0, claimed=True, quantization_dn2=0.0)
    m = ForwardModel(q=1.0, blur={}, registration=no_registration(), compression=comp, noise=noise)
    sim = lambda q: img  # noqa: E731
    got = m.delivered(sim, np.random.default_rng(5), quantized=True)
    # by hand: noise on the sharp product, whole DN, then JPEG
    noisy = img + np.random.default_rng(5).normal(0.0, 3.0, img.shape)
    want = comp.apply(np.round(noisy))
    assert np.array_equal(got, want)
    # the deterministic model: JPEG of the blurred product (no noise), not of the
    # simulation before the blur
    m2 = m.without(noise=None, blur={"atmospheric_blur": {"f0_cyc_per_px": 0.3}})
    det = m2.deterministic(sim)
    assert np.array_equal(det, comp.apply(m2.blurred(sim)))
    assert not np.array_equal(det, m2.blurred(sim))


def test_detector_wider_than_two_pixels_is_implausible():
    assert plausible("detector_integration", {"pitch_px": 1.4})
    assert not plausible("detector_integration", {"pitch_px": 2.4})
    assert plausible("atmospheric_blur", {"f0_cyc_per_px": 0.05})
    assert clearly_present("detector_integration", {"pitch_px": 2.4})


def test_field_sigma_scales_with_scatter_and_blocks():
    g = np.mgrid[8:128:8, 8:128:8].reshape(2, -1).T.astype(float)
    local = np.column_stack([g, np.zeros((len(g), 2))])
    corners = np.array([[0, 0], [128, 0], [0, 128], [128, 128]], float) - 64.0

    def aff(resid: float, n: int) -> AffineEstimate:
        return AffineEstimate((0.0, 0.0), np.zeros((2, 2)), (64.0, 64.0), 0.0, 1.0, resid, n,
                              local[:n])

    s1 = field_sigma_px(aff(0.5, len(local)), corners)
    # analytic: resid · r_max / sqrt(n/4 · mean|x − c|²)
    pos = local[:, :2] - 64.0
    want = 0.5 * np.hypot(64, 64) / np.sqrt(len(local) / 4 * np.mean(pos**2))
    assert np.isclose(s1, want)
    assert np.isclose(field_sigma_px(aff(1.0, len(local)), corners), 2 * s1)
