"""CPU seconds per phase of the align step, one process alone and two at once.

The align step's work (what ``geosim align`` does on a site, in a run folder where grid
and footprints are done) is run in child processes on one thread each
(``GEOSIM_THREADS=1``, in-process engine: the tasks of a single-threaded Dask worker, without
Dask), under a cProfile whose clock is the process's CPU time. Each child also runs the
pre-flight integrity read of the inputs (``validate.check_rasters``) and the footprints'
tasks, which every command that reads the flights' pixels runs before the step. Per phase
it reports the CPU seconds of one child alone (``alone``) and of each of two children
started together (``pair``): a phase whose CPU grows when two run at once is bound by
something the processes share (memory bandwidth, caches), not by the arithmetic.
Rounds alternate alone / pair, so a change in the machine's load hits both.

Usage::

    python benchmarks/bench_align_phases.py --site SITE.toml --run RUN --rounds 2 \\
        --out benchmarks/results/bench_align_phases.json

``RUN`` must hold grid and footprints (``geosim run SITE --out RUN --only grid --only
footprints``); each child aligns into its own copy of it.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Phases: (label, file suffix, function (``a|b``: either; the names of this version and
#: of the one before the memory-traffic work), direct caller's function or None). With a
#: caller, only the time of the calls made directly from that function counts.
PHASES = (
    ("preflight read (check_rasters)", "validate.py", "check_rasters", None),
    ("footprints (per-flight tasks)", "steps.py", "footprint_task", None),
    ("align step (run_align)", "steps.py", "run_align", None),
    ("  registration tasks", "alignment.py", "registration_task", None),
    ("    reading the two windows through their warps", "onewarp.py", "__call__",
     "registration_task"),
    ("    register_pair", "alignment.py", "register_pair", "registration_task"),
    ("  local check tasks", "alignment.py", "local_check_task", None),
    ("    reading every flight's block through its warp", "onewarp.py", "__call__",
     "local_check_task"),
    ("    phase correlation of the windows", "local.py", "local_shift_field|local_shift_fields",
     "local_check_task"),
    ("any: source decode (rasterio read, read_masks)", "bench_align_phases.py", "read*", None),
    ("any: bicubic remap and mask", "onewarp.py", "remap_window|remap_fixed", None),
    ("any: warp coordinates and maps", "onewarp.py", "_window_coords|_window_maps", None),
    ("any: as_grey", "phasecorr.py", "as_grey", None),
    ("any: phasecorr prepare", "phasecorr.py", "prepare", None),
    ("any: correlate_prepared", "phasecorr.py", "correlate_prepared", None),
)


def _profiled_reads() -> None:
    """Make rasterio's (Cython) reads visible to cProfile: Python wrappers named read*."""
    from rasterio.io import DatasetReader

    base_read, base_masks = DatasetReader.read, DatasetReader.read_masks

    def read_image(self, *args, **kwargs):
        return base_read(self, *args, **kwargs)

    def read_mask(self, *args, **kwargs):
        return base_masks(self, *args, **kwargs)

    DatasetReader.read, DatasetReader.read_masks = read_image, read_mask


def child(site_file: str, run: str, prof_path: str) -> dict:
    """Preflight read, footprint tasks and the align step on one thread, profiled."""
    sys.path.insert(0, str(ROOT))
    os.environ["GEOSIM_THREADS"] = "1"
    from geosim import engine
    from geosim.config import load_site
    from geosim.prepare import steps
    from geosim.prepare.steps import FootprintTask, footprint_task, read_grid
    from geosim.validate import check_rasters

    site = load_site(site_file)
    grid = read_grid(run)
    _profiled_reads()
    pr = cProfile.Profile(time.process_time)
    cpu0, t0 = time.process_time(), time.perf_counter()
    with engine.using(engine.InProcess()):
        pr.enable()
        check_rasters(site)
        engine.parallel_map(footprint_task, [
            FootprintTask(str(f.image), grid.crs, grid.sat_gsd_m,
                          site.parameters.footprint_simplify_m) for f in site.flights])
        steps.run_align(site, run)
        pr.disable()
    pr.dump_stats(prof_path)
    return {"cpu_s": round(time.process_time() - cpu0, 2),
            "wall_s": round(time.perf_counter() - t0, 2)}


