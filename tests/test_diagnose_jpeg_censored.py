"""A blur under JPEG read through the scene's quantisation intervals.

Truth from outside the code under test: Pillow's own quantisation table of the JPEG it
wrote, the image the JPEG was given (the likelihood must rank it first), and scenes made by
the independent generator (``benchmarks/diagnose_generator.py``: Pillow JPEG, the smear
drawn on the 0.05 m grid before sampling).
"""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from geosim.diagnose.jpeg_censored import censored_blocks, log_likelihood
from geosim.physics.radiometry import luma

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.simulate import QSimulator  # noqa: E402
from tests.generator_cases import diagnose_scene, render_scene  # noqa: E402


def _scene(seed: int = 3, n: int = 96) -> np.ndarray:
    """A smooth random texture, bands first, DN (a stand-in for a blurred product)."""
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.0)
    img = 120.0 + 25.0 * base / base.std()   # 16-220 DN: nothing clipped
    return np.stack([img, 0.9 * img + 10.0, 0.8 * img + 20.0])


def _pillow_jpeg(img: np.ndarray, quality: int) -> tuple[np.ndarray, np.ndarray]:
    """(decoded image, bands first; Pillow's luminance table, natural order)."""
    buf = io.BytesIO()
    Image.fromarray(np.clip(np.rint(img), 0, 255).astype(np.uint8).transpose(1, 2, 0)
                    ).save(buf, "JPEG", quality=quality)
    buf.seek(0)
    with Image.open(buf) as im:
        table = np.array(im.quantization[0])
        out = np.asarray(im.convert("RGB"), float).transpose(2, 0, 1)
    return out, table


@pytest.mark.parametrize("quality", [35, 60, 85])
def test_steps_are_the_encoders_table(quality):
    real, table = _pillow_jpeg(_scene(), quality)
    blocks = censored_blocks(luma(real), (0, 0), np.ones(real.shape[1:], bool))
    # every coefficient the lattice shows (texture reaches it) has Pillow's step; one with
    # a few non-zero values pins its lattice only to within one step unit
    assert blocks.coef.size >= 20
    expected = table[blocks.coef]
    seen = np.sum(blocks.index != 0, axis=0) >= 5
    assert seen.sum() >= 15
    assert np.array_equal(blocks.steps[seen], expected[seen]), (blocks.steps, expected)
    assert np.all(np.abs(blocks.steps - expected) <= 1), (blocks.steps, expected)


def test_the_image_the_jpeg_was_given_scores_best():
    truth = _scene()
    real, _ = _pillow_jpeg(truth, 50)
    blocks = censored_blocks(luma(real), (0, 0), np.ones(real.shape[1:], bool))
    ll = {}
    for sigma in (0.0, 0.4, 0.8):
        model = truth if sigma == 0 else np.stack(
            [ndimage.gaussian_filter(b, sigma) for b in truth])
        ll[f"blur {sigma}"] = log_likelihood(blocks, blocks.model_coefficients(luma(model)))
    sharper = truth + 0.5 * (truth - np.stack([ndimage.gaussian_filter(b, 0.8) for b in truth]))
    ll["sharper"] = log_likelihood(blocks, blocks.model_coefficients(luma(sharper)))
    assert max(ll, key=ll.get) == "blur 0.0", ll
    # the likelihood falls the further the model is from the truth
    assert ll["blur 0.0"] > ll["blur 0.4"] > ll["blur 0.8"], ll
    # on half the blocks it is the sum over them (no cross-talk between blocks)
    rows = np.arange(blocks.n_blocks)
    coef = blocks.model_coefficients(luma(truth))
    assert log_likelihood(blocks, coef, rows) == pytest.approx(ll["blur 0.0"])


