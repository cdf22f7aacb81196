"""An isotropic blur beside a resampling, found by its trace in the pixels.

The scenes come from the independent generator (``benchmarks/diagnose_generator.py``: a
detector box on the 0.05 m grid, the native grid rendered there and area-averaged, OpenCV's
bicubic back onto the product grid), run blind through the whole diagnosis; the held-out
measure and the naming are checked on hand-made residual sums.
"""

from __future__ import annotations

import numpy as np
import pytest

import geosim.diagnose.stage_isotropic_pixels as iso
from geosim.diagnose.stage_isotropic_pixels import IsotropicScan
from tests.generator_cases import diagnose_scene as _run

RESAMPLED_DETECTOR = {"resampling": {"native_pitch_px": 1.5},
                      "detector_integration": {"pitch_px": 1.5}}


def _halves() -> list[np.ndarray]:
    left = np.zeros((2, 4), bool)
    left[:, :2] = True
    return [left, ~left]   # 4 pixels each


def test_heldout_dchi2_per_member_and_naming_by_both_halves():
    base = [("b1", [40.0, 80.0]), ("b2", [36.0, 88.0])]
    scanned = [("detector_integration", 1.2, "d12", [30.0, 60.0]),
               ("detector_integration", 1.4, "d14", [20.0, 76.0]),
               ("atmospheric_blur", 0.4, "a04", [34.0, 50.0])]
    scan = IsotropicScan(halves=_halves(), base=base, scanned=scanned)  # type: ignore[arg-type]
    # every member: chosen on the left, base b2 (36) and d14 (20), scored on the right:
    # 88 → 76 in units of 88 / 4; chosen on the right, b1 (80) and a04 (50), on the left
    # 40 → 34 in units of 40 / 4
    assert scan.heldout_dchi2() == pytest.approx([(88 - 76) / 22, (40 - 34) / 10])
    # the detector alone: on the right d12 (60) is chosen, on the left 40 → 30
    assert scan.heldout_dchi2("detector_integration") == pytest.approx(
        [(88 - 76) / 22, (40 - 30) / 10])
    # named by the lowest RSS over both halves: a04 (84) against d12 (90) and d14 (96)
    assert scan.best() == ("atmospheric_blur", 0.4, "a04")
    assert scan.best("detector_integration") == ("detector_integration", 1.2, "d12")


def test_ends_of_the_scan_and_the_effect_size_are_not_claimed():
    pitches = iso.MEMBER_SCAN["detector_integration"][1]
    assert iso._pinned("detector_integration", float(pitches[0]))
    assert iso._pinned("detector_integration", float(pitches[-1]))
    assert not iso._pinned("detector_integration", 1.3)
    assert iso._sized("atmospheric_blur", 0.4) and not iso._sized("atmospheric_blur", 0.7)
    assert iso._sized("detector_integration", 0.6) and not iso._sized("detector_integration",
                                                                       0.4)


def test_detector_beside_a_resampling_found_in_the_pixels():
    claimed, se_base, se_ref, _ = _run(RESAMPLED_DETECTOR, q=1.6, seed=30, sat_px=128)
    assert set(claimed) == {"resampling", "detector_integration"}, list(claimed)
    assert abs(claimed["detector_integration"]["params"]["pitch_px"] - 1.5) <= 0.15
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - 1.5) <= 0.1
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_without_the_pixel_test_that_detector_goes_into_q(monkeypatch):
    """The same scene with the stage switched off: the transfer alone misses the detector
    (so the test above is this stage's)."""
    monkeypatch.setattr(iso, "ISO_PIXEL_MIN_DCHI2", np.inf)
    claimed, _, _, _ = _run(RESAMPLED_DETECTOR, q=1.6, seed=30, sat_px=128)
    assert set(claimed) == {"resampling"}, list(claimed)


def test_resampling_alone_claims_no_isotropic_blur():
    truth = {"resampling": {"native_pitch_px": 1.5}}
    claimed, se_base, se_ref, _ = _run(truth, q=1.6, seed=33, sat_px=128)
    assert set(claimed) == {"resampling"}, list(claimed)
    assert se_ref <= se_base


