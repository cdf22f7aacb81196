"""JPEG quality: the IJG step scaling, and the quality read from the scene's own lattice
whatever the blur.

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

from geosim.diagnose.jpeg_quality import ijg_luma_steps, lattice_quality  # noqa: E402
from geosim.diagnose.stage_inputs import grey  # noqa: E402
from geosim.diagnose.stage_jpeg import jpeg_quality_for_scale, jpeg_step_scale  # noqa: E402


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


@pytest.mark.parametrize(("q", "quality", "jpeg"), [
    (0.9, 60, "pillow_420"), (0.9, 27, "pillow_444"), (3.0, 40, "opencv_422"),
    (3.0, 73, "pillow_420"), (1.6, 12, "opencv_422")])
def test_quality_is_read_from_the_scene_whatever_the_blur(q, quality, jpeg):
    """The quality comes from the scene's own quantisation lattice, so it is the encoder's
    (Pillow or OpenCV, any chroma subsampling) under very sharp optics (Q 0.9, where the
    earlier match of block-edge steps against a re-encoded model gave 13 for 27) as under
    soft ones, with noise before the JPEG (it dithers the values, not the lattice)."""
    rng = np.random.default_rng(int(100 * q) + quality)
    ground = gen.synthetic_ground(rng, (96 + 24) * gen.PHI)
    truth = {"sensor_noise": {"gain_dn": 0.2, "read_var_dn2": 6.0}}
    _, img = gen.render(ground, q, truth, rng, margin_px=12)
    real = (gen.jpeg_opencv_422(img, quality) if jpeg == "opencv_422" else
            gen.jpeg_pillow(img, quality, subsampling=0 if jpeg == "pillow_444" else -1))
    g = grey(real)
    got = lattice_quality(g, (0, 0), np.ones(g.shape, bool))
    assert np.array_equal(ijg_luma_steps(got.quality), ijg_luma_steps(quality)), got
    assert got.log_lik_margin > 10.0, got
    # on another block grid there is no lattice to read: not the quality
    off = lattice_quality(g, (3, 5), np.ones(g.shape, bool))
    assert abs(off.quality - quality) > 5 or off.log_lik_margin < got.log_lik_margin / 10


@pytest.mark.parametrize("quality", [5, 27, 44, 50, 60, 90, 97])
def test_ijg_luma_steps_are_the_table_pillow_writes(quality):
    """The step table an IJG encoder uses, as Pillow reports it from the JPEG's DQT segment
    (natural order)."""
    from io import BytesIO

    from PIL import Image

    img = Image.fromarray(np.random.default_rng(quality).integers(0, 256, (16, 16, 3),
                                                                   dtype=np.uint8))
    buf = BytesIO()
    img.save(buf, format="JPEG", quality=quality)
    buf.seek(0)
    written = np.array(list(Image.open(buf).quantization[0]))
    assert np.array_equal(ijg_luma_steps(quality), written)
