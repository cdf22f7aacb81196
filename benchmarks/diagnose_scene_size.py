"""Pair the diagnosis on larger scenes with the same development cases at the halves' size.

Run the cases first (the development indices whose source holds a 384 px scene)::

    python benchmarks/diagnose_independent.py --large-sources 384
    python benchmarks/diagnose_independent.py --indices I,J,... --sat-px 384 \\
        --out benchmarks/results/diagnose_scene_size_384.json
    python benchmarks/diagnose_scene_size.py benchmarks/results/diagnose_scene_size_384.json

A case is paired only when both sizes drew the same Q and effects (the window is drawn
first and a larger window can need another draw, which moves every draw after it). Prints
the benchmark's scores of the pairs at both sizes and every pair whose claims differ.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402
from diagnose_independent import HALVES_FILE  # noqa: E402


def same_draw(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Both rows drew the same Q and effects (parameters included)."""
    return a["q_true"] == b["q_true"] and json.dumps(a["truth"], sort_keys=True) \
        == json.dumps(b["truth"], sort_keys=True)


def fmt(s: dict[str, Any]) -> str:
    return (f"precision {s['precision']:.2f} ({s['tp']}/{s['tp'] + s['fp']}), recall "
            f"{s['recall']:.2f} ({s['tp']}/{s['tp'] + s['fn']}), controls "
            f"{s['controls_clean']}/{s['n_controls']}, refined ≤ ½ baseline "
            f"{s['refined_le_half_baseline']}/{s['effect_cases']}, above baseline "
            f"{s['refined_above_baseline']}/{s['n_cases']}")


def main() -> None:
    big_doc = json.loads(Path(sys.argv[1]).read_text())
    halves = json.loads(HALVES_FILE.read_text())
    small = {r["case"]: r for r in halves["cases"]}
    px0 = halves["setup"]["sat_px"]
    pairs = [(small[r["case"]], r) for r in big_doc["cases"] if r["case"] in small]
    same = [(a, b) for a, b in pairs if same_draw(a, b)]
    px = big_doc["setup"]["sat_px"]
    print(f"{len(pairs)} cases, {len(same)} paired (same Q and effects)")
    print(f"  {px0} px: {fmt(gen.score([a for a, _ in same]))}")
    print(f"  {px} px: {fmt(gen.score([b for _, b in same]))}")
    for a, b in same:
        if set(a["claimed"]) != set(b["claimed"]) or set(b["claimed"]) != set(b["truth"]):
            print(f"  {a['case']} {a['source']} Q {a['q_true']:.2f} truth {sorted(a['truth'])}"
                  f" | {px0}: {sorted(a['claimed'])} {a['se_base']:.3f}->{a['se_refined']:.3f}"
                  f" | {px}: {sorted(b['claimed'])} {b['se_base']:.3f}->{b['se_refined']:.3f}")


if __name__ == "__main__":
    main()