def test_resampling_refined_on_the_spectrum_with_the_new_blur_held(monkeypatch):
    """After the pixel test adds the detector, the resampling's pitch, Q and phase are
    refined again on the power spectrum with it held: the delivered simulation's spectral
    error (the benchmark's own measure and the tool's) is no larger than without that step,
    and Q stays near the truth (1.6)."""
    out = {}
    for refine in (False, True):
        monkeypatch.setattr(iso, "REFINE_ON_SPECTRUM", refine)
        claimed, _, se_ref, d = _run(RESAMPLED_DETECTOR, q=1.6, seed=30, sat_px=128)
        assert set(claimed) == {"resampling", "detector_integration"}, list(claimed)
        out[refine] = (se_ref, d.summary["refined"]["spectral_error"], d.summary["refined"]["q"])
    assert out[True][0] <= out[False][0] and out[True][1] <= out[False][1], out
    assert abs(out[True][2] - 1.6) <= 0.05, out


def _thousand_pixel_halves() -> tuple[list[np.ndarray], list, list[str]]:
    """Halves of 1000 pixels each, a base of residual variance 1 DN² per pixel on each,
    and both members."""
    left = np.zeros((10, 200), bool)
    left[:, :100] = True
    return ([left, ~left], [("b", [1000.0, 1000.0])],
            ["detector_integration", "atmospheric_blur"])


def test_alternative_members_pass_the_same_held_out_test():
    """The other member is an alternative only where it passes the held-out test on both
    halves; a member with no scanned configuration (every Q below MIN_Q) is skipped, not
    an error (development c196 had raised min() of an empty sequence)."""
    halves, base, members = _thousand_pixel_halves()
    claimed = ("atmospheric_blur", 0.4, "a04", [0.0, 0.0])
    weak = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                         scanned=[("detector_integration", 1.2, "d12", [950.0, 950.0]),
                                  claimed])
    # the detector lowers each held-out half by 50 < ISO_PIXEL_MIN_DCHI2 (100)
    assert iso.member_alternatives(weak, "atmospheric_blur", members) == []
    strong = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                           scanned=[("detector_integration", 1.2, "d12", [800.0, 850.0]),
                                    claimed])
    # chosen on the left, the right drops 150; on the right, the left drops 200
    alts = iso.member_alternatives(strong, "atmospheric_blur", members)
    assert [(a.name, a.params) for a in alts] == [("detector_integration", {"pitch_px": 1.2})]
    assert alts[0].cv_gain == pytest.approx(150 / 1000)
    only_one = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                             scanned=[claimed])
    assert iso.member_alternatives(only_one, "atmospheric_blur", members) == []
    pinned = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                           scanned=[("detector_integration", 2.0, "d20", [800.0, 850.0]),
                                    claimed])
    # passing, but at the end of its scan: not an alternative
    assert iso.member_alternatives(pinned, "atmospheric_blur", members) == []


LONE_DETECTOR = {"detector_integration": {"pitch_px": 1.4}}


@pytest.mark.slow
def test_lone_detector_at_high_q_found_in_the_pixels():
    """No resampling, no noise, Q 3.5: a 1.4 px detector box (the generator's, on the
    0.05 m grid) is found and named, its pitch near the truth, and the refined simulation
    more than halves the baseline's spectral error (the generator's own measure)."""
    claimed, se_base, se_ref, _ = _run(LONE_DETECTOR, q=3.5, seed=43, sat_px=128)
    assert set(claimed) == {"detector_integration"}, list(claimed)
    assert abs(claimed["detector_integration"]["params"]["pitch_px"] - 1.4) <= 0.3
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


@pytest.mark.slow
def test_without_the_pixel_test_the_lone_detector_goes_into_q(monkeypatch):
    """The same scene with the stage switched off: the transfer alone claims nothing (so
    the test above is this stage's)."""
    monkeypatch.setattr(iso, "ISO_PIXEL_MIN_DCHI2", np.inf)
    claimed, _, _, _ = _run(LONE_DETECTOR, q=3.5, seed=43, sat_px=128)
    assert not claimed, list(claimed)


