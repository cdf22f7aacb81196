"""The anisotropic member the transfer named, checked against the other in the pixels.

Scenes from the independent generator (``benchmarks/diagnose_generator.py``: a box smear
or a line Gaussian applied on the 0.05 m grid before sampling, no geosim code); the model
is handed the wrong member with the true blur's second moment and direction (what the
transfer sees of it), or the right one.
"""

from __future__ import annotations

import numpy as np
import pytest

import geosim.diagnose.stage_anisotropic_member as am
from geosim.diagnose.context import ChangedRegions, EvalContext, FitWindow
from geosim.diagnose.effects import BLUR_EFFECTS
from geosim.diagnose.fit import fit_transfer
from geosim.diagnose.model import CompressionFit, ForwardModel
from geosim.diagnose.select import AcceptedEffect, BlurSelection
from geosim.diagnose.spectra import block_origins
from geosim.diagnose.stage_blur import spectral_setup
from geosim.diagnose.stage_claims import claim_effects
from geosim.diagnose.stage_resampling_coherent import checker_halves
from tests.generator_cases import no_registration, scene_inputs

Q = 2.0
SMEAR = {"motion_smear": {"length_px": 3.0, "direction_deg": 110.0}}
#: the off-nadir elongation of the smear's second moment (a box of length L: L²/12)
SMEAR_AS_OFF_NADIR = {"off_nadir_anisotropy": {"sigma_px": 3.0 / np.sqrt(12.0),
                                               "azimuth_deg": 110.0}}
OFF_NADIR = {"off_nadir_anisotropy": {"sigma_px": 0.9, "azimuth_deg": 40.0}}
OFF_NADIR_AS_SMEAR = {"motion_smear": {"length_px": 0.9 * np.sqrt(12.0),
                                       "direction_deg": 40.0}}


def _scene(truth: dict) -> tuple:
    inp, real = scene_inputs(truth, q=Q, seed=43, sat_px=64)
    mask = np.ones(real.shape[-2:], bool)
    ev = EvalContext(mask=mask, origins=block_origins(mask.shape, block_px=32, valid=mask),
                     block_px=32, real_grey=inp.grey, noise_seed=0)
    return inp, ev


def _angle_deg(a: float, b: float) -> float:
    return abs((a - b + 90.0) % 180.0 - 90.0)


@pytest.mark.parametrize("truth, swapped", [(SMEAR, SMEAR_AS_OFF_NADIR),
                                            (OFF_NADIR, OFF_NADIR_AS_SMEAR)])
def test_member_check_names_the_generators_shape(truth, swapped):
    """Handed the other member, both halves want the true one by over twice the margin
    (measured 156 / 125 for the smear, 110 / 69 for the off-nadir blur),
    whose fit recovers the generator's width and direction; handed the true member, both
    halves want it kept."""
    inp, ev = _scene(truth)
    halves = checker_halves(ev)
    name = next(iter(truth))
    check = am.member_check(inp, ForwardModel(q=Q, blur=swapped,
                                              registration=no_registration()), halves)
    assert check.other == name
    assert min(check.naming_dchi2) > 2 * am.MEMBER_MIN_DCHI2, check.naming_dchi2
    got, want = check.best_other().blur[name], truth[name]
    width, direction = list(want)
    assert abs(got[width] - want[width]) < 0.1 * want[width], got
    assert _angle_deg(got[direction], want[direction]) < 3.0, got
    kept = am.member_check(inp, ForwardModel(q=Q, blur=truth,
                                             registration=no_registration()), halves)
    assert max(kept.naming_dchi2) < -am.MEMBER_MIN_DCHI2, kept.naming_dchi2


def _selection(inp, name: str) -> tuple[ForwardModel, BlurSelection, object]:
    """The transfer's fit of ``name`` alone on the scene, as the selection's one step."""
    window = FitWindow(mask=inp.valid, q_lo=0.7, q_hi=3.0, candidates=BLUR_EFFECTS,
                       q_starts=(Q, 1.5))
    setup = spectral_setup(inp, ForwardModel(q=Q, blur={}, registration=no_registration()),
                           window)
    null = fit_transfer(setup.full, [], q_starts=(Q,))
    fit = fit_transfer(setup.full, [name], q_starts=(Q,))
    sel = BlurSelection(null=null, final=fit,
                        steps=[AcceptedEffect(name, 50.0, 0.1, [], fit)])
    model = ForwardModel(q=fit.q, blur={name: dict(fit.effects[name])},
                         registration=no_registration())
    return model, sel, setup


