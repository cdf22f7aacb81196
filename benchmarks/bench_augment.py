"""Benchmark: augmented pairs per second for a 5000 × 5000 and a 500 × 500 pair.

A 5000 × 5000 pair is a UAV tile pair at 0.05 m (250 m × 250 m); a 500 × 500 pair
is the same ground degraded to 0.5 m (the shipped config's lengths are rescaled
by the GSD, so its warp and shifts mean the same metres on both). Imagery: the
real Brazil pasture orthomosaic from ../shared/realdata resized to the pair size
(synthetic texture if absent), RGB uint8, 40 cattle-sized boxes per image.

Cases, each run once:

- ``shipped``: the shipped example config (geosim/augment/default_augment.toml)
  with its probabilities: the average cost of a typical output.
- ``all applied``: the same config with every probability set to 1 (worst case).
- per function: each function alone, probability 1 (where the time goes).
- ``end to end``: ``run_augment`` on a run folder (read GeoTIFF tiles, augment,
  write GeoTIFF + YOLO + CSVs).

Per worker. ``geosim augment --workers N`` runs N single-threaded worker
processes (OpenCV at one thread each), so the per-worker rate is that of one
thread: the ``shipped, 1 thread`` case. Its CPU seconds per pair are the
load-independent figure (the wall time on this shared 2-core machine includes
waiting for a core); the issue's target is 0.5 pairs/s per worker, i.e. ≤ 2 s
CPU per pair.

Before / after in the same run: ``--baseline-rev REV`` exports that git revision
of geosim (``git archive``) to a temporary folder and times its shipped pipeline,
one thread, on the same pairs and seeds in a subprocess, alternating with this
tree's, so both see the same machine load. With ``--end-to-end`` the same comparison
times the whole command instead (``run_augment`` on a run folder of one 5000² pair: read
the GeoTIFF tiles, augment, write the GeoTIFF outputs, YOLO labels and CSVs), and only that.

Writes benchmarks/results/bench_augment.json and prints a markdown table.
Usage: ``python benchmarks/bench_augment.py [--quick] [--baseline-rev main] [--end-to-end
[--outputs N] [--rounds R] [--compress deflate,none]] [--out FILE]``.

Per-worker rate of the whole command (issue 13's target, >= 0.5 pairs/s per worker, i.e.
<= 2 CPU s per output pair, with the default deflate output): ``--end-to-end``, whose
``cpu_pairs_per_second`` per code is that rate; run it with ``OMP_NUM_THREADS=1
OPENCV_FOR_THREADS_NUM=1 GDAL_NUM_THREADS=1`` as a Dask worker runs (OpenCV is set to one
thread while timed either way, and ``GEOSIM_THREADS=1`` is set for the command: the
default since 23 Nov, but the in-process engine of earlier revisions, which ``--baseline-rev``
may time, gave its tasks every core).
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from geosim.augment import AugImage, Boxes, Pipeline, load_pipeline  # noqa: E402
from geosim.augment.runner import run_augment  # noqa: E402
from geosim.io.raster import write_geotiff  # noqa: E402

REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))
OUT = ROOT / "benchmarks" / "results" / "bench_augment.json"


def _texture(size: int, seed: int) -> np.ndarray:
    src = REALDATA / "brazil_pasture_10cm_epsg3395.tif"
    if src.is_file():
        import rasterio

        with rasterio.open(src) as ds:
            img = ds.read([1, 2, 3])
        hwc = np.ascontiguousarray(np.moveaxis(img, 0, -1))
        if seed:  # the second image of the pair: the same ground, slightly changed
            hwc = np.ascontiguousarray(np.roll(hwc, 3, axis=1))
        out = cv2.resize(hwc, (size, size), interpolation=cv2.INTER_CUBIC)
        return np.ascontiguousarray(np.moveaxis(out, -1, 0))
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (3, size // 16 + 1, size // 16 + 1), dtype=np.uint8)
    return np.stack([cv2.resize(b, (size, size), interpolation=cv2.INTER_CUBIC) for b in small])


def _pair(size: int) -> tuple[AugImage, AugImage]:
    rng = np.random.default_rng(0)
    cattle_px = 40 * size / 5000  # ~2 m at 0.05 m
    xy = rng.uniform(0.1 * size, 0.9 * size, (40, 2))
    boxes = Boxes(np.zeros(40, int), np.column_stack([xy, xy + [cattle_px, cattle_px / 2]]))
    mask = np.ones((size, size), bool)
    return (AugImage(_texture(size, 0), mask, boxes), AugImage(_texture(size, 1), mask, boxes))


def _time_pipeline(p: Pipeline, a: AugImage, b: AugImage, n: int, length_scale: float,
                   threads: int | None = None, first_seed: int = 0) -> dict:
    """Time ``n`` pairs (seeds ``first_seed`` on) after a warm-up; ``threads``: OpenCV's."""
    before = cv2.getNumThreads()
    if threads is not None:
        cv2.setNumThreads(threads)
    try:
        p.apply(a, b, np.random.default_rng(10_000), length_scale=length_scale)  # warm-up
        load = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(first_seed, first_seed + n):
            p.apply(a, b, np.random.default_rng(i), length_scale=length_scale)
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        cv2.setNumThreads(before)
    return {"pairs": n, "seconds": round(dt, 3), "pairs_per_second": round(n / dt, 3),
            "seconds_per_pair": round(dt / n, 4), "cpu_seconds_per_pair": round(cpu / n, 4),
            "cpu_pairs_per_second": round(n / cpu, 3), "load_average": round(load, 2)}