def test_smear_under_strong_jpeg_found_through_the_intervals():
    # before the censored test this scene's smear went into Q (claimed: compression only).
    # At Q 3 the smear's sinc zero (0.42 cycles/px) lies beyond the optics' cut-off, so the
    # data cannot tell a smear from an off-nadir Gaussian: either may be claimed, with the
    # other as its alternative; the direction, Q and the fit are what the data decide
    truth = {"motion_smear": {"length_px": 2.4, "direction_deg": 100.0},
             "compression": {"quality": 45}}
    claimed, se_base, se_ref, d = diagnose_scene(truth, q=3.0, seed=23)
    aniso = {"motion_smear", "off_nadir_anisotropy"}
    assert set(claimed) - aniso == {"compression"}, list(claimed)
    assert len(set(claimed) & aniso) == 1, list(claimed)
    name = (set(claimed) & aniso).pop()
    p = claimed[name]["params"]
    direction = p.get("direction_deg", p.get("azimuth_deg"))
    assert abs((direction - 100.0 + 90) % 180 - 90) < 15, p
    assert {a["name"] for a in claimed[name]["alternatives"]} == aniso - {name}
    assert abs(d.summary["refined"]["q"] - 3.0) < 0.3, d.summary["refined"]["q"]
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_jpeg_alone_at_high_q_claims_no_blur_through_the_intervals():
    claimed, se_base, se_ref, _ = diagnose_scene({"compression": {"quality": 45}}, q=3.0, seed=22)
    assert set(claimed) == {"compression"}, list(claimed)
    assert se_ref <= se_base


def test_resampling_under_jpeg_named_through_the_intervals():
    # without the censored test Q took this resampling up (compression alone, Q 1.72 for
    # 1.05); through the intervals the native grid's aperture and aliasing are told from a
    # detector box or an atmosphere, which are listed as alternatives
    truth = {"resampling": {"native_pitch_px": 1.7}, "compression": {"quality": 50}}
    claimed, se_base, se_ref, d = diagnose_scene(truth, q=1.05, seed=25)
    assert set(claimed) == {"compression", "resampling"}, list(claimed)
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - 1.7) < 0.1
    assert abs(d.summary["refined"]["q"] - 1.05) < 0.1, d.summary["refined"]["q"]
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def _resampling_model(truth: dict, q: float, seed: int, pitch: float):
    """(inputs, a model holding a JPEG and a resampling of ``pitch``, window, ev) of a
    generator scene (synthetic ground, 96 px)."""
    from geosim.diagnose.context import EvalContext, FitWindow
    from geosim.diagnose.effects import BLUR_EFFECTS
    from geosim.diagnose.model import CompressionFit, ForwardModel
    from geosim.diagnose.spectra import block_origins
    from geosim.diagnose.stage_inputs import make_inputs
    from geosim.diagnose.stage_register import coregister

    uav, real = render_scene(truth, q, seed)
    inp = make_inputs(real, QSimulator(uav, phi=gen.PHI, q_min=0.6), q, None, None, True, 0.5)
    # the generator JPEGs the scene with its 12 px margin: blocks at 12 mod 16
    model = ForwardModel(q=q, blur={"resampling": {"native_pitch_px": pitch}},
                         registration=coregister(inp),
                         compression=CompressionFit(truth["compression"]["quality"], (12, 12),
                                                    {}))
    valid = np.ones(real.shape[-2:], bool)
    window = FitWindow(mask=valid, q_lo=0.7, q_hi=max(2.5, 1.3 * q), candidates=BLUR_EFFECTS,
                       q_starts=(q, 1.5))
    ev = EvalContext(mask=valid, origins=block_origins(valid.shape, block_px=32), block_px=32,
                     real_grey=inp.grey, noise_seed=0)
    return inp, model, window, ev


def test_resampling_under_jpeg_at_high_q_kept_only_where_the_intervals_want_it():
    from geosim.diagnose.stage_jpeg_blur import censored_resampling_check

    # a JPEG alone at Q 3.4, with a (false) 1.6 px resampling in the model: withdrawn, Q
    # fitted without it near the truth
    jpeg = {"compression": {"quality": 55}}
    inp, model, window, ev = _resampling_model(jpeg, 3.4, 31, 1.6)
    out, withdrawn = censored_resampling_check(inp, model, window, ev)
    assert [w["name"] for w in withdrawn] == ["resampling"] and out.blur == {}
    assert abs(out.q - 3.4) < 0.3, out.q
    # a true 1.5 px resampling under the same JPEG at Q 2.7 (the optics still pass some of
    # what its native grid aliases): kept
    truth = {"resampling": {"native_pitch_px": 1.5}, **jpeg}
    inp, model, window, ev = _resampling_model(truth, 2.7, 32, 1.5)
    out, withdrawn = censored_resampling_check(inp, model, window, ev)
    assert withdrawn == [] and out is model
