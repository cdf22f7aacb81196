"""How low can the refined spectral error go? An oracle for the halving target.

For development cases of ``benchmarks/diagnose_independent.py`` this renders the best
refined simulation the diagnosis could deliver if it knew the truth: geosim's paper
model at the **true** Q, moved by the true shift before sampling, with the true blurs
(shift-invariant ones on the fine grid before sampling, as the diagnosis renders them;
resampling with geosim's model), the true haze / colour, the true noise parameters (a
fresh realisation: the scene's own noise cannot be known) and the true JPEG quality,
applied last — and scores it with the benchmark's own spectral error. Moved objects
(scene change) are not moved: their new places are not in the UAV image.

Where the oracle's spectral error is above half the baseline's, the halving target cannot
be met by any diagnosis on that case: what is left is the spectral scatter of a noise or
quantisation realisation (two independent realisations of the same power differ bin by
bin) or the moved objects themselves.

Run (development cases only): python benchmarks/diagnose_oracle.py --indices 8,13,22
[--baseline benchmarks/results/diagnose_independent.json] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402
import diagnose_independent as di  # noqa: E402

LSI = ("motion_smear", "off_nadir_anisotropy", "atmospheric_blur", "detector_integration")


def oracle(case: gen.Case, seeds: tuple[int, ...] = (7, 8, 9)) -> list[float]:
    """Spectral errors of the oracle refined simulation, one per noise seed."""
    from geosim.diagnose.effects import get_effect
    from geosim.diagnose.simulate import QSimulator

    t = case.truth
    sim = QSimulator(case.uav, phi=gen.PHI, q_min=0.6)
    shift = tuple(t["misregistration"]["shift_px"]) if "misregistration" in t else (0.0, 0.0)
    lsi = {n: p for n, p in t.items() if n in LSI}

    def transfer(fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        h = np.ones(np.broadcast_shapes(fy.shape, fx.shape))
        for n, p in lsi.items():
            h = h * get_effect(n).transfer(fy, fx, **p)
        return h

    v = sim.variant(shift_px=shift, transfer=transfer if lsi else None, key="truth")
    s = np.asarray(v(case.q), float)
    if "resampling" in t:
        s = get_effect("resampling").apply(s, **t["resampling"])
    if "haze" in t:
        s = (np.asarray(t["haze"]["transmission"])[:, None, None] * s
             + np.asarray(t["haze"]["path_radiance_dn"])[:, None, None])
    if "colour_response" in t:
        s = np.asarray(t["colour_response"]["gain"])[:, None, None] * s
    out = []
    for seed in seeds:
        x = s
        if "sensor_noise" in t:
            p = t["sensor_noise"]
            x = gen.poisson_gaussian(x, p["gain_dn"], p["read_var_dn2"],
                                     np.random.default_rng(seed))
        x = np.clip(np.rint(x), 0, 255)
        if "compression" in t:
            x = gen.jpeg_pillow(x, t["compression"]["quality"])
        out.append(gen.spectral_error(x, case.real))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--indices", required=True,
                    type=lambda s: [int(v) for v in s.split(",")],
                    help="development case indices (`diagnose_independent.DEVELOPMENT`)")
    ap.add_argument("--baseline", default=str(di.HALVES_FILE),
                    help="a diagnose_independent result with se_base / se_refined per case")
    ap.add_argument("--out", default=None, help="JSON output (default: print only)")
    args = ap.parse_args()
    if set(args.indices) - set(di.DEVELOPMENT):
        sys.exit(f"--indices: development cases only (0-{max(di.DEVELOPMENT)}; not the "
                 "validation half)")
    sources = gen.default_sources()
    prev: dict[str, Any] = {}
    if Path(args.baseline).is_file():
        prev = {r["case"]: r for r in json.loads(Path(args.baseline).read_text())["cases"]}
    rows = []
    print("| case | truth | baseline | ½ baseline | oracle (3 noise seeds) | diagnosis |")
    print("|---|---|---|---|---|---|")
    for i in args.indices:
        case = gen.make_case(i, sources)
        se = oracle(case)
        p = prev.get(case.name, {})
        rows.append({"case": case.name, "truth": sorted(case.truth), "oracle_se": se,
                     "se_base": p.get("se_base"), "se_refined": p.get("se_refined")})
        base = p.get("se_base", float("nan"))
        print(f"| {case.name} | {', '.join(sorted(case.truth))} | {base:.3f} | "
              f"{base / 2:.3f} | {', '.join(f'{v:.3f}' for v in se)} | "
              f"{p.get('se_refined', float('nan')):.3f} |", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
