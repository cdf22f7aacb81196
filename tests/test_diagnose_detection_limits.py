"""Detection limits: the blurs a wider optical PSF absorbs at a given Q.

Checked against an independent implementation written here (numpy formulas for the
circular-aperture OTF, the detector's separable sinc, the atmospheric MTF, the smear's
sinc and the off-nadir Gaussian along one axis; the best wider PSF by Nelder-Mead over
(Q', gain)), and for the properties the limit must have.
The limits measured on a scene's transfer are checked on synthetic measured transfers
(the same formulas, a known per-frequency variance) against a brute-force search written
here and against the scaling the χ² must have.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from geosim.diagnose.detection_limits import (
    ANISOTROPIC_MARGIN,
    DETECTABLE_DIFFERENCE,
    DIRECTIONS_DEG,
    MEASURED_MARGIN,
    MeasuredTransfer,
    absorbed_difference,
    blur_evidence,
    combine_limits,
    detection_limit,
    detection_limits,
    detection_limits_json,
    limits_markdown,
    needed_delta_chi2,
    predicted_delta_chi2,
)
from geosim.diagnose.fit import HANN_CORRELATION, SpectralData
from geosim.diagnose.select import MIN_CV_GAIN, MIN_DELTA_BIC

F = np.linspace(0.0, 0.5, 121)[1:]
ANISOTROPIC = ("motion_smear", "off_nadir_anisotropy")


def _rays(max_deg: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    th = np.deg2rad(np.linspace(0.0, max_deg, n))
    fy, fx = F[None, :] * np.sin(th)[:, None], F[None, :] * np.cos(th)[:, None]
    return fy, fx, np.hypot(fy, fx)


def _airy_at(fr: np.ndarray, q: float) -> np.ndarray:
    v = np.clip(fr * q, 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(v) - v * np.sqrt(1 - v * v))


def _independent(q: float, name: str, value: float) -> float:
    if name in ANISOTROPIC:
        # along the x axis, against every frequency direction of a half plane
        fy, fx, fr = _rays(180.0, 37)
        blur = (np.sinc(fx * value) if name == "motion_smear"
                else np.exp(-2 * np.pi ** 2 * value ** 2 * fx ** 2))
    else:
        fy, fx, fr = _rays(45.0, 10)
        blur = (np.sinc(fx * value) * np.sinc(fy * value) if name == "detector_integration"
                else np.exp(-(fr / value) ** (5 / 3)))
    target = _airy_at(fr, q) * blur

    def _airy(qq: float) -> np.ndarray:
        return _airy_at(fr, qq)

    def err(x: np.ndarray) -> float:
        return float(np.sum((target - x[1] * _airy(x[0])) ** 2 * fr))

    r = minimize(err, np.array([1.05 * q, 1.0]), method="Nelder-Mead",
                 options={"xatol": 1e-6, "fatol": 1e-14, "maxiter": 4000})
    return float(np.max(np.abs(target - r.x[1] * _airy(r.x[0]))))


@pytest.mark.parametrize("q, name, value", [
    (1.5, "detector_integration", 1.0), (2.7, "detector_integration", 1.6),
    (4.4, "detector_integration", 1.2), (2.0, "atmospheric_blur", 0.45),
    (3.5, "atmospheric_blur", 0.9), (1.5, "motion_smear", 0.8), (3.0, "motion_smear", 2.0),
    (4.2, "motion_smear", 1.5), (2.0, "off_nadir_anisotropy", 0.3),
    (3.6, "off_nadir_anisotropy", 0.6)])
def test_difference_matches_an_independent_fit(q, name, value):
    got = absorbed_difference(q, name, value)
    want = _independent(q, name, value)
    assert got == pytest.approx(want, rel=0.08, abs=3e-4), (got, want)


def test_limit_sits_at_the_level_and_moves_with_q():
    det = [detection_limit(q, "detector_integration") for q in (1.5, 2.5, 3.5, 4.5)]
    atm = [detection_limit(q, "atmospheric_blur") for q in (1.5, 2.5, 3.5, 4.5)]
    for lim in det + atm:
        assert lim.limit is not None
        # the bisection stops within 0.5 % of the parameter around the crossing
        lo, hi = lim.limit / 1.006, lim.limit * 1.006
        weak, strong = (lo, hi) if lim.absorbed_side == "below" else (hi, lo)
        assert absorbed_difference(lim.q, lim.name, weak) < DETECTABLE_DIFFERENCE
        assert absorbed_difference(lim.q, lim.name, strong) >= DETECTABLE_DIFFERENCE
    # a wider optical PSF hides a wider detector box and a stronger atmosphere
    assert all(np.diff([d.limit for d in det[1:]]) > 0)
    assert all(np.diff([a.limit for a in atm]) < 0)
    # and a longer smear, a wider off-nadir blur
    for name in ANISOTROPIC:
        lims = [detection_limit(q, name) for q in (1.5, 2.5, 3.5, 4.5)]
        assert all(np.diff([x.limit for x in lims]) > 0), name
        for lim in lims:
            assert absorbed_difference(lim.q, name, lim.limit / 1.006) < DETECTABLE_DIFFERENCE
            assert absorbed_difference(lim.q, name, lim.limit * 1.006) >= DETECTABLE_DIFFERENCE


def test_absorbs_and_json():
    lim = detection_limit(4.0, "detector_integration")
    assert 1.4 < lim.limit < 1.9, lim.limit
    assert lim.absorbs(1.2) and not lim.absorbs(2.2)
    atm = detection_limit(4.0, "atmospheric_blur")
    assert atm.absorbs(2.0) and not atm.absorbs(0.3)
    doc = detection_limits_json(4.0)
    assert set(doc) == {"detector_integration", "atmospheric_blur", *ANISOTROPIC}
    d = doc["detector_integration"]
    assert (d["param"], d["absorbed_side"], d["q"]) == ("pitch_px", "below", 4.0)
    assert d["limit"] == pytest.approx(lim.limit)
    text = "\n".join(limits_markdown(doc))
    assert f"narrower than {lim.limit:.2f} px" in text and "What this scene cannot test" in text
    # a claimed blur gets no "cannot test" line (the data showed it)
    only_atm = "\n".join(limits_markdown(doc, claimed=["detector_integration"]))
    assert "detector box" not in only_atm and "atmospheric blur" in only_atm
    assert limits_markdown(doc, claimed=list(doc)) == []
    smear = detection_limit(4.0, "motion_smear")
    assert smear.absorbs(0.5 * smear.limit) and not smear.absorbs(2 * smear.limit)
    assert doc["motion_smear"]["param"] == "length_px"
    assert doc["off_nadir_anisotropy"]["param"] == "sigma_px"
    assert (f"a motion smear (motion_smear) shorter than {smear.limit:.2f} px, in any "
            "direction, is not testable") in text
    with pytest.raises(ValueError, match="no detection limit for 'haze'"):
        detection_limit(2.0, "haze")


# --- limits measured on the scene's transfer ------------------------------------------

def _blur_np(name: str, value: float, fy: np.ndarray, fx: np.ndarray,
             direction_deg: float = 0.0) -> np.ndarray:
    if name == "detector_integration":
        return np.sinc(fx * value) * np.sinc(fy * value)
    if name in ANISOTROPIC:
        # the frequency along a direction clockwise from grid north (rows grow southwards)
        th = np.deg2rad(direction_deg)
        f_par = fx * np.sin(th) - fy * np.cos(th)
        return (np.sinc(value * f_par) if name == "motion_smear"
                else np.exp(-2 * np.pi ** 2 * value ** 2 * f_par ** 2))
    return np.exp(-(np.hypot(fy, fx) / value) ** (5 / 3))


def _measured(q: float, sigma: float, *, blur: tuple[str, float] | None = None
              ) -> SpectralData:
    """A measured transfer on a 32 px Welch block's half plane: the Q grid's transfers
    are the circular-aperture OTF (numpy, written here), the scene's is OTF(q) (times a
    blur), every sample's variance sigma²."""
    f = np.fft.fftfreq(32)
    fy, fx = (a.ravel() for a in np.meshgrid(f, f, indexing="ij"))
    fr = np.hypot(fy, fx)
    keep = ((fx > 0) | ((fx == 0) & (fy > 0))) & (fr <= 0.5) & (fr > 0)
    fy, fx, fr = fy[keep], fx[keep], fr[keep]

    def airy(qq: float) -> np.ndarray:
        v = np.clip(fr * qq, 0.0, 1.0)
        return (2 / np.pi) * (np.arccos(v) - v * np.sqrt(1 - v * v))

    grid = np.exp(np.arange(np.log(0.7), np.log(6.0), np.log(1.04)))
    t = airy(q) * (_blur_np(*blur, fy, fx) if blur else 1.0)
    return SpectralData(fy=fy, fx=fx, t_real=t.astype(complex),
                        g_q=np.array([airy(g) for g in grid]).astype(complex), q_grid=grid,
                        var=np.full(fy.size, sigma ** 2), n_blocks=16)


