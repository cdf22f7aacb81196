"""The withdrawal of a refitted Q that is not significantly different from the LV Q."""

from types import SimpleNamespace

import pytest

from geosim.diagnose.model import ForwardModel, Registration
from geosim.diagnose.stage_withdraw import q_refit_insignificant


def _reg() -> Registration:
    return Registration(estimate=None, affine=None, applied=False,  # type: ignore[arg-type]
                        shift_px=(0.0, 0.0), whole_px=(0.0, 0.0))


def _run(q_refit: float, q_sigma: float, blur: dict | None = None, q_base: float = 3.0):
    inp = SimpleNamespace(q_base=q_base)
    sel = SimpleNamespace(final=SimpleNamespace(sigmas={"q": q_sigma}))
    model = ForwardModel(q=q_refit, blur=blur or {}, registration=_reg())
    return q_refit_insignificant(inp, model, sel)  # type: ignore[arg-type]


@pytest.mark.parametrize("n_sigma", [0.0, 0.5, 1.2, 1.99])
def test_a_q_within_its_uncertainty_gives_way_to_the_lv_q(n_sigma):
    model, withdrawn = _run(3.0 + n_sigma * 0.025, 0.025)
    assert model.q == 3.0
    assert [w["name"] for w in withdrawn] == ["refitted_q"]
    assert "within 2 σ" in withdrawn[0]["reason"]


@pytest.mark.parametrize("n_sigma", [2.01, 5.0, -3.0])
def test_a_significant_q_change_is_kept(n_sigma):
    q = 3.0 + n_sigma * 0.025
    model, withdrawn = _run(q, 0.025)
    assert model.q == q and withdrawn == []


def test_q_refitted_with_a_blur_is_never_touched():
    # a blur claimed moves Q with it: Q alone is not what was refitted
    blur = {"motion_smear": {"length_px": 2.0, "direction_deg": 30.0}}
    model, withdrawn = _run(3.01, 0.025, blur=blur)
    assert model.q == 3.01 and model.blur == blur and withdrawn == []


@pytest.mark.parametrize("q_sigma", [0.0, float("nan")])
def test_no_usable_uncertainty_keeps_the_refit(q_sigma):
    model, withdrawn = _run(3.01, q_sigma)
    assert model.q == 3.01 and withdrawn == []