def shipped_one_thread(size: int, n: int, first_seed: int = 0) -> dict:
    """The ``shipped, 1 thread`` case with whatever geosim is importable (for the baseline)."""
    a, b = _pair(size)
    return _time_pipeline(load_pipeline(), a, b, n, 1.0 if size == 5000 else 0.1, threads=1,
                          first_seed=first_seed)


_BASELINE_SCRIPT = """
import importlib.util, json, sys
sys.path.insert(0, {src!r})
import geosim.augment  # the baseline's, imported before the benchmark puts this tree first
assert geosim.augment.__file__.startswith({src!r}), geosim.augment.__file__
spec = importlib.util.spec_from_file_location("bench_augment_here", {bench!r})
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
print(json.dumps(bench.{func}({size}, {n}, {first})))
"""


def _export_revision(rev: str, dest: Path) -> str:
    """``git archive`` revision ``rev`` of this repository into ``dest``; its commit id."""
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", rev], check=True,
                            capture_output=True, text=True).stdout.strip()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", commit], check=True,
                             capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    return commit


def _baseline_one_thread(src: Path, size: int, n: int, first_seed: int,
                         func: str = "shipped_one_thread") -> dict:
    code = _BASELINE_SCRIPT.format(src=str(src), bench=str(Path(__file__).resolve()), size=size,
                                   n=n, first=first_seed, func=func)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, env=env, cwd=src)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _all_applied(p: Pipeline) -> Pipeline:
    return replace(p, steps=tuple(replace(s, probability=1.0) for s in p.steps))


