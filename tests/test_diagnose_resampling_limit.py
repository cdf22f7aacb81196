"""The resampling detection limit: a native pitch is testable where the aliasing it would add
brings the scene's power spectrum clearly closer.

The predicted gain is checked against the RMS formula on hand-made bin vectors, the limit
against hand-made curves, and the whole measurement on synthetic scenes whose resampling
is rendered here with OpenCV (area down to the native grid, bicubic back up; not geosim's
renderer), for the properties it must have: a model that matches the scene leaves every
pitch testable, white noise in the scene raises the limit, a larger margin never lowers it.
"""

from __future__ import annotations

import functools
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from geosim.diagnose.detection_limits import combine_limits, limits_markdown
from geosim.diagnose.fit import TransferFit
from geosim.diagnose.model import CompressionFit, ForwardModel
from geosim.diagnose.resampling_limit import (
    KERNELS,
    PITCHES,
    ResamplingLimit,
    limit_from_curve,
    predicted_spectral_gain,
    resampling_limit,
)
from geosim.diagnose.select import BlurSelection
from geosim.diagnose.spectra import block_origins, log_power_ratio, spectral_error
from geosim.diagnose.stage_withdraw import (
    JPEG_NYQUIST_MARGIN,
    jpeg_native_floor_px,
    jpeg_resampling_beyond_optics,
    native_nyquist_floor_px,
    optics_pass_native_nyquist,
)
from geosim.diagnose.truth_compare import _limit_note
from tests.helpers import no_registration


def test_predicted_gain_is_the_drop_of_the_rms():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(8, 12))
    # a model that matches the scene: the resampling would explain all of its change
    assert predicted_spectral_gain(np.zeros_like(d), d) == pytest.approx(1.0)
    # a residual orthogonal to the change and as large: RMS(e - d) = √2 RMS(e)
    e = np.zeros((8, 12))
    e[0, :6], d2 = 1.0, np.zeros((8, 12))
    d2[0, 6:] = 1.0
    assert predicted_spectral_gain(e, d2) == pytest.approx(1.0 - 1.0 / np.sqrt(2.0))
    # empty bins (NaN in either) are left out
    e2, d3 = e.copy(), d2.copy()
    e2[5, :], d3[6, :] = np.nan, np.nan
    assert predicted_spectral_gain(e2, d3) == pytest.approx(1.0 - 1.0 / np.sqrt(2.0))
    # a change the residual already holds: the scene would move away, the gain is negative
    assert predicted_spectral_gain(d2, d2 * 0.5) < 0.0


def test_spectral_error_is_the_rms_of_the_log_power_ratio():
    rng = np.random.default_rng(1)
    a, b = rng.normal(size=(96, 96)), rng.normal(size=(96, 96)).cumsum(axis=1)
    origins = block_origins(a.shape, block_px=32)
    r = log_power_ratio(a, b, block_px=32, origins=origins)
    assert r.shape == (8, 12)
    ok = np.isfinite(r)
    assert spectral_error(a, b, block_px=32, origins=origins) == \
        float(np.sqrt(np.mean(r[ok] ** 2)))


@pytest.mark.parametrize(("gains", "need", "expected"), [
    ((0.0, 0.05, 0.15, 0.3), 0.1, 1.1 + 0.1 * 0.5),      # crossing between 1.1 and 1.2
    ((0.2, 0.3, 0.4, 0.5), 0.1, 1.0),                    # every pitch passes
    ((0.0, 0.05, 0.08, 0.09), 0.1, None),                # none does
    ((0.3, 0.05, 0.2, 0.4), 0.1, 1.1 + 0.1 * 0.05 / 0.15),  # a dip: above it only
])
def test_limit_from_curve(gains, need, expected):
    curve = tuple(zip((1.0, 1.1, 1.2, 1.3), gains, strict=True))
    got = limit_from_curve(curve, need)
    assert got == (None if expected is None else pytest.approx(expected))


def _texture(n: int, seed: int) -> np.ndarray:
    """A scene with a natural 1/f² power spectrum, blurred as optics would, 8-bit range."""
    rng = np.random.default_rng(seed)
    f = np.hypot(np.fft.fftfreq(n)[:, None], np.fft.fftfreq(n)[None, :])
    amp = 1.0 / np.maximum(f, 1.0 / n) * np.exp(-(f / 0.3) ** 2)
    img = np.real(np.fft.ifft2(amp * np.exp(2j * np.pi * rng.random((n, n)))))
    return 120.0 + 40.0 * img / img.std()


