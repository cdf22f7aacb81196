"""Probe (round 46, for round 47): the anisotropic pixel fits beside the model's other blurs
with those blurs refitted instead of held at the transfer's values.

At the call of ``engine.pixel_anisotropic`` (first pass), where the model holds other blurs
(no anisotropic member, no JPEG) and the screen passes on all six splits, it fits on each
checkerboard colour (Nelder–Mead): the base (ln Q and each held blur's width parameter) and,
per member, ln Q, width, direction and the held widths; each scored on the other colour
(``heldout_drop``) and compared with the stage's own fits (held blurs fixed, ``shape_fit``).
Nothing the diagnosis decides is changed. Numbers: ``docs/diagnosis.md``, round 46, Next.

Run: python benchmarks/probe_anisotropic_refit_held.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import stage_anisotropic_pixels as an  # noqa: E402
from geosim.diagnose.grey_render import grey_expected  # noqa: E402
from geosim.diagnose.stage_resampling_coherent import heldout_drop, rss_on_halves  # noqa: E402

#: the width parameter of each isotropic blur refitted
WIDTH_KEYS = {"resampling": "native_pitch_px", "atmospheric_blur": "f0_cyc_per_px",
              "detector_integration": "pitch_px"}
MAX_RENDERS = 120


def _fit(inp: Any, model: Any, half: np.ndarray, x0: np.ndarray, steps: np.ndarray,
         build: Any) -> Any:
    simplex = np.vstack([x0, x0 + np.diag(steps)])
    res = minimize(lambda x: rss_on_halves(inp, [half], build(x))[0], x0, method="Nelder-Mead",
                   options={"maxfev": MAX_RENDERS, "initial_simplex": simplex})
    return build(res.x)


def measure(inp: Any, model: Any, sel: Any, setup: Any, ev: Any, cands: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"q_model": model.q, "blur": model.blur}
    splits = an.screen_splits(ev)
    if not model.blur or not an.in_domain(model) or splits is None:
        return out
    rendered = grey_expected(inp, model)
    screen = an.anisotropy_screen(inp.grey - rendered, rendered, splits)
    out["screen"] = screen.dchi2
    if min(screen.dchi2) < an.SCREEN_MIN_DCHI2:
        return out
    halves = splits[0]
    keys = [(b, WIDTH_KEYS[b]) for b in model.blur if b in WIDTH_KEYS]
    w0 = np.array([model.blur[b][k] for b, k in keys])

    def with_held(blur: dict, w: np.ndarray) -> dict:
        held = {b: dict(p) for b, p in model.blur.items()}
        for (b, k), v in zip(keys, w, strict=True):
            held[b][k] = float(v)
        return {**held, **blur}

    base_models = [_fit(inp, model, halves[h], np.r_[np.log(model.q), w0],
                        np.r_[0.05, 0.05 * np.maximum(w0, 0.1)],
                        lambda x: model.without(q=float(np.exp(x[0])),
                                                blur=with_held({}, x[1:])))
                   for h in (0, 1)]
    base_rss = [rss_on_halves(inp, halves, m) for m in base_models]
    out["base_refit"] = {"params": [m.blur for m in base_models], "q": [m.q for m in base_models]}
    base_scan = an._q_scan(inp, model, halves)
    for name, shape in an.SHAPES.items():
        lo, hi = shape.bounds_px
        held_fit = an.shape_fit(inp, model, halves, name, screen, base_scan)
        width0 = float(np.clip(np.sqrt(max(screen.variance_px2, 0.0)
                                       / shape.variance_per_width2), lo, hi))

        def build(x: np.ndarray, name: str = name, shape: Any = shape,
                  lo: float = lo, hi: float = hi) -> Any:
            return model.without(q=float(np.exp(x[0])), blur=with_held({name: {
                shape.width_key: float(np.clip(x[1], lo, hi)),
                shape.direction_key: float(x[2]) % 180.0}}, x[3:]))

        ms = [_fit(inp, model, halves[h],
                   np.r_[np.log(base_models[h].q), width0, screen.direction_deg,
                         [base_models[h].blur[b][k] for b, k in keys]],
                   np.r_[0.05, 0.25 * width0 + 0.1, 20.0, 0.05 * np.maximum(w0, 0.1)], build)
              for h in (0, 1)]
        rss = [rss_on_halves(inp, halves, m) for m in ms]
        drops = [heldout_drop(halves, [base_rss[h]], [rss[h]])[h] for h in (0, 1)]
        out[name] = {"held_dchi2": held_fit.dchi2, "refit_dchi2": drops,
                     "refit_rss": [sum(r) for r in rss], "held_rss": held_fit.best()[1],
                     "refit_params": [m.blur for m in ms]}
    return out


if __name__ == "__main__":
    probe_main(__doc__.splitlines()[0], measure, stage="pixel_anisotropic")