def end_to_end_one_thread(size: int, n: int, first_seed: int = 0,
                          compress: str | None = None) -> dict:
    """The whole command (``run_augment``, GeoTIFF in/out) with whatever geosim is importable.

    One pair, ``n`` outputs, seed ``first_seed``, after an untimed one-output warm-up in
    the same process (a worker's steady state); one thread for OpenCV, GDAL and FFTs as on
    a worker (``GEOSIM_THREADS=1`` while timed: the in-process engine of revisions before
    23 Nov would give the task every core);
    ``compress``: the GeoTIFF compression (``None``: the code's default, for revisions
    without the option).
    """
    a, b = _pair(size)
    before = cv2.getNumThreads()
    cv2.setNumThreads(1)
    # revisions before 23 Nov ran run_augment's in-process tasks with every core for
    # OpenCV, GDAL and FFTs unless GEOSIM_THREADS said otherwise; a Dask worker runs them
    # with one: time what a worker does, whatever the revision
    threads_env = os.environ.get("GEOSIM_THREADS")
    os.environ["GEOSIM_THREADS"] = "1"
    try:
        # warm-up (untimed): one output of another seed, so that the timed run sees the
        # process as a worker does after its first pair (imports, GDAL, the heap)
        _end_to_end(size, 1, a, b, seed=10_000 + first_seed, compress=compress)
        load = os.getloadavg()[0]
        r = _end_to_end(size, n, a, b, seed=first_seed + 1, compress=compress)
    finally:
        cv2.setNumThreads(before)
        if threads_env is None:
            del os.environ["GEOSIM_THREADS"]
        else:
            os.environ["GEOSIM_THREADS"] = threads_env
    return {**r, "cpu_pairs_per_second": round(1 / r["cpu_seconds_per_pair"], 3),
            "load_average": round(load, 2)}


def _end_to_end(size: int, n: int, a: AugImage, b: AugImage, seed: int = 1,
                compress: str | None = None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "run"
        gsd = 0.05 if size >= 5000 else 0.05 * 5000 / size
        t = Affine(gsd, 0, 500000, 0, -gsd, 6200000)
        for flight, img in (("PA1", a), ("PA2", b)):
            write_geotiff(d / "tiles" / flight / "r000_c000.tif", img.image, transform=t,
                          crs="EPSG:32756")
            lab = d / "labels" / "yolo" / flight
            lab.mkdir(parents=True)
            lines = [f"{r[0]:.0f} {r[1]:.6f} {r[2]:.6f} {r[3]:.6f} {r[4]:.6f}"
                     for r in img.boxes.to_yolo(img.shape)]
            (lab / "r000_c000.txt").write_text("\n".join(lines) + "\n")
        with open(d / "pairs.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["pair_id", "tile_id", "flight_a", "flight_b", "acquired_a", "acquired_b",
                        "path_a", "path_b", "minx", "miny", "maxx", "maxy", "crs"])
            w.writerow(["p0", "r000_c000", "PA1", "PA2", "", "", "tiles/PA1/r000_c000.tif",
                        "tiles/PA2/r000_c000.tif", 0, 0, 1, 1, "EPSG:32756"])
        with _stage_timer() as stages, _phase_timer() as phases:
            t0, c0 = time.perf_counter(), time.process_time()
            s = run_augment(d / "pairs.csv", load_pipeline(), n=n,
                            out_dir=Path(tmp) / "aug", seed=seed, **_compress_kw(compress))
            dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        sizes = sorted((Path(tmp) / "aug" / "images").iterdir())
        image_mb = sum(f.stat().st_size for f in sizes) / len(sizes) / 1e6
    per_pair = {k: round(v / n, 4) for k, v in stages.items()}
    per_pair["other"] = round(cpu / n - sum(per_pair.values()), 4)
    by_phase = {k: round(v / n, 4) for k, v in phases.items()}
    by_phase["rest_of_pipeline_and_command"] = round(cpu / n - sum(by_phase.values()), 4)
    return {"pairs": n, "seconds": round(dt, 3), "pairs_per_second": round(n / dt, 3),
            "seconds_per_pair": round(dt / n, 4), "cpu_seconds_per_pair": round(cpu / n, 4),
            "cpu_seconds_per_pair_by_stage": per_pair,
            "cpu_seconds_per_pair_by_phase": by_phase, "image_mb": round(image_mb, 2),
            "compress": compress, "boxes_out": s["boxes_out"]}


