"""The alias-cell transfer model (benchmarks/diagnose_alias_cells.py, a prototype not yet
in the diagnosis) sees a detector box that acts before sampling at low Q, where the
product-grid model cannot, and equals it where nothing aliases."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_alias_cells as alias  # noqa: E402


def test_a_low_q_box_is_recovered_by_the_alias_cell_model_only():
    # synthetic ground (no sources): the generator's own pasture texture
    r = alias.run_case(3, 0.9, "detector_integration", 1.4, [])
    a, o = r["alias_cells"], r["product_grid"]
    assert r["gain_alias_cells"] > 5 * max(r["gain_product_grid"], 5.0)
    assert a["q"] == pytest.approx(0.9, rel=0.05)
    assert a["param"] == pytest.approx(1.4, rel=0.08)
    # the product-grid model of the box is further from the data than the box is from Q
    assert a["chi2"] < 0.5 * o["chi2"]


def test_the_models_agree_where_nothing_aliases():
    r = alias.run_case(3, 2.3, "detector_integration", 1.4, [])
    assert r["gain_alias_cells"] == pytest.approx(r["gain_product_grid"], rel=0.01)
    assert r["alias_cells"]["q"] == pytest.approx(r["product_grid"]["q"], rel=0.01)
