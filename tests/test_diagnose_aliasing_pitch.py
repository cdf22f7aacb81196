"""A resampling's native pitch fitted on the transfer is moved to where the power spectrum
puts it (``stage_aliasing._pitch_on_spectrum``): the scan's minimum, not an end of the
scan, only where it is better, not under JPEG, and the claim (the selection's steps)
follows."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.fit import TransferFit, build_spectral_data, evaluate_chi2
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.select import AcceptedEffect, BlurSelection
from geosim.diagnose.stage_aliasing import (
    PITCH_SCAN,
    PITCH_STEP,
    _pitch_on_spectrum,
    _selected_pitch_on_spectrum,
)
from geosim.diagnose.stage_blur import SpectralSetup

RES = {"native_pitch_px": 1.3, "cubic_a": -0.75}
ATM = {"f0_cyc_per_px": 0.4}


def _setup() -> SpectralSetup:
    rng = np.random.default_rng(0)
    scene = rng.normal(size=(96, 96)) * 20 + 128
    q_grid = np.array([0.8, 1.2, 1.8, 2.7, 4.0])
    sims = [ndimage.gaussian_filter(scene, 0.3 * q) for q in q_grid]
    origins = [(r, c) for r in range(0, 65, 32) for c in range(0, 65, 32)]
    full = build_spectral_data(sims, q_grid, sims[2], origins=origins, block_px=32)
    return SpectralSetup(q_grid=q_grid, sims_grey=sims, origins=origins, block_px=32,
                         full=full, folds=[], n_screened=0)


def _fit(pitch: float = 1.3) -> TransferFit:
    return TransferFit(effects={"atmospheric_blur": dict(ATM),
                                "resampling": {**RES, "native_pitch_px": pitch}},
                       sigmas={"q": 0.05, "gain": 0.01, "atmospheric_blur": {"f0_cyc_per_px": 0.02},
                               "resampling": {"native_pitch_px": 0.02, "cubic_a": 0.1}},
                       q=1.8, gain=1.0, chi2=123.0, n_params=5, n_eff=80.0)


def _model() -> ForwardModel:
    return ForwardModel(q=1.8, blur={"atmospheric_blur": dict(ATM), "resampling": dict(RES)},
                        registration=None)  # type: ignore[arg-type]


def _se_with_minimum_at(p0: float):
    return lambda m: 0.05 + (m.blur["resampling"]["native_pitch_px"] - p0) ** 2


def test_pitch_moves_to_the_spectral_minimum_on_the_scan():
    setup, fit, model = _setup(), _fit(), _model()
    se_of = _se_with_minimum_at(1.62)
    new_fit, new_model = _pitch_on_spectrum(setup, fit, model, se_of(model), se_of)
    p = new_model.blur["resampling"]
    assert p == {"native_pitch_px": 1.6, "cubic_a": -0.75}       # nearest scanned pitch
    assert new_fit.effects["resampling"] == p and new_fit.effects["atmospheric_blur"] == ATM
    assert (new_fit.q, new_fit.gain, new_model.q) == (1.8, 1.0, 1.8)
    # the transfer's view of the moved pitch, and the scan's step as its uncertainty
    assert new_fit.chi2 == pytest.approx(evaluate_chi2(setup.full, q=1.8, gain=1.0,
                                                       effects=new_fit.effects))
    assert new_fit.sigmas["resampling"] == {"native_pitch_px": PITCH_STEP, "cubic_a": 0.1}
    assert model.blur["resampling"] == RES and fit.effects["resampling"]["native_pitch_px"] == 1.3


@pytest.mark.parametrize("p0, se_fit", [(1.0, None), (2.4, None), (1.62, 0.0)])
def test_pitch_kept_at_an_end_of_the_scan_or_where_nothing_is_better(p0, se_fit):
    setup, fit, model = _setup(), _fit(), _model()
    se_of = _se_with_minimum_at(p0)
    got = _pitch_on_spectrum(setup, fit, model, se_of(model) if se_fit is None else se_fit,
                             se_of)
    assert got[0] is fit and got[1] is model
    assert PITCH_SCAN[0] == 1.15 and PITCH_SCAN[-1] == 2.0


def test_pitch_kept_under_jpeg():
    setup, fit = _setup(), _fit()
    model = _model().without(compression=object())
    se_of = _se_with_minimum_at(1.62)
    got = _pitch_on_spectrum(setup, fit, model, se_of(model), se_of)
    assert got[0] is fit and got[1] is model


def test_a_selected_resampling_claims_the_moved_pitch():
    setup, model = _setup(), _model()
    atm_only = TransferFit(effects={"atmospheric_blur": dict(ATM)}, sigmas={}, q=1.8,
                           gain=1.0, chi2=200.0, n_params=3, n_eff=80.0)
    sel = BlurSelection(null=atm_only, final=_fit(),
                        steps=[AcceptedEffect("atmospheric_blur", 30.0, 0.2, [], atm_only),
                               AcceptedEffect("resampling", 20.0, 0.1, [], _fit())])
    moved = _selected_pitch_on_spectrum(sel, setup, model, _se_with_minimum_at(1.62))
    assert moved.blur["resampling"]["native_pitch_px"] == 1.6
    assert sel.steps[1].fit.effects["resampling"]["native_pitch_px"] == 1.6
    assert sel.final.effects["resampling"]["native_pitch_px"] == 1.6
    assert sel.steps[0].fit is atm_only          # the steps before it are left alone
