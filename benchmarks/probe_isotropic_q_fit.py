"""Probe (round 47): the lone isotropic pixel scan with Q fitted continuously in the pixels.

At the first pass's call of ``engine.pixel_isotropic``, where the model holds no blur and
no JPEG, it records the stage's own scan (``isotropic_scan``: Q at the transfer-refitted
value × 0.9–1.1, the base at the model's Q × 0.85–1.1) and the same held-out test with Q
fitted instead on each half (bounded on ln Q, × 0.85–1.15 of the starting value, for the
base and for every scanned member value), each fit scored on both halves: the held-out
drops over every member and per member, the best member, value and Q. Nothing the diagnosis
decides is changed. Round 47's numbers: ``docs/diagnosis.md``, round 47.

Run: python benchmarks/probe_isotropic_q_fit.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import stage_isotropic_pixels as iso  # noqa: E402
from geosim.diagnose.fit import fit_transfer  # noqa: E402
from geosim.diagnose.stage_resampling_coherent import heldout_drop, rss_on_halves  # noqa: E402

#: the span of Q fitted (factors on the starting Q)
Q_SPAN = (0.85, 1.15)


def _q_fitted(inp: Any, halves: list[np.ndarray], model: Any, q0: float, k: int
              ) -> tuple[Any, list[float]]:
    """``model`` with Q fitted on half ``k`` and its [RSS on each half, DN²]."""
    def rss_k(log_q: float) -> float:
        return rss_on_halves(inp, [halves[k]], model.without(q=float(np.exp(log_q))))[0]

    r = minimize_scalar(rss_k, bounds=(np.log(q0 * Q_SPAN[0]), np.log(q0 * Q_SPAN[1])),
                        method="bounded", options={"xatol": 2e-3})
    fitted = model.without(q=float(np.exp(r.x)))
    return fitted, rss_on_halves(inp, halves, fitted)


def measure(inp: Any, model: Any, sel: Any, setup: Any, ev: Any, cands: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"q": model.q, "blur": sorted(model.blur)}
    if model.blur or model.compression is not None:
        return out
    t0 = time.time()
    scan = iso.isotropic_scan(inp, model, setup, ev, list(iso.MEMBER_SCAN))
    if scan is None:
        return out
    out["old_lr"] = scan.heldout_dchi2()
    out["old_best"] = list(scan.best()[:2])
    halves = scan.halves
    base = [_q_fitted(inp, halves, model, model.q, k) for k in (0, 1)]
    out["base_q"] = [b[0].q for b in base]
    cand: dict[str, list[tuple[float, float, list[float]]]] = {}
    for name, (key, grid) in iso.MEMBER_SCAN.items():
        for v in grid:
            held = {name: {key: float(v)}}
            fit = fit_transfer(setup.full, [], q_starts=(model.q,), fixed=held)
            start = model.without(q=fit.q, blur=dict(fit.effects))
            for k in (0, 1):
                m, rss = _q_fitted(inp, halves, start, fit.q, k)
                cand.setdefault(name, []).append((float(v), m.q, rss))
    base_rss = [b[1] for b in base]
    out["new_lr"] = heldout_drop(halves, base_rss, [c[2] for cs in cand.values() for c in cs])
    out["new_member"] = {n: heldout_drop(halves, base_rss, [c[2] for c in cs])
                         for n, cs in cand.items()}
    name, best = min(((n, c) for n, cs in cand.items() for c in cs), key=lambda x: sum(x[1][2]))
    out["new_best"] = [name, best[0], best[1]]
    out["new_best_member"] = {n: list(min(cs, key=lambda c: sum(c[2]))[:2])
                              for n, cs in cand.items()}
    out["sec"] = time.time() - t0
    return out


if __name__ == "__main__":
    probe_main(__doc__.splitlines()[0], measure)
