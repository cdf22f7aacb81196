"""Probe (round 47): where a blur the scene holds is lost — every "no worse than the
baseline" verdict a diagnosis makes, and what it withdrew.

For each case it runs the benchmark's diagnosis (``diagnose_independent.diagnose_case``)
whole, with ``no_worse_than_baseline`` wrapped in every ``geosim.diagnose`` module that
uses it: each verdict is recorded with the calling module, the model's blurs and Q, the
spectral errors of its delivered simulation and the baseline's (the evaluation blocks, then
each whole-extent measure). The row (without ``detection_limits``) is written with
``withdrawn`` (the diagnosis's withdrawn effects) and ``nwb`` (the verdicts). Nothing the
diagnosis decides is changed. Round 47's numbers: ``docs/diagnosis.md``, round 47.

Run: python benchmarks/probe_no_worse_trail.py IDX[,IDX...] OUT.jsonl
"""

from __future__ import annotations

import importlib
import json
import pkgutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import diagnose_generator as gen  # noqa: E402
import diagnose_independent as bench  # noqa: E402

import geosim.diagnose as diagnose_pkg  # noqa: E402
import geosim.diagnose.grids as grids  # noqa: E402

VERDICTS: list[dict[str, Any]] = []


def _logged(module: str) -> Callable[..., Callable[[Any], bool]]:
    """``no_worse_than_baseline`` as ``module`` calls it, recording each verdict."""
    def no_worse(inp: Any, ev: Any, se_wholes: Sequence[Callable[[np.ndarray], float]] = ()
                 ) -> Callable[[Any], bool]:
        measures = [ev.spectral_error, *se_wholes]
        base = np.round(inp.base) if inp.quantized else inp.base
        base_errors = [se(base) for se in measures]

        def ok(m: Any) -> bool:
            img = m.delivered(inp.simulate, np.random.default_rng(ev.noise_seed),
                              quantized=inp.quantized)
            errors = [se(img) for se in measures]
            verdict = all(e <= b for e, b in zip(errors, base_errors, strict=True))
            VERDICTS.append({"mod": module, "q": m.q, "ok": verdict, "se": errors,
                             "base": base_errors, "blur": m.blur})
            return verdict
        return ok
    return no_worse


def main() -> None:
    for info in pkgutil.iter_modules(diagnose_pkg.__path__):
        mod = importlib.import_module(f"geosim.diagnose.{info.name}")
        if hasattr(mod, "no_worse_than_baseline"):
            mod.no_worse_than_baseline = _logged(info.name)  # type: ignore[attr-defined]
    summary: dict[str, Any] = {}
    run = grids.diagnose_pixels

    def keep_summary(*args: Any, **kwargs: Any) -> Any:
        d = run(*args, **kwargs)
        summary["s"] = d.summary
        return d

    grids.diagnose_pixels = keep_summary  # type: ignore[assignment]
    indices, out = sys.argv[1], sys.argv[2]
    sources = gen.default_sources()
    with open(out, "a") as f:
        for i in (int(v) for v in indices.split(",")):
            VERDICTS.clear()
            row = bench.diagnose_case(gen.make_case(i, sources))
            row.pop("detection_limits", None)
            row["withdrawn"] = summary["s"].get("withdrawn")
            row["nwb"] = list(VERDICTS)
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(i, sorted(row["truth"]), sorted(row["claimed"]),
                  [w["name"] for w in row["withdrawn"]], flush=True)


if __name__ == "__main__":
    main()
