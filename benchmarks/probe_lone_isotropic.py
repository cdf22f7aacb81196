"""Probe (round 43): the lone isotropic pixel test's scan on development cases.

For each case it runs the benchmark's diagnosis (``diagnose_independent.diagnose_case``) up
to the first pass's ``engine.pixel_isotropic`` call and stops there. Where the model it
would see holds no blur and no JPEG it records the anisotropic screen's checkerboard drops
(``stage_anisotropic_pixels.anisotropy_screen``, whose trace defers the lone test) and the
isotropic scan of ``stage_isotropic_pixels.isotropic_scan``: the held-out drop on the
left / right halves over every member and per member, and the best member, value and Q
over both halves and per member. Nothing the diagnosis decides is changed. Round 43's
numbers: ``docs/diagnosis.md``, round 43.

Run: python benchmarks/probe_lone_isotropic.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import stage_anisotropic_pixels as an  # noqa: E402
from geosim.diagnose import stage_isotropic_pixels as iso  # noqa: E402
from geosim.diagnose.grey_render import grey_expected  # noqa: E402


def measure(inp: Any, model: Any, setup: Any, ev: Any) -> dict[str, Any]:
    """The screen and the isotropic scan on ``model`` as the stage sees it."""
    out: dict[str, Any] = {"q_model": model.q, "blur": sorted(model.blur),
                           "jpeg": model.compression is not None}
    if model.blur or model.compression is not None:
        return out
    t0 = time.time()
    splits = an.screen_splits(ev)
    if splits is not None:
        rendered = grey_expected(inp, model)
        out["screen"] = an.anisotropy_screen(inp.grey - rendered, rendered, splits[:1]).dchi2
    members = list(iso.MEMBER_SCAN)
    scan = iso.isotropic_scan(inp, model, setup, ev, members)
    if scan is not None:
        present = [n for n in members if any(s[0] == n for s in scan.scanned)]
        name, value, best = scan.best()
        out["lr"] = scan.heldout_dchi2()
        out["lr_member"] = {n: scan.heldout_dchi2(n) for n in present}
        out["best"] = [name, value, best.q]
        best_of = {n: scan.best(n) for n in present}
        out["best_member"] = {n: [v, m.q] for n, (_, v, m) in best_of.items()}
    out["scan_seconds"] = time.time() - t0
    return out


def main() -> None:
    probe_main(__doc__.splitlines()[0],
               lambda inp, model, sel, setup, ev, candidates: measure(inp, model, setup, ev))


if __name__ == "__main__":
    main()