#: ``--phases``: what each phase of the whole command wraps, ``(module, attribute)``; every
#: call site looks the name up there at call time. Time is exclusive: a wrapped call made
#: inside another counts for its own phase only.
PHASES = {
    "read_decode": [("geosim.augment.runner", "read_tile"), ("geosim.augment.runner",
                                                             "read_yolo")],
    "warp_field": [("geosim.augment.functions", "smooth_field")],
    "geometric_resample": [("geosim.augment.pipeline", "affine_resample_hwc"),
                           ("geosim.augment.pipeline", "remap_resample_hwc"),
                           ("geosim.augment.pipeline", "permute_exact")],
    "mask_zeroing": [("geosim.augment.pipeline", "zero_invalid"),
                     ("geosim.augment.resample", "zero_invalid")],
    "photometric_colour_hsv": [("geosim.augment.photometric", "colour_shift"),
                               ("geosim.augment.photometric", "hsv_shift"),
                               ("geosim.augment.photometric", "colour_lut"),
                               ("geosim.augment.pipeline", "_photometric_stage"),
                               ("geosim.augment.pipeline", "_photometric_block")],
    "noise": [("geosim.augment.photometric", "add_noise")],
    "boxes": [("geosim.augment.geometry.BoxTrack", "map_points"),
              ("geosim.augment.geometry.BoxTrack", "to_boxes"),
              ("geosim.augment.geometry.BoxTrack", "from_boxes")],
    "encode_write": [("geosim.augment.runner", "write_image")],
    "bookkeeping_files": [("geosim.augment.runner", "write_yolo"),
                          ("geosim.augment.runner", "write_json"),
                          ("geosim.augment.runner", "write_csv")],
}


@contextlib.contextmanager
def _phase_timer():  # type: ignore[no-untyped-def]
    """Exclusive CPU seconds by phase (:data:`PHASES`) of whatever runs inside."""
    import importlib

    spent = dict.fromkeys(PHASES, 0.0)
    stack: list[list[float]] = []  # [start, child seconds] of the open wrapped calls
    saved = []

    def wrap(phase: str, func, static: bool):  # type: ignore[no-untyped-def]
        def timed(*args, **kwargs):  # type: ignore[no-untyped-def]
            stack.append([time.process_time(), 0.0])
            try:
                return func(*args, **kwargs)
            finally:
                start, child = stack.pop()
                total = time.process_time() - start
                spent[phase] += total - child
                if stack:
                    stack[-1][1] += total
        return staticmethod(timed) if static else timed

    for phase, targets in PHASES.items():
        for owner_name, attr in targets:
            mod_name, _, cls = owner_name.partition(".geometry.")
            owner = (getattr(importlib.import_module("geosim.augment.geometry"), cls)
                     if cls else importlib.import_module(owner_name))
            raw = owner.__dict__.get(attr)
            if raw is None:  # not in this revision
                continue
            static = isinstance(raw, classmethod | staticmethod)
            func = raw.__func__ if static else raw
            if isinstance(raw, classmethod):
                wrapped = classmethod(wrap(phase, func, False))
            else:
                wrapped = wrap(phase, func, static)
            saved.append((owner, attr, raw))
            setattr(owner, attr, wrapped)
    try:
        yield spent
    finally:
        for owner, attr, raw in saved:
            setattr(owner, attr, raw)


def _compress_kw(compress: str | None) -> dict:
    """``compress=`` for ``run_augment`` when given (a baseline revision may lack it)."""
    return {} if compress is None else {"compress": compress}


@contextlib.contextmanager
def _stage_timer():  # type: ignore[no-untyped-def]
    """CPU seconds spent in each stage of the command, by wrapping what the runner calls.

    Stages: ``read`` (source tiles), ``augment`` (the pipeline), ``write_images``,
    ``write_labels`` (YOLO), ``write_meta`` (per-pair JSON, the summary) and
    ``write_csv`` (manifest, parameters.csv); the rest of the command is ``other``.
    """
    from geosim.augment import runner

    targets = {"read": (runner, "read_tile"), "augment": (runner.Pipeline, "apply"),
               "write_images": (runner, "write_image"), "write_labels": (runner, "write_yolo"),
               "write_meta": (runner, "write_json"), "write_csv": (runner, "write_csv")}
    spent = dict.fromkeys(targets, 0.0)
    saved = []

    def wrap(stage: str, func):  # type: ignore[no-untyped-def]
        def timed(*args, **kwargs):  # type: ignore[no-untyped-def]
            c0 = time.process_time()
            try:
                return func(*args, **kwargs)
            finally:
                spent[stage] += time.process_time() - c0
        return timed

    for stage, (owner, name) in targets.items():
        func = owner.__dict__[name]
        saved.append((owner, name, func))
        setattr(owner, name, wrap(stage, func))
    try:
        yield spent
    finally:
        for owner, name, func in saved:
            setattr(owner, name, func)


