"""A/B of the align command between source trees (e.g. two commits), alternated rounds.

Each round runs ``geosim run SITE --only align`` once per version and worker setting, in
that order, each into a fresh copy of the version's base run folder (grid and footprints
done); it records the wall time, the CPU seconds of the command and every process it
started (``RUSAGE_CHILDREN``: the driver and, at ``--workers 2``, the local cluster's
processes, started inside the command), the step's own time from ``run.json``, the
1-minute load average before and after, and the alignment it wrote (matrices and local
check), which must be the same for every version and setting.

Usage::

    git archive OLD | tar -x -C /tmp/old     # a tree per version
    python benchmarks/bench_align_ab.py --site SITE.toml \\
        --version old=/tmp/old:/tmp/base_old --version new=/tmp/new:/tmp/base \\
        --modes 1t,2 --rounds 2 --out benchmarks/results/NAME.json

``1t`` is in-process on one thread (``GEOSIM_THREADS=1``), ``1`` in-process on every core,
``N`` a local cluster of N workers (its start-up is inside the command, so its CPU-s
include Dask's).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run_once(site: Path, src: Path, base: Path, mode: str, run: Path) -> dict:
    """One align command of the tree ``src`` into a copy of ``base``."""
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(base, run)
    env = {**os.environ, "PYTHONPATH": str(src)}
    env.pop("GEOSIM_THREADS", None)
    if mode.endswith("t"):
        env["GEOSIM_THREADS"] = "1"
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    subprocess.run([sys.executable, "-m", "geosim", "-q", "run", str(site), "--out", str(run),
                    "--workers", mode.rstrip("t"), "--only", "align"], check=True, cwd=src,
                   env=env, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    steps = json.loads((run / "run.json").read_text())["steps"]
    align = json.loads((run / "alignment.json").read_text())
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "step_s": steps["align"]["seconds"],
            "load_average_1min": [round(load0, 2), round(os.getloadavg()[0], 2)],
            "alignment": {"flights": {k: v.get("matrix_px") for k, v in
                                      align["flights"].items()},
                          "local_check": align["local_check"]}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--site", type=Path, required=True)
    ap.add_argument("--version", action="append", required=True,
                    help="NAME=SRC_TREE:BASE_RUN (repeat; run in this order every round)")
    ap.add_argument("--modes", default="1t,2")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    versions = [(v.split("=", 1)[0], *map(Path, v.split("=", 1)[1].split(":")))
                for v in args.version]
    tmp = Path(tempfile.mkdtemp(prefix="geosim-align-ab-"))
    records = []
    try:
        for r in range(args.rounds):
            for name, src, base in versions:
                for mode in args.modes.split(","):
                    rec = {"round": r, "version": name, "mode": mode,
                           **run_once(args.site, src, base, mode, tmp / f"{name}_{mode}")}
                    records.append(rec)
                    print(json.dumps({k: v for k, v in rec.items() if k != "alignment"}),
                          flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    same = all(x["alignment"] == records[0]["alignment"] for x in records)
    print(f"alignment identical in every run: {same}")
    if args.out:
        args.out.write_text(json.dumps({"benchmark": "bench_align_ab", "site": str(args.site),
                                        "versions": {n: str(s) for n, s, _ in versions},
                                        "alignment_identical": same,
                                        "runs": [{k: v for k, v in x.items() if k != "alignment"}
                                                 for x in records]}, indent=1) + "\n")


if __name__ == "__main__":
    main()
