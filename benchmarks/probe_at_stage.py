"""Shared loop of the probes that stop the benchmark's diagnosis at the first pass's
``engine.pixel_isotropic`` call (``probe_anisotropic_screen.py``,
``probe_lone_isotropic.py``): one JSON line per case, what ``measure`` recorded there."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import diagnose_generator as gen  # noqa: E402
import diagnose_independent as bench  # noqa: E402

from geosim.diagnose import engine  # noqa: E402


class _Stop(Exception):
    """Raised at the stage's place to end the diagnosis there."""


def probe_cases(indices: str, out: str, measure: Callable[..., dict[str, Any]],
                stage: str = "pixel_isotropic") -> None:
    """Run the cases ``indices`` ("i,j,...") up to the first pass's call of ``engine.<stage>``
    (a pixel stage taking ``(inp, model, sel, setup, ev, candidates)``), appending
    ``{"i", "probe", "seconds"}`` per case to ``out`` (JSON lines);
    ``measure(inp, model, sel, setup, ev, candidates)`` gives ``probe`` from what the
    stage would see."""
    captured: dict[str, Any] = {}

    def hook(*args: Any, **kwargs: Any) -> None:
        captured["result"] = measure(*args)
        raise _Stop

    setattr(engine, stage, hook)
    sources = gen.default_sources()
    with open(out, "a") as f:
        for i in (int(v) for v in indices.split(",")):
            captured.clear()
            t0 = time.time()
            try:
                bench.diagnose_case(gen.make_case(i, sources))
            except _Stop:
                pass
            rec = {"i": i, "probe": captured.get("result", {}), "seconds": time.time() - t0}
            f.write(json.dumps(rec) + "\n")
            f.flush()
            print(i, json.dumps(rec["probe"])[:200], flush=True)


def probe_main(description: str, measure: Callable[..., dict[str, Any]],
               stage: str = "pixel_isotropic") -> None:
    """The command line of a probe: ``IDX[,IDX...] OUT.jsonl``, then :func:`probe_cases`
    stopping at ``engine.<stage>``."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("indices")
    ap.add_argument("out")
    args = ap.parse_args()
    probe_cases(args.indices, args.out, measure, stage)