def _resampled(img: np.ndarray, pitch: float) -> np.ndarray:
    """The product grid → a native grid ``pitch`` times coarser (area) → bicubic back."""
    n = img.shape[0]
    m = int(round(n / pitch))
    small = cv2.resize(img, (m, m), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (n, n), interpolation=cv2.INTER_CUBIC)


@functools.cache
def _limit(noise_dn: float, margin: float = 1.0, floor: float | None = None
           ) -> ResamplingLimit:
    model = _texture(128, 3)
    rng = np.random.default_rng(4)
    real = model + rng.normal(0.0, noise_dn, model.shape)

    def render(params):
        img = model if params is None else _resampled(model, params["native_pitch_px"])
        # the model's expected spectrum with the scene's noise: mean of realisations
        return [img + np.random.default_rng(10 + k).normal(0.0, noise_dn, img.shape)
                for k in range(4)]

    origins = block_origins(real.shape, block_px=32)
    halves = [[o for o in origins if o[1] < 48], [o for o in origins if o[1] >= 48]]
    return resampling_limit(render, real, halves, block_px=32, q=2.0, need=0.1, margin=margin,
                            rule_floor_px=floor)


def test_limit_on_synthetic_scenes():
    clean = _limit(0.0)
    # the model is the scene: any resampling would be all the difference
    assert clean.limit == PITCHES[0]
    assert [p for p, _ in clean.curve] == list(PITCHES)
    assert all(g > 0.5 for _, g in clean.curve), clean.curve
    # white noise fills the high frequencies where the resampling acts: the predicted gain
    # falls at every pitch as it grows, and the limit rises until no pitch is testable
    by_noise = [_limit(n) for n in (5.0, 20.0, 35.0, 40.0, 50.0)]
    for a, b in zip([clean, *by_noise], by_noise, strict=False):
        assert all(gb < ga for (_, ga), (_, gb) in zip(a.curve, b.curve, strict=True))
    limits = [lim.limit for lim in by_noise]
    assert limits[:2] == [PITCHES[0]] * 2 and limits[-1] is None, limits
    assert PITCHES[0] < limits[2] < limits[3] < PITCHES[-1], limits
    # a larger margin asks more of the same curve
    for noise in (5.0, 20.0):
        lo, hi = _limit(noise, 1.0), _limit(noise, 8.0)
        assert hi.needed_gain == pytest.approx(8.0 * lo.needed_gain)
        assert hi.curve == lo.curve
        assert hi.limit is None or (lo.limit is not None and hi.limit >= lo.limit)


def test_jpeg_rule_floor():
    """Under JPEG the diagnosis withdraws a resampling whose native Nyquist the optics do
    not reach (pitch ≤ Q / 2): the stated limit is never below that, and the floor does not
    make a scene that tests nothing testable."""
    assert native_nyquist_floor_px(3.4) == pytest.approx(1.7)
    assert not optics_pass_native_nyquist(3.4, 1.7) and optics_pass_native_nyquist(3.4, 1.71)
    # the withdrawal asks for the fitted Q clearly beyond 2 x the fitted pitch: a pitch just
    # under Q / 2 (whose Nyquist the fitted optics miss by less than the margin) is kept
    assert JPEG_NYQUIST_MARGIN > 1.0
    assert jpeg_native_floor_px(3.4) == pytest.approx(1.7 / JPEG_NYQUIST_MARGIN)
    assert jpeg_native_floor_px(3.4) < 1.6 < native_nyquist_floor_px(3.4)
    clean = _limit(0.0)
    model = _texture(128, 3)
    origins = block_origins(model.shape, block_px=32)
    got = resampling_limit(lambda p: [model if p is None else
                                      _resampled(model, p["native_pitch_px"])],
                           model, [origins], block_px=32, q=3.4, need=0.2,
                           rule_floor_px=1.7)
    assert clean.limit == PITCHES[0] and got.limit == pytest.approx(1.7)
    assert got.rule_floor_px == 1.7 and got.to_json()["rule_floor_px"] == 1.7
    assert "under JPEG the optics at this Q pass nothing" in got.to_json()["note"]
    assert _limit(50.0, floor=1.7).limit is None and _limit(5.0, floor=1.7).limit == 1.7


