"""Resampling under noise found by its coherent trace in the pixels.

The scenes come from the independent generator (``benchmarks/diagnose_generator.py``: the
native grid rendered on the 0.05 m grid, area-averaged, OpenCV's bicubic back onto the
product grid, Poisson-Gaussian noise), run blind through the whole diagnosis; the held-out
measure is checked on hand-made residual sums.
"""

from __future__ import annotations

import numpy as np
import pytest

import geosim.diagnose.stage_resampling_coherent as coherent
from geosim.diagnose.stage_resampling_coherent import CoherentScan
from tests.test_diagnose_independent import _run

NOISE = {"gain_dn": 0.18, "read_var_dn2": 3.6}


def test_heldout_dchi2_chooses_on_one_half_and_scores_the_other():
    left = np.zeros((2, 4), bool)
    left[:, :2] = True
    right = ~left   # 4 pixels each
    base = [[40.0, 80.0], [36.0, 88.0]]   # two Q factors
    resampled = [("r1", [30.0, 60.0]), ("r2", [20.0, 76.0])]
    scan = CoherentScan(halves=[left, right], base=base, resampled=resampled)  # type: ignore[arg-type]
    # chosen on the left: base Q 2 (36), resampled r2 (20); scored on the right: 88 → 76
    # in units of 88 / 4 per pixel; chosen on the right: Q 1 (80), r1 (60); on the left
    # 40 → 30 in units of 40 / 4
    assert scan.heldout_dchi2() == pytest.approx([(88 - 76) / 22, (40 - 30) / 10])
    assert scan.best() == "r1"   # lowest over both halves (90 against 96)


def test_resampling_under_noise_found_in_the_pixels():
    truth = {"resampling": {"native_pitch_px": 1.4}, "sensor_noise": NOISE}
    claimed, se_base, se_ref, _ = _run(truth, q=2.0, seed=27, sat_px=160)
    assert set(claimed) == {"resampling", "sensor_noise"}, list(claimed)
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - 1.4) <= 0.1
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_without_the_coherent_test_that_resampling_is_missed(monkeypatch):
    """The same scene with the coherent test switched off: the spectrum alone misses it
    (so the test above is this stage's)."""
    monkeypatch.setattr(coherent, "COHERENT_MIN_DCHI2", np.inf)
    truth = {"resampling": {"native_pitch_px": 1.4}, "sensor_noise": NOISE}
    claimed, _, _, _ = _run(truth, q=2.0, seed=27, sat_px=160)
    assert "resampling" not in claimed and "sensor_noise" in claimed, list(claimed)


def test_noise_alone_claims_no_resampling():
    claimed, se_base, se_ref, _ = _run({"sensor_noise": NOISE}, q=2.0, seed=28, sat_px=160)
    assert set(claimed) == {"sensor_noise"}, list(claimed)
    assert se_ref <= se_base
