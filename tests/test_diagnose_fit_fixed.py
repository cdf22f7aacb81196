"""Transfer fits with an effect held at given parameters (``fit_transfer(fixed=)``).

The measured transfer is built analytically: a Gaussian optical family G(q)(f) =
exp(−(π f q / 2)²) on a grid of q, times the resampling's own transfer at known parameters
and a known gain. Nothing here comes from a fit.
"""

from __future__ import annotations

import numpy as np
import pytest

from geosim.diagnose.effects import get_effect
from geosim.diagnose.fit import SpectralData, fit_transfer

Q_TRUE = 2.4
GAIN = 0.9
RESAMPLING = {"native_pitch_px": 1.6, "cubic_a": -0.75}


def _data(extra: dict[str, dict[str, float]]) -> SpectralData:
    f = np.fft.fftfreq(32)
    fy, fx = (a.ravel() for a in np.meshgrid(f, f, indexing="ij"))
    half = (fy > 0) | ((fy == 0) & (fx > 0))
    fy, fx = fy[half], fx[half]
    q_grid = np.geomspace(0.6, 6.0, 60)
    g_q = np.array([np.exp(-(np.pi * np.hypot(fy, fx) * q / 2) ** 2) for q in q_grid])
    t = GAIN * np.exp(-(np.pi * np.hypot(fy, fx) * Q_TRUE / 2) ** 2)
    for name, p in extra.items():
        t = t * get_effect(name).transfer(fy, fx, **p)
    return SpectralData(fy=fy, fx=fx, t_real=t.astype(complex), g_q=g_q, q_grid=q_grid,
                        var=np.full(fy.size, 1e-4), n_blocks=16)


def test_held_resampling_lets_q_come_out_true():
    data = _data({"resampling": RESAMPLING})
    held = fit_transfer(data, [], q_starts=(2.0,), fixed={"resampling": RESAMPLING})
    assert held.q == pytest.approx(Q_TRUE, rel=2e-3)
    assert held.gain == pytest.approx(GAIN, rel=2e-3)
    assert held.effects == {"resampling": RESAMPLING}
    assert held.n_params == 2  # Q and gain: the held effect is not fitted
    assert "resampling" not in held.sigmas
    # without it Q takes up the resampling's roll-off (wider) and fits worse
    alone = fit_transfer(data, [], q_starts=(2.0,))
    assert alone.q > 1.02 * Q_TRUE
    assert alone.chi2 > 100 * max(held.chi2, 1e-9)


def test_other_blur_fitted_beside_a_held_resampling():
    atmosphere = {"f0_cyc_per_px": 0.35}
    data = _data({"resampling": RESAMPLING, "atmospheric_blur": atmosphere})
    fit = fit_transfer(data, ["atmospheric_blur"], q_starts=(2.0,),
                       fixed={"resampling": RESAMPLING})
    assert fit.q == pytest.approx(Q_TRUE, rel=1e-2)
    assert fit.effects["atmospheric_blur"]["f0_cyc_per_px"] == pytest.approx(0.35, rel=1e-2)
    assert fit.effects["resampling"] == RESAMPLING


def test_a_fitted_effect_is_not_also_held():
    # an effect both fitted and held is fitted (the held copy is ignored)
    data = _data({"resampling": RESAMPLING})
    fit = fit_transfer(data, ["resampling"], q_starts=(2.0,),
                       fixed={"resampling": {"native_pitch_px": 1.2, "cubic_a": -0.5}})
    assert fit.n_params == 4
    assert fit.effects["resampling"]["native_pitch_px"] == pytest.approx(1.6, abs=0.05)
