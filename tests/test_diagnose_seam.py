"""Exposure seams must not be absorbed into the satellite's haze (regression: flight PA2 of
the sample site, whose 7 % seam across half the window gave t = 0.63, L = 44 DN in green)."""

import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.fit import fit_radiometry
from geosim.diagnose.seam import find_gain_step, step_side

T = np.array([0.99, 0.94, 0.91])
L = np.array([7.8, 9.9, 15.2])
CORR = 4.0 * np.pi * 2.0**2


def _scene(seam_gain: float, rng: np.random.Generator):
    """Ground with a narrow brightness range (like pasture), satellite = t·ground + L with
    noise and shadow-like outliers; the UAV model = ground × seam_gain left of a diagonal."""
    shape = (160, 170)
    base = ndimage.gaussian_filter(rng.normal(0, 1, shape), 6)
    base = 95 + 18 * base / base.std()
    ground = np.stack([base * 0.95, base, base * 0.65])
    sat = T[:, None, None] * ground + L[:, None, None] + rng.normal(0, 2.0, (3, *shape))
    # shadows in the UAV only (dark in the model, sunlit in the satellite)
    shadow = ndimage.gaussian_filter(rng.random(shape), 2) > 0.56
    model = ground * np.where(shadow, 0.55, 1.0)
    left = step_side(shape, normal_deg=140.0, offset_px=4.0)
    model = model * np.where(left, seam_gain, 1.0)
    lp = lambda img: np.stack([ndimage.gaussian_filter(b, 2.0) for b in img])  # noqa: E731
    return lp(model), lp(sat), np.ones(shape, bool), left


def test_seam_breaks_a_single_regression_and_is_found():
    rng = np.random.default_rng(3)
    model, sat, mask, left = _scene(0.93, rng)
    # one global regression threads between the two sides: offsets ≫ the path radiance
    naive = fit_radiometry(model, sat, mask, corr_px2=CORR)
    assert np.all(naive.offset_dn - L > 4.0)
    st = find_gain_step(model, sat, mask, corr_px2=CORR)
    assert st is not None
    # the stepped (darker) side is the seam's left side, factor = 1 / 0.93
    assert np.mean(st.side[mask] == left[mask]) > 0.97
    assert st.factor == pytest.approx(1 / 0.93, rel=0.01)
    corrected = model * np.where(st.side, st.factor, 1.0)
    fr = fit_radiometry(corrected, sat, mask, corr_px2=CORR)
    # relative to the brighter (right) side: exactly the satellite's haze
    np.testing.assert_allclose(fr.gain, T, atol=0.02)
    np.testing.assert_allclose(fr.offset_dn, L, atol=2.0)


def test_no_seam_no_claim():
    rng = np.random.default_rng(4)
    model, sat, mask, _ = _scene(1.0, rng)
    assert find_gain_step(model, sat, mask, corr_px2=CORR) is None
    fr = fit_radiometry(model, sat, mask, corr_px2=CORR)
    np.testing.assert_allclose(fr.gain, T, atol=0.02)
