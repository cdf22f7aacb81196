"""JPEG quality and isotropic blur: the quality estimate depends on the model's sharpness.

Scenes from ``benchmarks/diagnose_generator.py`` (no geosim code; JPEG through Pillow).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.stage_inputs import grey, make_inputs  # noqa: E402
from geosim.diagnose.stage_jpeg import (  # noqa: E402
    blockiness,
    jpeg_quality_for_scale,
    jpeg_step_scale,
    match_quality,
)
from geosim.diagnose.stage_radiometry import band_affine  # noqa: E402


@pytest.mark.parametrize(("quality", "scale"), [(25, 200.0), (50, 100.0), (75, 50.0),
                                                (10, 500.0), (90, 20.0)])
def test_jpeg_step_scale_is_the_ijg_scaling(quality, scale):
    # IJG (libjpeg, Pillow, OpenCV): 5000/q below 50, 200 - 2q from 50 up (percent)
    assert jpeg_step_scale(quality) == pytest.approx(scale)
    assert jpeg_quality_for_scale(scale) == quality


def test_coarser_steps_mean_lower_quality():
    for q in (20, 33, 48, 55, 70):
        q_low = jpeg_quality_for_scale(1.25 * jpeg_step_scale(q))
        assert q_low < q
        # 25 % coarser steps: e.g. 40 -> 32, 60 -> 50
        assert jpeg_step_scale(q_low) == pytest.approx(
            1.25 * jpeg_step_scale(q), rel=0.06)


def _jpeg_scene(q: float, quality: int, seed: int, sat_px: int = 96):
    rng = np.random.default_rng(seed)
    ground = gen.synthetic_ground(rng, (sat_px + 24) * gen.PHI)
    uav, real = gen.render(ground, q, {"compression": {"quality": quality}}, rng,
                           margin_px=12)
    return uav, real


def test_quality_matched_on_the_right_model_and_biased_on_a_sharper_one():
    """The block-edge moment match recovers Pillow's quality when the model has the scene's
    sharpness (the paper's model at the true Q), and overestimates it on a sharper model
    (a Q too low, as the LV baseline under JPEG): the cause of the joint fixed point."""
    q_true, quality = 3.0, 40
    uav, real = _jpeg_scene(q_true, quality, seed=21)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    inp = make_inputs(real, sim, q_true, None, None, None, 0.5)
    blk = blockiness(grey(real - band_affine(sim(q_true), real, inp.valid)), inp.valid)
    offset = (int(blk["row_phase"]) % 8, int(blk["col_phase"]) % 8)
    right = match_quality(inp, band_affine(sim(q_true), real, inp.valid),
                          offset, fine_step=1)
    sharp = match_quality(inp, band_affine(sim(0.6 * q_true), real, inp.valid),
                          offset, fine_step=1)
    assert abs(right - quality) <= 6, right
    assert sharp > right + 4, (sharp, right)
