"""The benchmark's ideal observer (benchmarks/diagnose_ideal.py): its evidence for a blur
is large where the blur is plain and small where a Q change explains it within the noise."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402
import diagnose_ideal as ideal  # noqa: E402


def _inputs(q: float, truth: dict) -> gen.CaseInputs:
    ground = gen.synthetic_ground(np.random.default_rng(11), (40 + 2 * 12) * gen.PHI)
    return gen.CaseInputs(index=0, seed=0, source="synthetic", q=q, truth=truth,
                          ground=ground, rng=np.random.default_rng(4))


def test_a_wide_box_at_low_q_is_plain_and_a_narrow_one_in_noise_at_high_q_is_not():
    plain = ideal.assess_inputs(_inputs(1.2, {"detector_integration": {"pitch_px": 1.6}}))
    e = plain["ideal"]["detector_integration"]
    assert e["detectable"] and e["delta_chi2"] > 1000
    assert e["q_without"] > 1.2                   # Q widens to stand in for the box
    assert plain["error_var_dn2"] == pytest.approx([1 / 12] * 3, abs=0.01)  # whole DN only
    hidden = ideal.assess_inputs(_inputs(4.3, {
        "detector_integration": {"pitch_px": 0.9},
        "sensor_noise": {"gain_dn": 0.4, "read_var_dn2": 12.0}}))
    h = hidden["ideal"]["detector_integration"]
    assert not h["detectable"] and 0 <= h["delta_chi2"] < ideal.THRESHOLD
    assert h["signature_rms_dn"] < 0.1 * np.sqrt(min(hidden["error_var_dn2"]))


def test_the_best_alternative_is_no_worse_than_the_true_q_without_the_effect():
    """The Q search finds at least what Q unchanged gives (the evidence is a minimum)."""
    inp = _inputs(2.0, {"atmospheric_blur": {"f0_cyc_per_px": 0.3}})
    _, clean = gen.render(inp.ground, inp.q, inp.truth, np.random.default_rng(4),
                          margin_px=12, noise_free=True)
    _, same_q = gen.render(inp.ground, inp.q, {}, np.random.default_rng(4), margin_px=12,
                           noise_free=True)
    inv_var = np.full(3, 12.0)
    d2, q_alt, _ = ideal.best_without(inp, "atmospheric_blur", clean, inv_var)
    assert d2 <= ideal.weighted_rss(clean, ideal.affine_fit(clean, same_q), inv_var)
    assert q_alt > inp.q


def test_a_long_smear_at_low_q_is_nameable_and_a_short_one_at_high_q_is_not():
    """A 3 px smear at Q 1.2 is told from any off-nadir Gaussian; a 1.5 px one at Q 4 is
    plainly there (Q cannot stand in for it) but its shape is not (the naming evidence is
    far below the blur's own)."""
    long = ideal.assess_inputs(_inputs(1.2, {"motion_smear": {"length_px": 3.0,
                                                               "direction_deg": 30.0}}))
    v = long["ideal"]["motion_smear"]
    assert v["nameable"] and v["naming_delta_chi2"] > 100
    short = ideal.assess_inputs(_inputs(4.0, {"motion_smear": {"length_px": 1.5,
                                                                "direction_deg": 30.0}}))
    w = short["ideal"]["motion_smear"]
    assert w["detectable"] and w["naming_delta_chi2"] < 0.05 * w["delta_chi2"]
