"""The refined simulation judged over the whole extent at the configured Welch block.

Where scene changes put the fit on 16 px Welch blocks, the never-worse guard and the moved
objects' test also judge the refined simulation on the configured (32 px) blocks over the
whole extent; the scenes below, from the independent generator, are scored by the
generator's own spectral error (its own Welch estimate, not geosim's).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.context import EvalContext, whole_extents  # noqa: E402
from geosim.diagnose.engine import diagnose_arrays  # noqa: E402
from geosim.diagnose.grids import calibrate_q_lv  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.physics.radiometry import luma  # noqa: E402


def _ev(shape: tuple[int, int]) -> EvalContext:
    return EvalContext(mask=np.ones(shape, bool), origins=[(0, 0)], block_px=16,
                       real_grey=np.zeros(shape), noise_seed=0)


def test_whole_extents_configured_block_first_and_only_where_blocks_fit():
    valid = np.ones((128, 128), bool)
    ev = _ev(valid.shape)
    both = whole_extents(ev, valid, (32, 16))
    # half-overlapping blocks: (128 - 32) / 16 + 1 = 7 and (128 - 16) / 8 + 1 = 15 per side
    assert [(w.block_px, len(w.origins)) for w in both] == [(32, 49), (16, 225)]
    assert all(w.mask is valid and w.noise_seed == ev.noise_seed for w in both)
    assert [w.block_px for w in whole_extents(ev, valid, (32, 32))] == [32]
    strip = np.zeros_like(valid)
    strip[:20] = True   # no 32 px block fits in 20 rows; a row of 16 px blocks does
    assert [(w.block_px, len(w.origins)) for w in whole_extents(ev, strip, (32, 16))] == \
        [(16, 15)]
    assert whole_extents(ev, np.zeros_like(valid), (32, 16)) == []


@pytest.mark.parametrize("index", [865, 868])
def test_refined_no_worse_at_the_configured_block_when_fitted_on_small_blocks(
        realdata, samples_dir, index):
    # development c865 (a control) and c868 (JPEG only): fitted on 16 px blocks, their
    # refined simulations were better than the baseline there and worse on 32 px blocks
    # (c865 by its Q alone, c868 with a false motion smear)
    case = gen.make_case(index, gen.pick_sources(gen.list_sources(realdata, samples_dir)))
    sim = QSimulator(case.uav, phi=gen.PHI, q_min=0.6)
    q_base = calibrate_q_lv(sim, luma(case.real), np.ones(case.real.shape[-2:], bool))
    d = diagnose_arrays(case.real, sim, q_base=q_base, rng=np.random.default_rng(0), q_lo=0.7)
    s = d.summary
    assert (s["settings"]["block_px"], s["settings"]["block_px_whole"]) == (16, 32)
    assert s["refined"]["spectral_error_whole"] <= s["baseline"]["spectral_error_whole"]
    assert gen.spectral_error(np.rint(d.refined), case.real) <= \
        gen.spectral_error(np.rint(d.baseline), case.real)
    assert {e["name"] for e in s["effects"]} <= set(case.truth)


def test_refined_judged_as_delivered_with_its_moved_objects(realdata, samples_dir):
    # development c331 (JPEG 27, colour, moved objects), fitted on 16 px blocks: without
    # its moved objects the refined model is worse than the baseline on 32 px blocks (the
    # benchmark's 0.283 against 0.233), with them much better; judging the model before
    # the objects on 32 px blocks had withdrawn everything
    case = gen.make_case(331, gen.pick_sources(gen.list_sources(realdata, samples_dir)))
    sim = QSimulator(case.uav, phi=gen.PHI, q_min=0.6)
    q_base = calibrate_q_lv(sim, luma(case.real), np.ones(case.real.shape[-2:], bool))
    d = diagnose_arrays(case.real, sim, q_base=q_base, rng=np.random.default_rng(0), q_lo=0.7)
    s = d.summary
    claims = {e["name"]: e for e in s["effects"]}
    assert s["settings"]["block_px"] == 16 and "scene_change" in claims
    assert claims["scene_change"]["params"]["n_objects_modelled"] > 0
    assert s["refined"]["spectral_error_whole"] < s["baseline"]["spectral_error_whole"]
    assert gen.spectral_error(np.rint(d.refined), case.real) < \
        0.75 * gen.spectral_error(np.rint(d.baseline), case.real)