def phase_seconds(prof_path: str) -> dict[str, float]:
    """Cumulative CPU seconds of each phase of :data:`PHASES` in one profile."""
    stats = pstats.Stats(prof_path).stats  # (file, line, fn) -> (cc, nc, tt, ct, callers)
    out: dict[str, float] = {}
    for label, file, fn, caller in PHASES:
        def match(k: tuple, fn: str = fn, file: str = file) -> bool:
            name_ok = k[2].startswith(fn[:-1]) if fn.endswith("*") else k[2] in fn.split("|")
            return name_ok and k[0].endswith(file)
        keys = [k for k in stats if match(k)]
        if caller is None:
            total = sum(stats[k][3] for k in keys)
        else:
            total = sum(v[3] for k in keys for c, v in stats[k][4].items() if c[2] == caller)
        out[label] = round(total, 2)
    return out


def run_round(site: Path, base: Path, n: int, tmp: Path, tag: str) -> list[dict]:
    """``n`` children at once, each into its own copy of ``base``."""
    procs = []
    for i in range(n):
        run = tmp / f"{tag}_{i}"
        shutil.copytree(base, run)
        prof = tmp / f"{tag}_{i}.prof"
        cmd = [sys.executable, __file__, "--child", "--site", str(site), "--run", str(run),
               "--prof", str(prof)]
        procs.append((subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True,
                                       env={**os.environ, "PYTHONPATH": str(ROOT)}), prof, run))
    load0 = os.getloadavg()[0]
    recs = []
    for p, prof, run in procs:
        out, _ = p.communicate()
        if p.returncode != 0:
            raise RuntimeError(f"child failed ({p.returncode})")
        rec = json.loads(out.strip().splitlines()[-1])
        rec["phases_cpu_s"] = phase_seconds(str(prof))
        rec["load_average_1min"] = [round(load0, 2), round(os.getloadavg()[0], 2)]
        rec["alignment_json"] = json.loads((run / "alignment.json").read_text())
        recs.append(rec)
    return recs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--site", type=Path)
    ap.add_argument("--run", type=Path)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--label", default="")
    ap.add_argument("--child", action="store_true")
    ap.add_argument("--prof")
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child(str(args.site), str(args.run), args.prof)))
        return
    tmp = Path(tempfile.mkdtemp(prefix="geosim-alignph-"))
    rounds = []
    try:
        for r in range(args.rounds):
            for n in (1, 2):
                recs = run_round(args.site, args.run, n, tmp, f"r{r}_n{n}")
                print(f"round {r}, {n} at once: "
                      + "; ".join(f"cpu {x['cpu_s']} s wall {x['wall_s']} s "
                                  f"load {x['load_average_1min']}" for x in recs), flush=True)
                rounds.append({"round": r, "at_once": n, "children": recs})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    docs = [c.pop("alignment_json") for rd in rounds for c in rd["children"]]
    same = all(_strip(d) == _strip(docs[0]) for d in docs)
    doc = {"benchmark": "bench_align_phases", "label": args.label, "site": str(args.site),
           "rounds": rounds, "alignment_json_identical": same,
           "load_average_at_end": [round(x, 2) for x in os.getloadavg()]}
    print(table(doc))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(doc, indent=2) + "\n")


def _strip(doc: dict) -> dict:
    return json.loads(json.dumps(doc))


def table(doc: dict) -> str:
    """Markdown: per phase, the median CPU-s alone and per child two at once."""
    import statistics

    alone = [c["phases_cpu_s"] for rd in doc["rounds"] if rd["at_once"] == 1
             for c in rd["children"]]
    pair = [c["phases_cpu_s"] for rd in doc["rounds"] if rd["at_once"] == 2
            for c in rd["children"]]
    lines = ["| phase | CPU-s alone | CPU-s each, two at once | ratio |", "|---|---|---|---|"]
    for label, *_ in PHASES:
        a = statistics.median(x[label] for x in alone) if alone else float("nan")
        b = statistics.median(x[label] for x in pair) if pair else float("nan")
        lines.append(f"| {label} | {a:.2f} | {b:.2f} | {b / a if a else float('nan'):.2f} |")
    lines.append(f"\nalignment.json identical in every child: {doc['alignment_json_identical']}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
