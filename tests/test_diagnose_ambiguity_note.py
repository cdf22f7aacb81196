"""The ambiguity note says on what evidence two names tie: held-out blocks for blurs,
BIC for radiometric names (whose alternatives carry ``delta_bic``, no ``heldout_gain``)."""
from geosim.diagnose.model import Claim
from geosim.diagnose.stage_summary import _ambiguity_note


def test_radiometric_tie_is_described_by_bic() -> None:
    haze = Claim("haze", {"transmission": [0.9] * 3, "path_radiance_dn": [5.0] * 3}, {}, 40.0,
                 alternatives=[{"name": "colour_response", "params": {"gain": [0.95] * 3},
                                "delta_bic": 38.8}])
    note = _ambiguity_note(haze)
    assert "colour_response" in note and "BIC" in note and "held-out" not in note


def test_blur_tie_is_described_by_held_out_blocks() -> None:
    smear = Claim("motion_smear", {"length_px": 2.0, "direction_deg": 30.0}, {}, 25.0, 0.2,
                  alternatives=[{"name": "off_nadir_anisotropy", "heldout_gain": 0.19,
                                 "params": {"sigma_px": 0.8, "azimuth_deg": 30.0}}])
    note = _ambiguity_note(smear)
    assert "off_nadir_anisotropy" in note and "held-out blocks" in note and "BIC" not in note


def test_blur_tie_named_by_the_exact_fit_states_its_evidence() -> None:
    """Where the exact duel named the claim, the note gives the ΔBIC on all blocks and its
    evidence on Kass & Raftery's scale (< 2: not worth more than a bare mention)."""
    alt = {"name": "off_nadir_anisotropy", "heldout_gain": 0.21,
           "params": {"sigma_px": 0.8, "azimuth_deg": 30.0}, "delta_bic": 0.4}
    smear = Claim("motion_smear", {"length_px": 2.0, "direction_deg": 30.0}, {}, 25.0, 0.2,
                  alternatives=[alt])
    note = _ambiguity_note(smear)
    assert "held-out blocks" in note and "better by ΔBIC 0.4" in note
    assert "not worth more than a bare mention" in note
    strong = Claim("motion_smear", {}, {}, 25.0, 0.2,
                   alternatives=[{**alt, "delta_bic": 12.0}])
    assert "evidence very strong" in _ambiguity_note(strong)


def test_bic_evidence_scale() -> None:
    from geosim.diagnose.select import bic_evidence

    assert [bic_evidence(d) for d in (0.0, 1.99, 2.0, 5.9, 6.0, 9.9, 10.0, 50.0)] == [
        "not worth more than a bare mention", "not worth more than a bare mention",
        "positive", "positive", "strong", "strong", "very strong", "very strong"]
