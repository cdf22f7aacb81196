"""Probe (round 47): the censored-likelihood blur test under JPEG, whatever the model holds.

At the call of ``engine.censored_resampling_check`` (first pass), where the model holds a
JPEG, it records the model's Q and blurs and, with the model's blurs left out, the
censored test's own fits (``stage_jpeg_blur``: Q and each member on one half of the
blocks, scored on the other): each member's held-out gains (nats) over the model without
a blur, and its fitted parameters. Nothing the diagnosis decides is changed.

Run: python benchmarks/probe_jpeg_blur.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from probe_at_stage import probe_main  # noqa: E402

from geosim.diagnose import stage_jpeg_blur as jb  # noqa: E402


def _gains(score: Any, halves: Any, members: list[str], q0: float) -> dict[str, Any]:
    base = [score.fit_q({}, h, q0) for h in halves]
    base_heldout = jb._base_heldout(score, halves, base)
    out: dict[str, Any] = {"base_q": [b.q for b in base]}
    for n in members:
        fits = [score.fit_member(n, h, q0, jb.MEMBER_STARTS[n]) for h in halves]
        out[n] = {"gain": jb._heldout(score, halves, fits, base_heldout),
                  "params": [jb._claimed(f.blur) for f in fits], "q": [f.q for f in fits]}
    return out


def measure(inp: Any, model: Any, window: Any, ev: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"q_model": model.q, "blur": model.blur,
                           "jpeg": None if model.compression is None
                           else model.compression.quality}
    if model.compression is None:
        return out
    prepared = jb._prepare(inp, model, window, ev)
    if prepared is None:
        out["too_small"] = True
        return out
    score, halves = prepared
    members = [n for n in jb.MEMBER_STARTS if n in window.candidates]
    if not jb._renders_natively(inp, model.q) and "resampling" in members:
        members.remove("resampling")
    out["plain"] = _gains(score, halves, members, model.q)
    return out


if __name__ == "__main__":
    probe_main(__doc__.splitlines()[0], measure, stage="censored_resampling_check")
