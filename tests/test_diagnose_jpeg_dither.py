"""JPEG of a noisy product: noise dithers the quantisation; the JPEG's own lattice.

Scenes from ``benchmarks/diagnose_generator.py`` (no geosim code: Poisson-Gaussian noise,
whole DN, JPEG through Pillow). The truth is the generator's quality and whether it
compressed at all.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.jpeg_noise import MIN_LATTICE_GAIN, lattice_evidence  # noqa: E402
from geosim.diagnose.model import NoiseEstimate  # noqa: E402
from geosim.diagnose.noise import noise_dither  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.stage_inputs import grey, make_inputs  # noqa: E402
from geosim.diagnose.stage_jpeg import (  # noqa: E402
    blockiness,
    find_compression,
)
from geosim.diagnose.stage_radiometry import band_affine  # noqa: E402
from geosim.diagnose.stage_register import coregister  # noqa: E402
from tests.generator_cases import render_scene  # noqa: E402

#: the block-edge step test that gated compression until round 16 (ratio of the step
#: phase to the others and z-score, both axes): a tiled pattern passes it
BLOCK_STEP_RATIO = 1.2
BLOCK_STEP_Z = 3.0


def _noise(gain_dn: float, read_var_dn2: float) -> NoiseEstimate:
    return NoiseEstimate(gain_dn=gain_dn, read_var_dn2=read_var_dn2, gain_sigma=0.0,
                         read_sigma=0.0, white_var_dn2=read_var_dn2, whiteness=1.0,
                         claimed=True, quantization_dn2=1 / 12)


def test_no_dither_without_claimed_noise():
    assert noise_dither(None) is None
    n = _noise(0.1, 5.0)
    n.claimed = False
    assert noise_dither(n) is None


def test_block_steps_without_a_lattice_are_not_compression():
    """An uncompressed scene with 8-periodic steps added (a structured residual that is not
    a JPEG: a tiled brightness pattern, 3 DN) passes the block-step test but has no
    quantisation lattice in its DCT coefficients, so no compression is claimed; Pillow's
    JPEG of the same scene at quality 40 and 65 has the lattice and is claimed."""
    q_true = 1.5
    uav, real = render_scene({}, q_true, 11)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    rows, cols = real.shape[-2:]
    tiles = 3.0 * (((np.arange(rows)[:, None] // 8) + (np.arange(cols)[None] // 8)) % 2)
    stepped = np.clip(np.rint(real + tiles), 0, 255)
    inp = make_inputs(stepped, sim, q_true, None, None, None, 0.5)
    reg = coregister(inp)
    blk = blockiness(grey(stepped - band_affine(reg.move(inp.base), stepped, inp.valid)),
                     inp.valid)
    assert min(blk["row_ratio"], blk["col_ratio"]) > BLOCK_STEP_RATIO
    assert min(blk["row_z"], blk["col_z"]) > BLOCK_STEP_Z
    offset = (int(blk["row_phase"]) % 8, int(blk["col_phase"]) % 8)
    assert lattice_evidence(inp.grey, offset, inp.valid) < MIN_LATTICE_GAIN
    assert find_compression(inp, reg) is None
    for quality in (40, 65):
        jp = gen.jpeg_pillow(np.clip(np.rint(real), 0, 255), quality)
        inp_j = make_inputs(jp, sim, q_true, None, None, None, 0.5)
        assert lattice_evidence(inp_j.grey, (0, 0), inp_j.valid) > MIN_LATTICE_GAIN
        found = find_compression(inp_j, coregister(inp_j))
        assert found is not None and found.quality == quality, (quality, found)
