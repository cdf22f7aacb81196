"""Probe (round 42): the lone-anisotropic pixel stage's screen and fits on development cases.

For each case it runs the benchmark's diagnosis (``diagnose_independent.diagnose_case``) up
to the first pass's ``engine.pixel_isotropic`` call, where the model the new stage
(``geosim.diagnose.stage_anisotropic_pixels``) would see is complete, and stops there.
Where that model holds no blur and no JPEG it records the screen's six held-out drops
(checkerboard, left / right, top / bottom; ``anisotropy_screen``), its second moment and
direction, and, where the weaker checkerboard drop reaches ``--fit-above``, both members'
fits (``shape_fit``: held-out drops, parameters, Q, RSS over both colours). Nothing the
diagnosis decides is changed. Round 42's numbers: ``docs/diagnosis.md``, round 42.

``--beside-blurs`` (round 45): the screen instead where the model holds a blur (a
resampling, detector or atmosphere) and no anisotropic member and no JPEG, rendered with
those blurs; no fits. Round 45's numbers: ``docs/diagnosis.md``, round 45.

``--beside-fits`` (round 46): as ``--beside-blurs``, but at the call of
``engine.pixel_anisotropic`` itself (after the isotropic pixel stage), and where the
weaker checkerboard drop reaches ``--fit-above`` both members fitted with the model's
blurs held (``shape_fit``), with whether the better fit is claimable and no worse than the
baseline. Round 46's numbers: ``docs/diagnosis.md``, round 46.

Run: python benchmarks/probe_anisotropic_screen.py IDX[,IDX...] OUT.jsonl [--fit-above 10]
[--beside-blurs | --beside-fits]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_cases  # noqa: E402

from geosim.diagnose import stage_anisotropic_pixels as an  # noqa: E402
from geosim.diagnose.grey_render import grey_expected  # noqa: E402
from geosim.diagnose.stage_withdraw import no_worse_than_baseline  # noqa: E402


def measure(inp: Any, model: Any, ev: Any, fit_above: float,
            beside_blurs: bool = False, with_fits: bool = False) -> dict[str, Any]:
    """The screen (and, above ``fit_above``, the fits) on ``model`` as the stage sees it;
    ``beside_blurs``: the screen alone, where the model holds blurs but no anisotropic
    member (and no JPEG); ``with_fits``: there also the fits."""
    out: dict[str, Any] = {"q_model": model.q, "blur": sorted(model.blur),
                           "jpeg": model.compression is not None}
    splits = an.screen_splits(ev)
    in_domain = (bool(model.blur) and not set(model.blur) & set(an.SHAPES) if beside_blurs
                 else not model.blur)
    if not in_domain or model.compression is not None or splits is None:
        return out
    rendered = grey_expected(inp, model)
    screen = an.anisotropy_screen(inp.grey - rendered, rendered, splits)
    out["screen"] = {"dchi2": screen.dchi2, "variance_px2": screen.variance_px2,
                     "direction_deg": screen.direction_deg}
    if (with_fits or not beside_blurs) and min(screen.dchi2[:2]) >= fit_above:
        t0 = time.time()
        base = an._q_scan(inp, model, splits[0])
        for name in an.SHAPES:
            f = an.shape_fit(inp, model, splits[0], name, screen, base)
            m, rss = f.best()
            out[name] = {"dchi2": f.dchi2, "params": m.blur[name], "q": m.q, "rss": rss,
                         "claimable": an.claimable(name, m),
                         "no_worse": bool(no_worse_than_baseline(inp, ev)(m))}
        out["fit_seconds"] = time.time() - t0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("indices")
    ap.add_argument("out")
    ap.add_argument("--fit-above", type=float, default=10.0)
    ap.add_argument("--beside-blurs", action="store_true",
                    help="the screen where the model holds blurs but no anisotropic member")
    ap.add_argument("--beside-fits", action="store_true",
                    help="as --beside-blurs at the anisotropic stage itself, with the fits")
    args = ap.parse_args()
    beside = args.beside_blurs or args.beside_fits
    probe_cases(args.indices, args.out,
                lambda inp, model, sel, setup, ev, cands: measure(
                    inp, model, ev, args.fit_above, beside, args.beside_fits),
                stage="pixel_anisotropic" if args.beside_fits else "pixel_isotropic")


if __name__ == "__main__":
    main()