def test_pixel_member_renames_the_selections_step_and_the_claim_says_so():
    """A smear the transfer named off-nadir: the stage names the smear, replaces the step
    (its fit holds the smear at the fitted Q) and the claim records the transfer's member
    and the pixels' evidence as its ``test``; the claim keeps the transfer's gain."""
    inp, ev = _scene(SMEAR)
    model, sel, setup = _selection(inp, "off_nadir_anisotropy")
    out = am.pixel_member(inp, model, sel, setup, ev, BLUR_EFFECTS)
    assert set(out.blur) == {"motion_smear"}
    assert abs(out.blur["motion_smear"]["length_px"] - 3.0) < 0.3, out.blur
    step = sel.steps[0]
    assert step.name == "motion_smear" and sel.final is step.fit
    assert step.fit.effects["motion_smear"] == out.blur["motion_smear"]
    assert step.fit.q == pytest.approx(out.q) and step.heldout_gain == 0.1
    assert step.test["transfer_named"] == "off_nadir_anisotropy"
    assert min(step.test["naming_dchi2"]) >= am.MEMBER_MIN_DCHI2
    # the transfer's member stays on record as the alternative, with its parameters
    assert [a.name for a in step.alternatives] == ["off_nadir_anisotropy"]
    assert step.alternatives[0].params == model.blur["off_nadir_anisotropy"]
    change = ChangedRegions(regions=[], labels=np.zeros(inp.valid.shape, int),
                            inner=inp.valid)
    claims = claim_effects(inp, out, sel, change, ev)
    smear = next(c for c in claims if c.name == "motion_smear").to_json()
    assert smear["test"]["transfer_named"] == "off_nadir_anisotropy"
    assert smear["params"] == out.blur["motion_smear"]
    assert [a["name"] for a in smear["alternatives"]] == ["off_nadir_anisotropy"]


def test_pixel_member_keeps_the_right_member():
    inp, ev = _scene(SMEAR)
    model, sel, setup = _selection(inp, "motion_smear")
    step = sel.steps[0]
    assert am.pixel_member(inp, model, sel, setup, ev, BLUR_EFFECTS) is model
    assert sel.steps[0] is step and step.test is None


@pytest.mark.parametrize("change", ["jpeg", "no_other_candidate", "two_members", "none"])
def test_pixel_member_domain(monkeypatch, change):
    """Not tested under JPEG, where the other member is not a candidate, where the model
    holds both members or neither (no fitting is run)."""
    calls = []
    monkeypatch.setattr(am, "member_check", lambda *a, **k: calls.append(a))
    model = ForwardModel(q=Q, blur=dict(SMEAR), registration=no_registration())
    candidates = BLUR_EFFECTS
    if change == "jpeg":
        model = model.without(compression=CompressionFit(quality=80, offset_px=(0, 0), test={}))
    elif change == "no_other_candidate":
        candidates = tuple(n for n in BLUR_EFFECTS if n != "off_nadir_anisotropy")
    elif change == "two_members":
        model = model.without(blur={**SMEAR, **SMEAR_AS_OFF_NADIR})
    else:
        model = model.without(blur={})
    assert am.pixel_member(None, model, None, None, None, candidates) is model
    assert not calls


def test_report_says_the_member_was_named_in_the_pixels():
    """report.md: a renamed member's line gives the transfer's member and the halves'
    evidence with ΔBIC as its evidence (the lattice's wording is the JPEG's alone)."""
    from geosim.diagnose.report_markdown import _effect_lines

    common = {"explanation": "x.", "delta_bic": 40.0, "heldout_gain": 0.1,
              "rmse_after": 1.0, "spectral_error_after": 0.1}
    smear = {"name": "motion_smear", "params": {"length_px": 3.0}, **common,
             "test": {"transfer_named": "off_nadir_anisotropy", "naming_dchi2": [150.2, 120.7],
                      "min_dchi2": 25.0},
             "indistinguishable_from": ["off_nadir_anisotropy", "atmospheric_blur"]}
    text = "\n".join(_effect_lines(smear))
    assert "Evidence: ΔBIC = 40" in text and "quantisation lattice" not in text
    assert "the transfer named off_nadir_anisotropy" in text and "150 and 121" in text
    # the member the pixels told apart is no caution; another alternative still is
    assert "cannot be told apart from atmospheric_blur." in text
    caution = "\n".join(_effect_lines({**smear, "test": None}))
    assert "cannot be told apart from off_nadir_anisotropy, atmospheric_blur." in caution
    jpeg = {"name": "compression", "params": {"quality": 80}, **common,
            "test": {"lattice_log_lik_gain": 20.0}}
    text = "\n".join(_effect_lines(jpeg))
    assert "quantisation lattice" in text and "Named in the pixels" not in text
    assert "Named in the pixels" not in caution