def _baseline_and_current(rev: str, n: int, func: str = "shipped_one_thread") -> dict:
    """Shipped 5000 px, one thread: baseline revision and this tree, alternating (same load).

    ``func``: ``shipped_one_thread`` (the pipeline alone) or ``end_to_end_one_thread``.
    """
    here = globals()[func]
    out: dict = {"revision": rev, "case": func, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        out["commit"] = _export_revision(rev, Path(tmp))
        half = max(1, n // 2)
        for rnd in range(2):  # seeds 0..half-1, then half..2·half-1: both codes, same pairs
            for which in ("baseline", "this tree"):
                r = (_baseline_one_thread(Path(tmp), 5000, half, rnd * half, func)
                     if which == "baseline" else here(5000, half, rnd * half))
                out["runs"].append({"round": rnd, "code": which, **r})
                print(f"5000 shipped, 1 thread, {which} (round {rnd}): {r}", flush=True)
    for which in ("baseline", "this tree"):
        runs = [r for r in out["runs"] if r["code"] == which]
        pairs = sum(r["pairs"] for r in runs)
        cpu = sum(r["cpu_seconds_per_pair"] * r["pairs"] for r in runs)
        wall = sum(r["seconds"] for r in runs)
        out[which] = {"pairs": pairs, "cpu_seconds_per_pair": round(cpu / pairs, 3),
                      "cpu_pairs_per_second": round(pairs / cpu, 3),
                      "wall_pairs_per_second": round(pairs / wall, 3),
                      "load_average": [r["load_average"] for r in runs]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repetitions")
    ap.add_argument("--baseline-rev", default=None,
                    help="git revision to time the shipped 5000 px pipeline of, in the same run")
    ap.add_argument("--end-to-end", action="store_true",
                    help="time only the whole command (GeoTIFF in/out), with --baseline-rev "
                    "also that revision's, alternating")
    ap.add_argument("--outputs", type=int, default=None,
                    help="--end-to-end: outputs per command run (--n; default 5 as the CLI's "
                    "--n, 2 with --quick)")
    ap.add_argument("--rounds", type=int, default=2,
                    help="--end-to-end: alternating rounds (default 2)")
    ap.add_argument("--compress", default="deflate,none",
                    help="--end-to-end: GeoTIFF compressions of this tree to time (default "
                    "deflate,none)")
    ap.add_argument("--out", default=None, help="results JSON (default: benchmarks/results/)")
    args = ap.parse_args()
    if args.end_to_end:
        _main_end_to_end(args)
        return
    shipped = load_pipeline()
    full = _all_applied(shipped)
    reps = {5000: (2, 1) if args.quick else (4, 1), 500: (20, 10) if args.quick else (60, 20)}
    n_shipped = {5000: 8 if args.quick else 12, 500: 20 if args.quick else 60}
    results: dict = {
        "machine": {"python": platform.python_version(), "platform": platform.platform(),
                    "cpus": os.cpu_count(), "numpy": np.__version__, "opencv": cv2.__version__,
                    "opencv_threads": cv2.getNumThreads(),
                    "load_average_at_start": [round(x, 2) for x in os.getloadavg()]},
        "imagery": "realdata brazil pasture resized" if (
            REALDATA / "brazil_pasture_10cm_epsg3395.tif").is_file() else "synthetic texture",
        "config": "geosim/augment/default_augment.toml", "cases": []}
    if args.baseline_rev:
        results["baseline"] = _baseline_and_current(args.baseline_rev, n_shipped[5000])
    for size in (5000, 500):
        a, b = _pair(size)
        ls = 1.0 if size == 5000 else 0.1  # lengths: 0.05 m reference → this GSD
        n_main, n_fn = reps[size]
        r = _time_pipeline(shipped, a, b, n_shipped[size], ls, threads=1)
        results["cases"].append({"size_px": size, "case": "shipped, 1 thread", **r})
        print(f"{size} shipped, 1 thread: {r}", flush=True)
        for label, p, n in (("shipped", shipped, n_shipped[size]),
                            ("all applied", full, n_main)):
            r = _time_pipeline(p, a, b, n, ls)
            results["cases"].append({"size_px": size, "case": label, **r})
            print(f"{size} {label}: {r}", flush=True)
        for step in shipped.steps:
            p = Pipeline((replace(step, probability=1.0),), reference_gsd_m=None)
            r = _time_pipeline(p, a, b, n_fn, ls)
            results["cases"].append({"size_px": size, "case": f"only {step.function.name}", **r})
            print(f"{size} only {step.function.name}: {r}", flush=True)
        r = _end_to_end(size, n_fn, a, b)
        results["cases"].append({"size_px": size, "case": "end to end (GeoTIFF in/out)", **r})
        print(f"{size} end to end: {r}", flush=True)
        del a, b
    results["machine"]["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    results["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    out_path = Path(args.out) if args.out else OUT
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(results, indent=2) + "\n")
    print()
    if "baseline" in results:
        _print_baseline_table(results["baseline"], "5000 shipped, 1 thread")
        print()
    print("| pair size (px) | case | pairs | pairs/s | wall s/pair | CPU s/pair | load |")
    print("|---|---|---|---|---|---|---|")
    for c in results["cases"]:
        print(f"| {c['size_px']} | {c['case']} | {c['pairs']} | {c['pairs_per_second']} | "
              f"{c['seconds_per_pair']} | {c['cpu_seconds_per_pair']} | "
              f"{c.get('load_average', '')} |")
    m = results["machine"]
    print(f"\n{m['cpus']} CPUs, load average {m['load_average_at_start'][0]} at start, "
          f"{m['load_average_at_end'][0]} at end (shared machine: wall times include waiting); "
          f"peak RSS {results['peak_rss_mb']} MB; results in {out_path}")


def _print_baseline_table(res: dict, title: str) -> None:
    """Markdown table of a baseline revision's timing next to this tree's."""
    print(f"| {title} | pairs | CPU s/pair | pairs/s (CPU) | pairs/s (wall) "
          "| load average |\n|---|---|---|---|---|---|")
    for which in ("baseline", "this tree"):
        r = res[which]
        name = f"{res['revision']} ({res['commit'][:8]})" if which == "baseline" else which
        print(f"| {name} | {r['pairs']} | {r['cpu_seconds_per_pair']} | "
              f"{r['cpu_pairs_per_second']} | {r['wall_pairs_per_second']} | "
              f"{', '.join(map(str, r['load_average']))} |")


def _main_end_to_end(args: argparse.Namespace) -> None:
    """The whole command: baseline revision (optional) and this tree, alternating."""
    out_path = Path(args.out) if args.out else OUT.with_name("bench_augment_end_to_end.json")
    outputs = args.outputs or (2 if args.quick else 5)
    variants = [v.strip() for v in args.compress.split(",") if v.strip()]
    load0 = [round(x, 2) for x in os.getloadavg()]
    codes: list[tuple[str, str | None]] = [("this tree", v) for v in variants]
    res: dict = {"case": "end_to_end_one_thread", "outputs_per_command": outputs,
                 "rounds": args.rounds, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        if args.baseline_rev:
            res["revision"] = args.baseline_rev
            res["commit"] = _export_revision(args.baseline_rev, Path(tmp))
            codes.insert(0, ("baseline", None))
        for rnd in range(args.rounds):  # same seeds for every code in a round
            for which, compress in codes:
                label = which if compress is None else f"{which}, compress={compress}"
                r = (_baseline_one_thread(Path(tmp), 5000, outputs, rnd * outputs,
                                          "end_to_end_one_thread")
                     if which == "baseline" else
                     end_to_end_one_thread(5000, outputs, rnd * outputs, compress))
                res["runs"].append({"round": rnd, "code": label, **r})
                print(f"whole command, 5000², {label} (round {rnd}): {r}", flush=True)
    labels = list(dict.fromkeys(r["code"] for r in res["runs"]))
    res["summary"] = {}
    for label in labels:
        runs = [r for r in res["runs"] if r["code"] == label]
        pairs = sum(r["pairs"] for r in runs)
        cpu = sum(r["cpu_seconds_per_pair"] * r["pairs"] for r in runs)
        wall = sum(r["seconds"] for r in runs)
        stages = {k: round(sum(r["cpu_seconds_per_pair_by_stage"][k] * r["pairs"]
                               for r in runs) / pairs, 3)
                  for k in runs[0]["cpu_seconds_per_pair_by_stage"]}
        phases = {k: round(sum(r["cpu_seconds_per_pair_by_phase"][k] * r["pairs"]
                               for r in runs) / pairs, 3)
                  for k in runs[0].get("cpu_seconds_per_pair_by_phase", {})}
        res["summary"][label] = {
            "pairs": pairs, "cpu_seconds_per_pair": round(cpu / pairs, 3),
            "cpu_seconds_per_pair_by_phase": phases,
            "cpu_seconds_per_pair_median_of_runs": round(float(np.median(
                [r["cpu_seconds_per_pair"] for r in runs])), 3),
            "cpu_pairs_per_second": round(pairs / cpu, 3),
            "wall_pairs_per_second": round(pairs / wall, 3),
            "cpu_seconds_per_pair_by_stage": stages,
            "image_mb": round(sum(r["image_mb"] for r in runs) / len(runs), 2),
            "load_average": [r["load_average"] for r in runs]}
    res["machine"] = {"cpus": os.cpu_count(), "load_average_at_start": load0,
                      "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
                      "thread_env": {k: os.environ.get(k) for k in (
                          "OMP_NUM_THREADS", "OPENCV_FOR_THREADS_NUM", "GDAL_NUM_THREADS")},
                      "opencv_threads_while_timed": 1, "geosim_threads_while_timed": 1}
    # issue 13: >= 0.5 pairs/s per single-threaded worker, i.e. <= 2 CPU s per output pair
    res["target_cpu_seconds_per_pair"] = 2.0
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=2) + "\n")
    stage_names = list(next(iter(res["summary"].values()))["cpu_seconds_per_pair_by_stage"])
    print(f"| whole command, 5000² pair, 1 thread | pairs | CPU s/pair | "
          f"{' | '.join(stage_names)} | pairs/s (CPU) | pairs/s (wall) | MB/image | load |")
    print("|---" * (7 + len(stage_names)) + "|")
    for label, r in res["summary"].items():
        name = f"{res['revision']} ({res['commit'][:8]})" if label == "baseline" else label
        st = " | ".join(str(r["cpu_seconds_per_pair_by_stage"][k]) for k in stage_names)
        print(f"| {name} | {r['pairs']} | {r['cpu_seconds_per_pair']} | {st} | "
              f"{r['cpu_pairs_per_second']} | {r['wall_pairs_per_second']} | "
              f"{r['image_mb']} | {', '.join(map(str, r['load_average']))} |")
    phase_names = list(PHASES) + ["rest_of_pipeline_and_command"]
    print(f"\n| CPU s per pair by phase | {' | '.join(phase_names)} |")
    print("|---" * (1 + len(phase_names)) + "|")
    for label, r in res["summary"].items():
        ph = r["cpu_seconds_per_pair_by_phase"]
        print(f"| {label} | {' | '.join(str(ph.get(k, '')) for k in phase_names)} |")
    print(f"results in {out_path}")


if __name__ == "__main__":
    main()
