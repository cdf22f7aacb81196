"""Probe (round 41, not part of the diagnosis): held-out pixel evidence for a lone
anisotropic blur where the first pass's model holds no blur and no JPEG.

For each development case it runs the benchmark's diagnosis (``diagnose_independent.
diagnose_case``) with the first call of ``engine.pixel_isotropic`` wrapped: there, on the
evaluation pixels' checkerboard halves (``stage_resampling_coherent.checker_halves``), Q
alone (bounded search, ±20 %) is compared with Q + an off-nadir blur or a motion smear
(Nelder–Mead on ln Q, width and direction, 4 directions × 2 widths as starts, 40
evaluations each) fitted on one half and scored on the other: the held-out Δχ² is the
drop of the other half's residual sum of squares over its residual variance per pixel.
Nothing the diagnosis decides is changed. Round 41's numbers (weaker half): 24
development controls at Q 2.5–4.5 at most 6.1; six noise-free lone blurs the tool missed
567–1271; with sensor noise −6.4 to 34.6 (docs/diagnosis.md, round 41, Next).

Run: python benchmarks/probe_lone_anisotropic.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize, minimize_scalar

sys.path.insert(0, str(Path(__file__).resolve().parent))

import diagnose_generator as gen  # noqa: E402
import diagnose_independent as bench  # noqa: E402

from geosim.diagnose import engine  # noqa: E402
from geosim.diagnose import stage_resampling_coherent as coherent  # noqa: E402

#: (effect, width parameter, direction parameter, width bounds px, width starts px)
SHAPES = (("off_nadir_anisotropy", "sigma_px", "azimuth_deg", (0.05, 1.5), (0.4, 0.8)),
          ("motion_smear", "length_px", "direction_deg", (0.2, 4.0), (1.0, 2.2)))
DIRECTION_STARTS_DEG = (0.0, 45.0, 90.0, 135.0)


def heldout(inp: Any, model: Any, ev: Any) -> dict[str, Any]:
    """Per shape, per half (fitted on the other): held-out Δχ², width, direction, Q."""
    if model.blur or model.compression is not None:
        return {"skipped": "a blur or JPEG in the model"}
    halves = coherent.checker_halves(ev)
    if halves is None:
        return {"skipped": "no checkerboard halves"}

    def rss(m: Any, h: np.ndarray) -> float:
        return coherent.rss_on_halves(inp, [h], m)[0]

    out: dict[str, Any] = {"q_model": model.q}
    for name, width, direction, (lo, hi), starts in SHAPES:
        def build(x: np.ndarray, name=name, width=width, direction=direction, lo=lo, hi=hi):
            return model.without(q=float(np.exp(x[0])), blur={name: {
                width: float(np.clip(x[1], lo, hi)), direction: float(x[2]) % 180.0}})

        per_half = []
        for k in (0, 1):
            fit, test = halves[k], halves[1 - k]
            r = minimize_scalar(lambda lq, f=fit: rss(model.without(q=float(np.exp(lq))), f),
                                bounds=(np.log(model.q * 0.8), np.log(model.q * 1.2)),
                                method="bounded", options={"xatol": 2e-3})
            lq = float(r.x)
            base_test = rss(model.without(q=float(np.exp(lq))), test)
            best = None
            for az in DIRECTION_STARTS_DEG:
                for w0 in starts:
                    x0 = np.array([lq, w0, az])
                    simplex = np.vstack([x0, x0 + np.diag([0.05, 0.2, 20.0])])
                    res = minimize(lambda x, f=fit: rss(build(x), f), x0, method="Nelder-Mead",
                                   options={"maxfev": 40, "initial_simplex": simplex})
                    if best is None or res.fun < best.fun:
                        best = res
            alt_test = rss(build(best.x), test)
            n = int(test.sum())
            per_half.append({"dchi2": (base_test - alt_test) / max(base_test / n, 1e-12),
                             "width_px": float(np.clip(best.x[1], lo, hi)),
                             "direction_deg": float(best.x[2]) % 180.0,
                             "q": float(np.exp(best.x[0])), "q_alone": float(np.exp(lq))})
        out[name] = per_half
    return out


def main() -> None:
    indices = [int(v) for v in sys.argv[1].split(",")]
    captured: dict[str, Any] = {}
    original = engine.pixel_isotropic

    def hook(inp, model, sel, setup, ev, candidates):
        if "result" not in captured:          # the first pass only
            captured["result"] = heldout(inp, model, ev)
        return original(inp, model, sel, setup, ev, candidates)

    engine.pixel_isotropic = hook
    sources = gen.default_sources()
    with open(sys.argv[2], "w") as f:
        for i in indices:
            captured.clear()
            t0 = time.time()
            row = bench.diagnose_case(gen.make_case(i, sources))
            probe = captured.get("result") or {}
            f.write(json.dumps({"case": row["case"], "q_true": row["q_true"],
                                "truth": row["truth"], "claimed": sorted(row["claimed"]),
                                "probe": probe, "seconds": time.time() - t0}) + "\n")
            f.flush()
            weaker = {n: round(min(h["dchi2"] for h in probe[n]), 1)
                      for n, *_ in SHAPES if n in probe}
            print(row["case"], f"Q {row['q_true']:.2f}", sorted(row["truth"]), "->",
                  sorted(row["claimed"]), weaker or probe.get("skipped"), flush=True)


if __name__ == "__main__":
    main()
