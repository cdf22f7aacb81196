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


def _results(path: Path, rows: list[dict], sat_px: int = 128) -> Path:
    path.write_text(json.dumps({"cases": rows, "setup": {"sat_px": sat_px}}))
    return path


def _row(case: str, seed: int, **kw) -> dict:
    return {"case": case, "seed": seed, "split": "validation", "source": "s", "q_true": 2.0,
            "q_base": 2.0, "q_refined": 3.0, "truth": {}, "claimed": {},
            "se_base": 0.1, "se_refined": 0.05, "seconds_total": 1.5, **kw}


def test_merge_takes_rows_by_case_recomputes_splits_and_states_limits(tmp_path):
    """``diagnose_independent.py --merge``: later files win; each row's split comes from
    its seed (a past validation half joins development); rows without the diagnosis's
    detection limits get the ones it states at their delivered Q; a file of other-sized
    scenes is refused and nothing is written."""
    import diagnose_independent as bench

    from geosim.diagnose.detection_limits import detection_limits_json

    lim = {"detector_integration": {"param": "pitch_px", "limit": 9.0,
                                    "absorbed_side": "below", "q": 3.0}}
    a = _results(tmp_path / "a.json", [_row("c00", 1000), _row("c300", 1300)])
    b = _results(tmp_path / "b.json", [_row("c00", 1000, claimed={"haze": {}},
                                            detection_limits=lim)])
    out = tmp_path / "merged.json"
    bench.merge([a, b], str(out))
    doc = json.loads(out.read_text())
    rows = {r["case"]: r for r in doc["cases"]}
    assert [r["case"] for r in doc["cases"]] == ["c00", "c300"]
    assert rows["c00"]["claimed"] == {"haze": {}} and rows["c00"]["detection_limits"] == lim
    assert rows["c00"]["split"] == "development" and rows["c300"]["split"] == "validation"
    assert rows["c300"]["detection_limits"] == detection_limits_json(3.0)
    assert rows["c300"]["detection_limits_restated"] is True
    assert doc["halves"]["development"]["n_cases"] == 1
    assert doc["seconds_total"] == pytest.approx(3.0, abs=0.5)
    big = _results(tmp_path / "big.json", [_row("c01", 1001)], sat_px=384)
    with pytest.raises(SystemExit, match="384 px"):
        bench.merge([a, big], str(tmp_path / "refused.json"))
    assert not (tmp_path / "refused.json").exists()


def test_stated_untestable_reads_the_rows_limits():
    lim = {"detector_integration": {"param": "pitch_px", "limit": 1.5, "absorbed_side": "below"},
           "atmospheric_blur": {"param": "f0_cyc_per_px", "limit": None,
                                "absorbed_side": "above"}}
    row = {"truth": {"detector_integration": {"pitch_px": 1.2}}, "claimed": {},
           "detection_limits": lim, "se_base": 0.1, "se_refined": 0.05}
    assert gen.stated_untestable(row) == {"detector_integration"}
    row["truth"]["detector_integration"]["pitch_px"] = 1.6
    assert gen.stated_untestable(row) == set()
    row["truth"]["atmospheric_blur"] = {"f0_cyc_per_px": 0.3}   # limit None: never testable
    assert gen.stated_untestable(row) == {"atmospheric_blur"}
    s = gen.score([row])
    assert (s["recall_testable"], s["stated_untestable"], s["rows_with_limits"]) == (0.0, 1, 1)
    assert s["recall"] == 0.0 and s["stated_untestable_found"] == 0
    row["claimed"] = {"atmospheric_blur": {}}   # claimed: the report states no limit for it
    assert gen.stated_untestable(row) == set()