def _brute_force(data: SpectralData, q: float, name: str, value: float,
                 direction_deg: float = 0.0) -> float:
    """The definition by exhaustive search on a dense log-Q grid (numpy only): the scene
    with the blur that matches the delivered Q-only model best, then the χ² of the best
    Q-only model to it (gains in closed form)."""
    w = 1.0 / data.var
    lq = np.log(data.q_grid)
    dense = np.exp(np.linspace(lq[0], lq[-1], 6001))

    def g_at(qq: float) -> np.ndarray:
        x = np.interp(np.log(qq), lq, np.arange(lq.size))
        j = min(int(x), lq.size - 2)
        return (1 - (x - j)) * data.g_q[j].real + (x - j) * data.g_q[j + 1].real

    units = np.array([g_at(qq) for qq in dense])
    h = _blur_np(name, value, data.fy, data.fx, direction_deg)

    def best(target: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        g = (u * w * target).sum(1) / (u * w * u).sum(1)
        return ((target - g[:, None] * u) ** 2 * w).sum(1), g

    delivered = g_at(q)
    c1, g1 = best(delivered, units * h)
    k = int(np.argmin(c1))
    scene = g1[k] * units[k] * h
    return float(best(scene, units)[0].min())


@pytest.mark.parametrize("q, name, value", [
    (1.4, "detector_integration", 1.3), (3.0, "detector_integration", 1.6),
    (2.0, "atmospheric_blur", 0.4), (3.5, "atmospheric_blur", 0.6)])
def test_predicted_evidence_matches_a_brute_force_search(q, name, value):
    data = _measured(q, 0.01)
    m = MeasuredTransfer.of(data, q, {})
    got = predicted_delta_chi2(m, name, value)
    want = _brute_force(data, q, name, value)
    assert got == pytest.approx(want, rel=0.03), (got, want)
    # the delivered model fits the scene but for the Q grid's log-linear interpolation
    assert m.gain == pytest.approx(1.0, abs=1e-3) and m.chi2 < 0.02 * got


@pytest.mark.parametrize("q, name, value, direction_deg", [
    (2.0, "motion_smear", 1.5, 0.0), (3.2, "motion_smear", 2.2, 73.0),
    (2.6, "off_nadir_anisotropy", 0.5, 140.0)])
def test_anisotropic_evidence_matches_a_brute_force_search(q, name, value, direction_deg):
    data = _measured(q, 0.01)
    m = MeasuredTransfer.of(data, q, {})
    got = predicted_delta_chi2(m, name, value, direction_deg)
    want = _brute_force(data, q, name, value, direction_deg)
    assert got == pytest.approx(want, rel=0.03), (got, want)
    # the limit's evidence: the most favourable of the scanned directions
    each = [_brute_force(data, q, name, value, d) for d in DIRECTIONS_DEG]
    assert blur_evidence(m, name, value) == pytest.approx(max(each), rel=0.03)


def test_anisotropic_evidence_follows_the_measurement_direction():
    """A scene whose transfer is measured well along one axis only: a smear along that
    axis is resolved, one across it is not, and the stated limit (any direction) follows
    the favourable one."""
    q = 2.5
    data = _measured(q, 0.01)
    # frequencies within ~11° of the x axis measured 100× better than the rest (a scene
    # textured along one axis)
    data.var[np.abs(data.fy) > 0.2 * np.abs(data.fx)] = 1.0
    m = MeasuredTransfer.of(data, q, {})
    along_x, along_y = (predicted_delta_chi2(m, "motion_smear", 2.0, d) for d in (90.0, 0.0))
    assert along_x > 10 * along_y, (along_x, along_y)
    each = [predicted_delta_chi2(m, "motion_smear", 2.0, d) for d in DIRECTIONS_DEG]
    assert blur_evidence(m, "motion_smear", 2.0) == pytest.approx(max(each), rel=1e-12)
    assert max(each) >= along_x
    lim = detection_limit(q, "motion_smear", measured=m)
    need = needed_delta_chi2(m, ANISOTROPIC_MARGIN, n_params=2)
    assert lim.limit is not None and lim.needed_delta_chi2 == pytest.approx(need)
    assert predicted_delta_chi2(m, "motion_smear", lim.limit * 1.006, 90.0) >= need
    assert max(predicted_delta_chi2(m, "motion_smear", lim.limit / 1.006, d)
               for d in DIRECTIONS_DEG) < need


def test_predicted_evidence_scales_with_the_measurement_and_the_blur():
    q = 2.5
    m1 = MeasuredTransfer.of(_measured(q, 0.01), q, {})
    m2 = MeasuredTransfer.of(_measured(q, 0.02), q, {})
    for name, weak, strong in (("detector_integration", 0.9, 1.5),
                               ("atmospheric_blur", 0.9, 0.35)):
        # χ² is inverse in the variance: twice the standard error, a quarter of the evidence
        a, b = predicted_delta_chi2(m1, name, strong), predicted_delta_chi2(m2, name, strong)
        assert b == pytest.approx(a / 4, rel=1e-3)
        assert predicted_delta_chi2(m1, name, weak) < a


def test_needed_evidence_is_the_claim_rule():
    data = _measured(2.0, 0.01)
    n_values = 2 * data.t_real.size
    small = MeasuredTransfer(data, 2.0, 1.0, {}, chi2=0.5 * n_values)
    # a good fit: ΔBIC decides (scale 1)
    assert needed_delta_chi2(small, margin=1.0) == pytest.approx(
        (MIN_DELTA_BIC + np.log(data.n_eff)) * HANN_CORRELATION)
    # a blur with a direction pays the BIC penalty for its second parameter
    assert needed_delta_chi2(small, margin=1.0, n_params=2) == pytest.approx(
        (MIN_DELTA_BIC + 2 * np.log(data.n_eff)) * HANN_CORRELATION)
    # a poor fit (other physics unmodelled): both rules grow with its χ² (ΔBIC through the
    # variance scale, the held-out gain relative to it); the stricter is needed
    big = MeasuredTransfer(data, 2.0, 1.0, {}, chi2=40.0 * n_values)
    by_bic = (MIN_DELTA_BIC + np.log(data.n_eff)) * HANN_CORRELATION * big.chi2 / (n_values - 3)
    by_gain = MIN_CV_GAIN / (1 - MIN_CV_GAIN) * big.chi2
    assert needed_delta_chi2(big, margin=1.0) == pytest.approx(max(by_bic, by_gain))
    assert needed_delta_chi2(big, margin=1.0) > 40 * needed_delta_chi2(small, margin=1.0) * 0.99
    one = needed_delta_chi2(big, margin=1.0)
    assert needed_delta_chi2(big, margin=2.0) == pytest.approx(2 * one)
    # the stated limits ask MEASURED_MARGIN times the rule
    assert needed_delta_chi2(big) == pytest.approx(
        MEASURED_MARGIN * needed_delta_chi2(big, margin=1.0))
    # with many frequencies (64 px blocks) the held-out gain is the stricter
    many_data = SpectralData(fy=np.zeros(2000), fx=np.zeros(2000),
                             t_real=np.zeros(2000, complex), g_q=data.g_q[:, :1],
                             q_grid=data.q_grid, var=np.ones(2000), n_blocks=16)
    many = MeasuredTransfer(many_data, 2.0, 1.0, {}, chi2=40.0 * 4000)
    assert needed_delta_chi2(many, margin=1.0) == pytest.approx(
        MIN_CV_GAIN / (1 - MIN_CV_GAIN) * many.chi2)


def test_measured_limit_is_stated_when_stricter():
    q = 3.0
    transfer_only = detection_limit(q, "detector_integration")
    # a precise measurement: the optics' own limit holds
    sharp = detection_limit(q, "detector_integration",
                            measured=MeasuredTransfer.of(_measured(q, 1e-4), q, {}))
    assert sharp.measured and sharp.measured_limit < sharp.transfer_limit
    assert sharp.limit == pytest.approx(transfer_only.limit)
    # a noisy measurement: the scene's own limit is wider and is the one stated
    noisy = detection_limit(q, "detector_integration",
                            measured=MeasuredTransfer.of(_measured(q, 0.015), q, {}))
    assert noisy.limit == noisy.measured_limit > transfer_only.limit
    assert noisy.absorbs(0.5 * (noisy.limit + transfer_only.limit))
    doc = noisy.to_json()
    assert doc["basis"] == "measured_transfer" and "measured transfer does not resolve" in \
        doc["note"]
    assert len(doc["predicted_delta_chi2"]) >= 8 and doc["needed_delta_chi2"] > 0
    # at the limit the predicted evidence reaches what a claim needs
    m = MeasuredTransfer.of(_measured(q, 0.015), q, {})
    need = needed_delta_chi2(m)
    assert predicted_delta_chi2(m, "detector_integration", noisy.limit * 1.006) >= need
    assert predicted_delta_chi2(m, "detector_integration", noisy.limit / 1.006) < need
    # so poor a measurement that no blur in range is testable
    hopeless = detection_limit(q, "atmospheric_blur",
                               measured=MeasuredTransfer.of(_measured(q, 30.0), q, {}))
    assert hopeless.limit is None and "no atmospheric_blur" in hopeless.to_json()["note"]
    assert hopeless.to_json()["basis"] == "measured_transfer"
    # every blur's limit is stated, also beside a delivered anisotropic blur (there: the
    # evidence an additional one would add); the report then leaves out the whole family,
    # which the data showed
    smeared = MeasuredTransfer.of(_measured(q, 0.015, blur=("motion_smear", 1.5)), q,
                                  {"motion_smear": {"length_px": 1.5, "direction_deg": 0.0}})
    doc = {lim.name: lim.to_json() for lim in detection_limits(q, smeared)}
    assert list(doc) == ["detector_integration", "atmospheric_blur", *ANISOTROPIC]
    text = "\n".join(limits_markdown(doc, claimed=["motion_smear"]))
    assert "detector box" in text and "motion smear" not in text and "off-nadir" not in text
    assert "off-nadir blur (off_nadir_anisotropy) with σ below" in "\n".join(
        limits_markdown(doc, claimed=["detector_integration"]))
    # the optics find no limit (a level no blur reaches) while the scene would: the note
    # and basis name the optics
    optics = detection_limit(q, "detector_integration", level=10.0,
                             measured=MeasuredTransfer.of(_measured(q, 1e-4), q, {}))
    assert optics.transfer_limit is None and optics.measured_limit is not None
    doc = optics.to_json()
    assert optics.limit is None and doc["basis"] == "transfer_difference"
    assert "differs from a slightly wider optical PSF by less than" in doc["note"]


def test_combined_limits_need_a_majority_of_flights():
    def flight(det, atm):
        return {"detector_integration": {"limit": det}, "atmospheric_blur": {"limit": atm}}

    flights = [flight(0.8, 1.2), flight(1.0, 0.9), flight(None, 0.5)]
    out = combine_limits(flights, need=2, q=2.0)
    # two flights test detectors from 1.0 px, two test atmospheres below f0 0.9
    assert out["detector_integration"]["limit"] == 1.0
    assert out["atmospheric_blur"]["limit"] == 0.9
    assert out["detector_integration"]["limit_by_flight"] == [0.8, 1.0, None]
    assert out["detector_integration"]["q"] == 2.0
    assert "narrower than 1.00 px is testable in fewer than 2 of 3 flights" in \
        out["detector_integration"]["note"]
    # all three needed: the least sensitive flight; never testable in one -> never
    assert combine_limits(flights, need=3, q=2.0)["detector_integration"]["limit"] is None
    assert combine_limits(flights, need=3, q=2.0)["atmospheric_blur"]["limit"] == 0.5
    # flights without an anisotropic limit (older documents, or the family claimed there)
    # count as the optics' own limit at the median Q
    smear_q = detection_limit(2.0, "motion_smear").limit
    assert out["motion_smear"]["limit"] == pytest.approx(smear_q)
    withs = [dict(f, motion_smear={"limit": v}) for f, v in zip(flights, (1.2, 3.0, None),
                                                                 strict=True)]
    assert combine_limits(withs, need=2, q=2.0)["motion_smear"]["limit"] == 3.0
