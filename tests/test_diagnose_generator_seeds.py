"""The independent benchmark's seeds → cases mapping does not move: cases drawn now
equal the stored development rows of benchmarks/results/diagnose_independent.json."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402


@pytest.mark.parametrize("index", [2, 16, 24, 54])
def test_development_cases_are_the_stored_ones(realdata, samples_dir, index):
    stored = json.loads((ROOT / "benchmarks" / "results" / "diagnose_independent.json")
                        .read_text())
    row = next(r for r in stored["cases"]
               if r["split"] == "development" and r["case"] == f"c{index:02d}")
    case = gen.make_case(index, gen.pick_sources(gen.list_sources(realdata, samples_dir)))
    assert case.q == pytest.approx(row["q_true"], rel=1e-12)
    assert case.source == row["source"]
    assert set(case.truth) == set(row["truth"])
    for name, params in row["truth"].items():
        for k, v in params.items():
            assert case.truth[name][k] == pytest.approx(v, rel=1e-9), (name, k)


def test_forced_effects_draw_the_named_effects_only(realdata, samples_dir):
    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(3, sources, base_seed=6000, force=("motion_smear",))
    assert set(case.truth) == {"motion_smear"}
    lo, hi = gen.RANGES["motion_smear"]["length_px"]
    assert lo <= case.truth["motion_smear"]["length_px"] <= hi
