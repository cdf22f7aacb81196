"""Detection limits: the isotropic blurs a wider optical PSF absorbs at a given Q.

Checked against an independent implementation written here (numpy formulas for the
circular-aperture OTF, the detector's separable sinc and the atmospheric MTF; the best
wider PSF by Nelder-Mead over (Q', gain)), and for the properties the limit must have.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import minimize

from geosim.diagnose.detection_limits import (
    DETECTABLE_DIFFERENCE,
    absorbed_difference,
    detection_limit,
    detection_limits_json,
    limits_markdown,
)

F = np.linspace(0.0, 0.5, 121)[1:]
TH = np.deg2rad(np.linspace(0.0, 45.0, 10))
FY, FX = F[None, :] * np.sin(TH)[:, None], F[None, :] * np.cos(TH)[:, None]
FR = np.hypot(FY, FX)


def _airy(q: float) -> np.ndarray:
    v = np.clip(FR * q, 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(v) - v * np.sqrt(1 - v * v))


def _independent(q: float, name: str, value: float) -> float:
    blur = (np.sinc(FX * value) * np.sinc(FY * value) if name == "detector_integration"
            else np.exp(-(FR / value) ** (5 / 3)))
    target = _airy(q) * blur

    def err(x: np.ndarray) -> float:
        return float(np.sum((target - x[1] * _airy(x[0])) ** 2 * FR))

    r = minimize(err, np.array([1.05 * q, 1.0]), method="Nelder-Mead",
                 options={"xatol": 1e-6, "fatol": 1e-14, "maxiter": 4000})
    return float(np.max(np.abs(target - r.x[1] * _airy(r.x[0]))))


@pytest.mark.parametrize("q, name, value", [
    (1.5, "detector_integration", 1.0), (2.7, "detector_integration", 1.6),
    (4.4, "detector_integration", 1.2), (2.0, "atmospheric_blur", 0.45),
    (3.5, "atmospheric_blur", 0.9)])
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


def test_absorbs_and_json():
    lim = detection_limit(4.0, "detector_integration")
    assert 1.4 < lim.limit < 1.9, lim.limit
    assert lim.absorbs(1.2) and not lim.absorbs(2.2)
    atm = detection_limit(4.0, "atmospheric_blur")
    assert atm.absorbs(2.0) and not atm.absorbs(0.3)
    doc = detection_limits_json(4.0)
    assert set(doc) == {"detector_integration", "atmospheric_blur"}
    d = doc["detector_integration"]
    assert (d["param"], d["absorbed_side"], d["q"]) == ("pitch_px", "below", 4.0)
    assert d["limit"] == pytest.approx(lim.limit)
    text = "\n".join(limits_markdown(doc))
    assert f"narrower than {lim.limit:.2f} px" in text and "What this scene cannot test" in text
    # a claimed blur gets no "cannot test" line (the data showed it)
    only_atm = "\n".join(limits_markdown(doc, claimed=["detector_integration"]))
    assert "detector box" not in only_atm and "atmospheric blur" in only_atm
    assert limits_markdown(doc, claimed=list(doc)) == []
    with pytest.raises(ValueError, match="no detection limit for 'haze'"):
        detection_limit(2.0, "haze")