@pytest.mark.parametrize("truth, lone", [
    (LONE_DETECTOR, True),
    ({"off_nadir_anisotropy": {"sigma_px": 0.6, "azimuth_deg": 40.0}}, False),
    ({"motion_smear": {"length_px": 2.0, "direction_deg": 110.0}}, False)])
def test_lone_test_defers_to_an_anisotropic_trace(truth, lone):
    """Against the paper's model at the true Q (no blur), the residual of a lone detector
    opens the lone isotropic test; the generator's off-nadir elongation and motion smear
    leave an anisotropic trace, and the test is left to the anisotropic stage."""
    from geosim.diagnose.context import EvalContext
    from geosim.diagnose.model import ForwardModel
    from tests.generator_cases import no_registration, scene_inputs

    inp, real = scene_inputs(truth, q=3.5, seed=43, sat_px=96)
    model = ForwardModel(q=3.5, blur={}, registration=no_registration())
    ev = EvalContext(mask=np.ones(real.shape[-2:], bool), origins=[], block_px=32,
                     real_grey=inp.grey, noise_seed=0)
    assert iso._lone_domain(inp, model, ev) is lone
    assert not iso._lone_domain(inp, model.without(blur=truth), ev)   # a blur held: no


def test_lone_test_left_out_where_the_engine_says_so(monkeypatch):
    """``lone=False`` (a first pass that located moved objects, whose second pass on the
    painted ground tests it): the lone detector's scan is not run; with ``lone=True`` it is."""
    from geosim.diagnose.context import EvalContext
    from geosim.diagnose.model import ForwardModel
    from tests.generator_cases import no_registration, scene_inputs

    inp, real = scene_inputs(LONE_DETECTOR, q=3.5, seed=43, sat_px=96)
    model = ForwardModel(q=3.5, blur={}, registration=no_registration())
    ev = EvalContext(mask=np.ones(real.shape[-2:], bool), origins=[], block_px=32,
                     real_grey=inp.grey, noise_seed=0)
    scanned = []
    monkeypatch.setattr(iso, "isotropic_scan", lambda *a: scanned.append(a) and None)
    members = ("detector_integration", "atmospheric_blur")
    args = (inp, model, None, None, ev, members)
    assert iso.pixel_isotropic(*args, lone=False) is model and not scanned
    assert iso.pixel_isotropic(*args, lone=True) is model and len(scanned) == 1


def test_the_other_member_claimed_where_the_best_sits_at_an_end_of_its_scan():
    """A value at an end of its scan stands in for a shape beyond it: the other member is
    claimed where it passes the held-out test on its own, is inside its scan and fits no
    worse (development c33: an atmosphere whose best detector sat at 2.0 px)."""
    halves, base, _ = _thousand_pixel_halves()
    pinned = ("detector_integration", 2.0, "d20", [700.0, 700.0])
    scan = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                         scanned=[pinned, ("atmospheric_blur", 0.4, "a04", [750.0, 760.0])])
    name, value, model, dchi2 = iso.first_claimable(scan, lambda m: True)
    assert (name, value, model) == ("atmospheric_blur", 0.4, "a04")
    assert dchi2 == pytest.approx([240.0, 250.0])     # its own held-out drops
    # the other member weaker than the threshold on one half: nothing claimed
    weak = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                         scanned=[pinned, ("atmospheric_blur", 0.4, "a04", [950.0, 760.0])])
    assert iso.first_claimable(weak, lambda m: True) is None
    # an interior best fitting worse than the baseline gives way to the other member
    inner = IsotropicScan(halves=halves, base=base,  # type: ignore[arg-type]
                          scanned=[("detector_integration", 1.3, "d13", [700.0, 700.0]),
                                   ("atmospheric_blur", 0.4, "a04", [750.0, 760.0])])
    assert iso.first_claimable(inner, lambda m: m != "d13")[2] == "a04"
    assert iso.first_claimable(inner, lambda m: True)[2] == "d13"
