"""Probe (round 44): the anisotropic member the transfer named, checked in the pixels.

For each case it runs the benchmark's diagnosis (``diagnose_independent.diagnose_case``) up
to the first pass's ``engine.pixel_isotropic`` call and stops there. Where the model holds
one anisotropic member (``motion_smear`` or ``off_nadir_anisotropy``) and no JPEG, it fits
that member and the other one in the pixels (ln Q, width, direction by Nelder–Mead, the
model's other blurs held, started from the claimed blur's second moment and direction) on
each checkerboard half and scores each fit on the other half. ``naming_dchi2`` is, per
half fitted on, the other half's drop of the residual sum of squares when the other member
replaces the claimed one, in units of that half's residual variance per pixel (positive:
the other member predicts better). Nothing the diagnosis decides is changed. Round 44's
numbers: ``docs/diagnosis.md``, round 44.

Run: python benchmarks/probe_anisotropic_naming.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import stage_anisotropic_pixels as an  # noqa: E402
from geosim.diagnose.model import ForwardModel  # noqa: E402
from geosim.diagnose.stage_resampling_coherent import (  # noqa: E402
    checker_halves,
    rss_on_halves,
)

MEMBERS = ("motion_smear", "off_nadir_anisotropy")


def fit_member(inp: Any, model: ForwardModel, halves: list[np.ndarray], claimed: str,
               name: str, k: int) -> ForwardModel:
    """``name`` in place of ``claimed`` (the model's other blurs held), fitted on half
    ``k`` from the claimed blur's second moment and direction and the model's Q."""
    shape, was = an.SHAPES[name], an.SHAPES[claimed]
    lo, hi = shape.bounds_px
    rest = {n: p for n, p in model.blur.items() if n != claimed}
    params = model.blur[claimed]
    variance = float(params[was.width_key]) ** 2 * was.variance_per_width2

    def build(x: np.ndarray) -> ForwardModel:
        return model.without(q=float(np.exp(x[0])), blur={**rest, name: {
            shape.width_key: float(np.clip(x[1], lo, hi)),
            shape.direction_key: float(x[2]) % 180.0}})

    width0 = float(np.clip(np.sqrt(variance / shape.variance_per_width2), lo, hi))
    x0 = np.array([np.log(model.q), width0, float(params[was.direction_key])])
    simplex = np.vstack([x0, x0 + np.diag([0.05, 0.25 * width0 + 0.1, 20.0])])
    res = minimize(lambda x: rss_on_halves(inp, [halves[k]], build(x))[0], x0,
                   method="Nelder-Mead",
                   options={"maxfev": an.MAX_EVALUATIONS, "initial_simplex": simplex})
    return build(res.x)


def measure(inp: Any, model: ForwardModel, ev: Any) -> dict[str, Any]:
    """Both members fitted on each checkerboard half, scored on the other."""
    out: dict[str, Any] = {"q_model": model.q, "blur": model.blur,
                           "jpeg": model.compression is not None}
    claimed = [n for n in MEMBERS if n in model.blur]
    halves = checker_halves(ev)
    if len(claimed) != 1 or model.compression is not None or halves is None:
        return out
    t0 = time.time()
    x = claimed[0]
    y = next(n for n in MEMBERS if n != x)
    fits: dict[str, list[dict[str, Any]]] = {}
    for name in (x, y):
        fits[name] = []
        for k in (0, 1):
            m = fit_member(inp, model, halves, x, name, k)
            fits[name].append({"q": m.q, "p": m.blur[name],
                               "rss": rss_on_halves(inp, halves, m)})
    naming = []
    for k in (0, 1):
        o = 1 - k
        rss_x, rss_y = fits[x][k]["rss"][o], fits[y][k]["rss"][o]
        naming.append((rss_x - rss_y) / max(rss_x / int(halves[o].sum()), 1e-12))
    out.update(x=x, rss_model=rss_on_halves(inp, halves, model), fits=fits,
               naming_dchi2=naming, seconds_probe=time.time() - t0)
    return out


def main() -> None:
    probe_main(__doc__.splitlines()[0],
               lambda inp, model, sel, setup, ev, candidates: measure(inp, model, ev))


if __name__ == "__main__":
    main()