def test_json_note_and_absorbs():
    lim = ResamplingLimit(1.42, 3.1, 0.1, tuple((p, 0.0) for p in PITCHES))
    assert lim.absorbs(1.3) and not lim.absorbs(1.6)
    doc = lim.to_json()
    assert (doc["param"], doc["absorbed_side"], doc["basis"]) == \
        ("native_pitch_px", "below", "measured_spectrum")
    assert doc["kernels_cubic_a"] == list(KERNELS) and len(doc["predicted_spectral_gain"]) == 8
    assert "finer than 1.42 px is not testable" in doc["note"]
    none = ResamplingLimit(None, 3.1, 0.1, ()).to_json()
    assert none["limit"] is None and "no resampling with a native pitch up to 2.00 px" in \
        none["note"]
    assert ResamplingLimit(None, 3.1, 0.1, ()).absorbs(2.5)
    # every scanned pitch testable: the note says so, and that finer grids are not scanned
    bottom = ResamplingLimit(PITCHES[0], 1.4, 0.1, ()).to_json()["note"]
    assert "native grid of 1.15-2.00 px is testable" in bottom
    assert "finer than 1.15 px is not tested (below the range the diagnosis scans" in bottom
    # the report lists it unless resampling was claimed
    text = "\n".join(limits_markdown({"resampling": doc}))
    assert "finer than 1.42 px" in text and "Such an effect is not claimed" in text
    assert limits_markdown({"resampling": doc}, claimed=["resampling"]) == []
    # a truth comparison sets a missed resampling against it
    assert _limit_note(doc, {"native_pitch_px": 1.3}) == (
        "below the stated detection limit native_pitch_px 1.42 at Q 3.10: aliasing not "
        "resolved by the scene's spectrum")
    assert _limit_note(doc, {"native_pitch_px": 1.6}).startswith("missed, though beyond")


def test_combined_over_flights():
    def res(limit):
        return {"resampling": ResamplingLimit(limit, 2.0, 0.1, ()).to_json()}

    flights = [res(1.3), res(1.6), res(None)]
    out = combine_limits(flights, need=2, q=2.5)
    r = out["resampling"]
    # two flights test resampling from 1.6 px; the one that tests none counts last
    assert r["limit"] == 1.6 and r["limit_by_flight"] == [1.3, 1.6, None]
    assert r["basis"] == "majority_of_flights" and r["q"] == 2.5
    assert "(resampling) from a native grid finer than 1.60 px is testable in fewer than 2 of 3 " \
        "flights" in r["note"]
    assert combine_limits(flights, need=3, q=2.5)["resampling"]["limit"] is None
    bottom = combine_limits([res(PITCHES[0])] * 2, need=2, q=2.5)["resampling"]["note"]
    assert "finer than 1.15 px is testable in fewer than 2 of 2" in bottom
    assert "below the range the diagnosis scans" in bottom
    # a flight that states no resampling limit (an older diagnosis.json) counts as none
    older = combine_limits([res(1.3), {}], need=1, q=2.5)["resampling"]
    assert older["limit"] == 1.3 and older["limit_by_flight"] == [1.3, None]
    # no flight states one: no entry
    assert "resampling" not in combine_limits([{}, {}], need=1, q=2.5)


def _resampled_under_jpeg(q: float, pitch_px: float) -> ForwardModel:
    reg = no_registration()
    return ForwardModel(q=q, blur={"resampling": {"native_pitch_px": pitch_px,
                                                  "cubic_a": -0.75}},
                        registration=reg,
                        compression=CompressionFit(quality=40, offset_px=(0, 0), test={}))


@pytest.mark.parametrize(("q", "pitch_px", "withdrawn"), [
    (2.82, 1.35, False),   # Q / (2 pitch) 1.04: within the fitted values' margin, kept
    (3.29, 1.49, False),   # 1.10
    (3.38, 1.30, True),    # 1.30: the optics clearly short of the native Nyquist
    (4.08, 1.20, True),    # 1.70
])
def test_jpeg_resampling_withdrawn_only_clearly_beyond_the_optics(q, pitch_px, withdrawn):
    """The rule on a model with resampling alone (Q then goes back to the null fit's)."""
    null = TransferFit(effects={}, sigmas={}, q=q * 1.1, gain=1.0, chi2=1.0, n_params=2,
                       n_eff=10.0)
    sel = BlurSelection(null=null, final=null)
    model = _resampled_under_jpeg(q, pitch_px)
    inp = SimpleNamespace(q_base=q)   # the refit without it needs only the baseline Q
    got, why = jpeg_resampling_beyond_optics(inp, model, sel, None)  # type: ignore[arg-type]
    assert ("resampling" not in got.blur) == withdrawn
    assert bool(why) == withdrawn
    if withdrawn:
        assert got.q == pytest.approx(q * 1.1) and "native pitch" in why[0]["reason"]
    else:
        assert got is model
    # without JPEG the claim always stands
    plain = model.without(compression=None)
    assert jpeg_resampling_beyond_optics(inp, plain, sel, None)[0] is plain  # type: ignore[arg-type]
