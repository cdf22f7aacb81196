"""Probe (round 44): the anisotropic member the transfer named, checked in the pixels.

For each case it runs the benchmark's diagnosis (``diagnose_independent.diagnose_case``) up
to the first pass's ``engine.pixel_isotropic`` call and stops there. Where the model holds
one anisotropic member (``motion_smear`` or ``off_nadir_anisotropy``) and no JPEG, it fits
that member and the other one in the pixels (ln Q, width, direction by Nelder–Mead, the
model's other blurs held, started from the claimed blur's second moment and direction) on
each checkerboard half and scores each fit on the other half. ``naming_dchi2`` is, per
half fitted on, the other half's drop of the residual sum of squares when the other member
replaces the claimed one, in units of that half's residual variance per pixel (positive:
the other member predicts better). The fits are the stage's own
(``geosim.diagnose.stage_anisotropic_member.member_check``, round 45), and that stage is
switched off here so that the probe sees the member the transfer named. Round 44's and 45's
numbers: ``docs/diagnosis.md``.

Run: python benchmarks/probe_anisotropic_naming.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import engine  # noqa: E402
from geosim.diagnose import stage_anisotropic_member as am  # noqa: E402
from geosim.diagnose.model import ForwardModel  # noqa: E402
from geosim.diagnose.stage_resampling_coherent import (  # noqa: E402
    checker_halves,
    rss_on_halves,
)


def measure(inp: Any, model: ForwardModel, ev: Any) -> dict[str, Any]:
    """Both members fitted on each checkerboard half, scored on the other
    (:func:`~geosim.diagnose.stage_anisotropic_member.member_check`, both halves)."""
    out: dict[str, Any] = {"q_model": model.q, "blur": model.blur,
                           "jpeg": model.compression is not None}
    halves = checker_halves(ev)
    if (sum(n in model.blur for n in am.MEMBERS) != 1 or model.compression is not None
            or halves is None):
        return out
    t0 = time.time()
    check = am.member_check(inp, model, halves)
    fits = {name: [{"q": m.q, "p": m.blur[name], "rss": r}
                   for m, r in zip(check.models[name], check.rss[name], strict=True)]
            for name in (check.claimed, check.other)}
    out.update(x=check.claimed, rss_model=rss_on_halves(inp, halves, model), fits=fits,
               naming_dchi2=check.naming_dchi2, seconds_probe=time.time() - t0)
    return out


def main() -> None:
    # the stage that acts on this check (round 45) runs before the probe's hook: off, so
    # that the probe sees the member the transfer named
    engine.pixel_member = lambda inp, model, *args: model
    probe_main(__doc__.splitlines()[0],
               lambda inp, model, sel, setup, ev, candidates: measure(inp, model, ev))


if __name__ == "__main__":
    main()
