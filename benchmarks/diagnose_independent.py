"""Benchmark: the diagnosis, blind, on scenes made by an independent implementation.

The "real" satellite scenes come from ``benchmarks/diagnose_generator.py``, which
imports nothing from geosim (each effect written again from its physics, blur applied
on the 0.05 m grid before sampling). Cases come from every real image in
``../shared/realdata`` and the sample site, phi = 10, Q from 0.8 to 4.5, 0-3 effects,
every 5th case a control. Seeds 1000 + i. Development half: seeds 1000-2535 (thresholds are
tuned on these only; each earlier round's validation half was seen in its final report, so
it joined development). Validation half (round 48, fresh): the 32 seeds 2536-2567, run only
for the final report. The diagnosis sees the
UAV image and the scene, calibrates Q by Laplacian variance, and is scored by the
benchmark's own measures (exact effect names; its own spectral error). Each row also
records the tool's ``detection_limits`` (the blurs it states would be absorbed into Q at
its delivered Q — isotropic, and since round 15 anisotropic in any direction — and the
native pitch below which it states a resampling's aliasing unresolved); the score adds
the recall over the true effects it did not declare untestable, and how many it declared
untestable but found anyway.

Development extension (tuning allowed): seeds 5000-5999, cases with a forced effect set and
Q range drawn from ``EXTENSION_RECIPES`` (case k: seed 5000 + offset + k, recipe k mod its
length; offsets in ``EXTENSION_SEED_OFFSET``),
for failure kinds the development half holds few of. They never change the halves' cases.

Run: python benchmarks/diagnose_independent.py   (both halves; writes their results file)
     python benchmarks/diagnose_independent.py [--cases N] [--only development|validation]
     [--indices I,J] --out FILE
(part of the halves, written elsewhere, then --merge'd; --cases N: the first N development
cases; the validation half is always all 32.)
     python benchmarks/diagnose_independent.py --extension noise|isoblur [--extension-cases K]
     --out /tmp/x.json   (the extension only)
     python benchmarks/diagnose_independent.py --merge OLD.json NEW.json [--out FILE]
     (one results file from several runs: rows by case, later files win; each row's split
     from its seed; rows from before 24 Nov get the detection limits the tool states at
     their delivered Q)
     python benchmarks/diagnose_independent.py --variants [--only ...] [--indices ...] --out FILE
     (the same cases rendered with other implementation choices, drawn per case: the
     atmosphere's MTF exponent, the resampling's cubic kernel, the JPEG encoder's chroma
     subsampling, the shift's interpolation; ``diagnose_generator.draw_variant``)
     python benchmarks/diagnose_independent.py --flight [--only ...] [--indices ...] --out FILE
     (the same cases as surveyed flights deliver them: the UAV image 0 outside a footprint
     turned against the grid whose bounding box is the scene, with its validity mask; a
     misregistration also a rotation and scale; ``diagnose_generator.draw_flight``. The
     spectral errors are over the blocks the flight imaged)
     python benchmarks/diagnose_independent.py --indices I,J,... --sat-px 384 --out /tmp/y.json
     (the same development cases on larger scenes: how much the scene's size limits the
     diagnosis; sources smaller than the scene give what they hold, so pick the indices of
     the large ones, ``--large-sources`` prints them)
Writes benchmarks/results/diagnose_independent.json and prints markdown tables.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# this checkout's geosim only where none is importable: PYTHONPATH=<another checkout> then
# runs that checkout's code with this benchmark (before round 43 this checkout was put
# first, so such runs silently used its own code)
if importlib.util.find_spec("geosim") is None:
    sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

REAL = gen.REALDATA
#: the halves' results (128 px scenes); other runs write elsewhere
HALVES_FILE = ROOT / "benchmarks" / "results" / "diagnose_independent.json"
SEEDS_NOTE = (f"1000 + i; development 1000-{gen.VALIDATION_FIRST_SEED - 1}, validation "
              f"{gen.VALIDATION_FIRST_SEED}-{gen.VALIDATION_LAST_SEED} (round 48)")
N_VALIDATION_LAST = 1567
#: case indices (seed 1000 + i) of the two halves (round 48: development 0-1535,
#: validation 1536-1567)
DEVELOPMENT = [i for i in range(N_VALIDATION_LAST + 1) if not gen.is_validation_seed(1000 + i)]
VALIDATION = [i for i in range(N_VALIDATION_LAST + 1) if gen.is_validation_seed(1000 + i)]
N_CASES = len(DEVELOPMENT)
#: side of the halves' scenes on the 0.5 m grid, px (64 m)
SAT_PX = 128
#: development extension recipes: (forced effects, Q range or None for the full range).
#: "noise": sensor noise under JPEG and with moved objects at low Q (the validation
#: half's largest group of misses), and the same without noise (false-claim checks).
EXTENSION_RECIPES: dict[str, list[tuple[tuple[str, ...], tuple[float, float] | None]]] = {
    "noise": [
        (("sensor_noise", "compression"), None),
        (("sensor_noise", "scene_change"), (0.8, 1.5)),
        (("sensor_noise", "compression", "scene_change"), None),
        (("sensor_noise", "compression", "motion_smear"), None),
        (("compression",), None),
        (("scene_change",), (0.8, 1.5)),
    ],
    # "isoblur": the isotropic roll-offs the validation half missed at high Q (detector
    # under a wide optical PSF, alone, with noise, with resampling; resampling with noise;
    # atmosphere at high Q and at low Q with resampling and noise), and false-claim checks
    # at high Q (the paper's model alone, noise alone)
    "isoblur": [
        (("detector_integration",), (2.0, 4.5)),
        (("detector_integration", "sensor_noise"), (2.0, 4.5)),
        (("detector_integration", "resampling"), (1.5, 4.5)),
        (("resampling", "sensor_noise"), None),
        (("atmospheric_blur",), (2.5, 4.5)),
        (("atmospheric_blur", "resampling", "sensor_noise"), (0.8, 1.5)),
        ((), (2.0, 4.5)),
        (("sensor_noise",), (2.0, 4.5)),
    ],
}
#: first seed of each recipe's cases (5000 + offset + k), so recipes do not share seeds
EXTENSION_SEED_OFFSET = {"noise": 0, "isoblur": 200}


def diagnose_case(case: gen.Case) -> dict[str, Any]:
    """Run the diagnosis as a user's flight runs it (the flight's pixels: LV baseline, then
    diagnose; ``geosim.diagnose.grids.diagnose_pixels``) and score it."""
    from affine import Affine
    from rasterio.crs import CRS

    from geosim.diagnose.grids import FlightPixels, diagnose_pixels

    t0 = time.time()
    # a UTM grid at the product's 0.5 m (the place does not enter the diagnosis)
    pixels = FlightPixels.of_arrays(case.uav, case.real, crs=CRS.from_epsg(32755),
                                    sat_transform=Affine(gen.PHI * gen.FINE_GSD_M, 0.0, 0.0,
                                                         0.0, -gen.PHI * gen.FINE_GSD_M,
                                                         0.0),
                                    phi=gen.PHI, uav_valid=case.uav_valid)
    d = diagnose_pixels(pixels, phi=gen.PHI)
    s = d.summary
    claimed = {e["name"]: e["params"] for e in s["effects"]}
    alts = {e["name"]: e.get("alternatives", e.get("indistinguishable_from", []))
            for e in s["effects"]}
    # the benchmark's own measure, over the blocks the flight imaged
    pv = case.product_valid
    return {"case": case.name, "seed": case.seed, "split": case.split, "source": case.source,
            "q_true": case.q, "q_base": s["baseline"]["q"], "q_refined": s["refined"]["q"],
            "truth": case.truth, "claimed": claimed, "alternatives": alts,
            "claimed_gain": {e["name"]: e.get("heldout_gain") for e in s["effects"]},
            "detection_limits": s["detection_limits"],
            # a scene change's second pass on the ground with the moved objects painted in
            "scene_change_refit": {k: v for k, v in s.get("scene_change_refit", {}).items()
                                   if k != "note"},
            # both simulations as delivered: whole DN, like the scene
            "se_base": gen.spectral_error(np.rint(d.baseline), case.real, valid=pv),
            "se_refined": gen.spectral_error(np.rint(d.refined), case.real, valid=pv),
            "tool_spectral_error": [s["baseline"]["spectral_error"],
                                    s["refined"]["spectral_error"]],
            "seconds": time.time() - t0,
            **({"variant": case.variant} if case.variant is not None else {}),
            **({"flight": case.flight, "imaged_frac": float(np.mean(pv))}
               if case.flight is not None else {})}


def extension_kw(recipe: str, k: int) -> dict[str, Any]:
    """make_case keywords of development-extension case ``k`` (seed 5000 + offset + k)."""
    recipes = EXTENSION_RECIPES[recipe]
    effects, q_range = recipes[k % len(recipes)]
    return {"base_seed": gen.EXTENSION_SEEDS[0] + EXTENSION_SEED_OFFSET[recipe],
            "effects": effects, "q_range": q_range}


def run(indices: list[int], sources: list[gen.Source],
        case_kw: Callable[[int], dict[str, Any]] | None = None) -> list[dict[str, Any]]:
    rows = []
    for i in indices:
        t0 = time.time()
        case = gen.make_case(i, sources, **(case_kw(i) if case_kw else {}))
        try:
            row = diagnose_case(case)
        except Exception as exc:  # a crash is a failure of the tool, recorded as such
            row = {"case": case.name, "seed": case.seed, "split": case.split,
                   "source": case.source, "q_true": case.q, "q_base": float("nan"),
                   "q_refined": float("nan"), "truth": case.truth, "claimed": {},
                   "error": f"{type(exc).__name__}: {exc}", "se_base": float("nan"),
                   "se_refined": float("nan")}
        row["seconds_total"] = time.time() - t0
        rows.append(row)
        ok = "ok" if set(row["truth"]) == set(row["claimed"]) else "MISS"
        print(f"{case.name} [{case.split[:3]}] {case.source:18s} Q {case.q:.2f} "
              f"truth {sorted(case.truth)} claimed {sorted(row['claimed'])} {ok} "
              f"se {row['se_base']:.3f}->{row['se_refined']:.3f} "
              f"({row['seconds_total']:.1f}s)", flush=True)
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    lines = ["| case | half | source | Q true / LV | truth | claimed | spectral error base → "
             "refined |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['split'][:3]} | {r['source']} | {r['q_true']:.2f} / "
                     f"{r['q_base']:.2f} | {', '.join(sorted(r['truth'])) or '—'} | "
                     f"{', '.join(sorted(r['claimed'])) or '—'} | {r['se_base']:.3f} → "
                     f"{r['se_refined']:.3f} |")
    return "\n".join(lines)


def fmt_summary(name: str, s: dict[str, Any]) -> str:
    return (f"{name}: precision {s['precision']:.2f} ({s['tp']} of {s['tp'] + s['fp']}), "
            f"recall {s['recall']:.2f} ({s['tp']} of {s['tp'] + s['fn']}); families "
            f"{s['family_precision']:.2f} / {s['family_recall']:.2f}; controls clean "
            f"{s['controls_clean']}/{s['n_controls']}; refined ≤ ½ baseline "
            f"{s['refined_le_half_baseline']}/{s['effect_cases']}; refined above baseline "
            f"{s['refined_above_baseline']}/{s['n_cases']}; recall over effects not stated "
            f"untestable {s['recall_testable']:.2f} ({s['stated_untestable']} stated "
            f"untestable, {s['stated_untestable_found']} of them found; limits in "
            f"{s['rows_with_limits']}/{s['n_cases']} rows); effects stated testable "
            f"found {s['stated_testable_found']}/{s['stated_testable']} ("
            + ", ".join(f"{k} {f}/{t}" for k, (t, f) in
                        sorted(s.get("stated_testable_by_effect", {}).items())) + ")")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=N_CASES,
                    help="number of development cases (the first N)")
    ap.add_argument("--only", choices=("development", "validation"))
    ap.add_argument("--indices", type=lambda t: [int(v) for v in t.split(",")],
                    help=f"comma-separated development case indices (0-{DEVELOPMENT[-1]}), "
                         "e.g. to rerun the failures")
    ap.add_argument("--extension", choices=sorted(EXTENSION_RECIPES),
                    help="run only the development extension (seeds 5000-5999) with these "
                         "recipes")
    ap.add_argument("--extension-cases", type=int, default=24,
                    help="number of extension cases (seeds 5000 ...)")
    ap.add_argument("--sat-px", type=int, default=SAT_PX,
                    help=f"scene side on the 0.5 m grid, px (default {SAT_PX}; any other "
                         "value only with --indices and --out elsewhere)")
    ap.add_argument("--variants", action="store_true",
                    help="render each case with its drawn implementation choices "
                         "(diagnose_generator.draw_variant); needs --out elsewhere")
    ap.add_argument("--flight", action="store_true",
                    help="the real-flight form: each case's UAV image with a nodata rim "
                         "around its footprint and its misregistration also a rotation and "
                         "scale (diagnose_generator.draw_flight); needs --out elsewhere")
    ap.add_argument("--large-sources", type=int, metavar="PX",
                    help="print the development indices whose source holds a PX-pixel scene "
                         "and exit")
    ap.add_argument("--merge", nargs="+", type=Path, metavar="FILE",
                    help="merge these results files (rows by case, later files win) into "
                         "--out and exit")
    ap.add_argument("--out", default=str(HALVES_FILE))
    args = ap.parse_args()
    if args.merge:
        return merge(args.merge, args.out)
    halves_file = Path(args.out).resolve() == HALVES_FILE.resolve()
    if args.sat_px != SAT_PX and (not args.indices or halves_file):
        sys.exit("--sat-px: give --indices and --out (the halves' results file holds "
                 f"{SAT_PX} px scenes only)")
    if args.variants and halves_file:
        sys.exit("--variants: give --out (the halves' results file holds the default "
                 "implementation only)")
    if args.flight and halves_file:
        sys.exit("--flight: give --out (the halves' results file holds whole-window "
                 "scenes only)")
    if halves_file and (args.only or args.indices or args.cases != N_CASES):
        sys.exit("--only, --indices and --cases run part of the halves: give --out, then "
                 "--merge that file into the halves' results file")
    sources = gen.default_sources()
    if not sources:
        sys.exit(f"no real images under {REAL}; set GEOSIM_REALDATA")
    if args.large_sources:
        big = {s.name for s in sources if gen.source_sat_px(s) >= args.large_sources}
        print(",".join(str(i) for i in DEVELOPMENT
                       if gen.source_of(i, sources).name in big))
        return None
    if args.extension:
        n_ext = (gen.EXTENSION_SEEDS[1] - gen.EXTENSION_SEEDS[0] + 1
                 - EXTENSION_SEED_OFFSET[args.extension])
        if not 0 < args.extension_cases <= n_ext:
            sys.exit(f"--extension-cases: 1-{n_ext}")
        if halves_file:
            sys.exit("--extension: give --out (the halves' results file is not overwritten)")
        recipe = args.extension
        return _write(args.out, run(list(range(args.extension_cases)), sources,
                                    lambda k: extension_kw(recipe, k)),
                      sources, time.time(), f"extension '{recipe}': "
                      f"{gen.EXTENSION_SEEDS[0] + EXTENSION_SEED_OFFSET[recipe]} + k")
    dev = DEVELOPMENT[:args.cases]
    idx = {"development": dev, "validation": VALIDATION}.get(args.only, dev + VALIDATION)
    if args.indices:
        if set(args.indices) - set(DEVELOPMENT):
            sys.exit(f"--indices: development cases only (0-{DEVELOPMENT[-1]})")
        idx = args.indices
    t0 = time.time()
    print(f"geosim from {geosim_location()}", flush=True)
    kw: dict[str, Any] = {}
    if args.sat_px != SAT_PX:
        kw["sat_px"] = args.sat_px
    if args.variants:
        kw["variants"] = True
    if args.flight:
        kw["flight"] = True
    _write(args.out, run(idx, sources, (lambda k: kw) if kw else None), sources, t0,
           SEEDS_NOTE, sat_px=args.sat_px, variants=args.variants, flight=args.flight)


def geosim_location() -> str:
    """The folder of the geosim package this run imports (which checkout's code ran)."""
    import geosim

    return str(Path(geosim.__file__).resolve().parent)


def merge(files: list[Path], out: str) -> None:
    """One results file from several runs of this benchmark (the halves at 128 px).

    Rows are taken by case name, later files replacing earlier ones; each row's split is
    recomputed from its seed (:func:`gen.is_validation_seed`), so a past validation half
    becomes development when a new one is drawn. Rows written before the diagnosis stated
    its detection limits (24 Nov) get the ones it states at their delivered Q (the same
    function of that Q, :func:`geosim.diagnose.detection_limits.detection_limits_json`).
    """
    from geosim.diagnose.detection_limits import detection_limits_json

    rows: dict[str, dict[str, Any]] = {}
    notes = []
    for f in files:
        doc = json.loads(f.read_text())
        if doc.get("setup", {}).get("sat_px", SAT_PX) != SAT_PX:
            sys.exit(f"--merge: {f} holds {doc['setup']['sat_px']} px scenes, not the "
                     f"halves' {SAT_PX} px")
        if doc.get("setup", {}).get("variants") or any("variant" in r for r in doc["cases"]):
            sys.exit(f"--merge: {f} holds cases rendered with implementation variants, not "
                     "the halves' default implementation")
        if doc.get("setup", {}).get("flight") or any("flight" in r for r in doc["cases"]):
            sys.exit(f"--merge: {f} holds real-flight-form cases, not the halves' "
                     "whole-window scenes")
        notes.append(f"{f.name}: {len(doc['cases'])} rows")
        rows.update({r["case"]: r for r in doc["cases"]})
    for r in rows.values():
        r["split"] = "validation" if gen.is_validation_seed(r["seed"]) else "development"
        if "detection_limits" not in r and np.isfinite(r["q_refined"]):
            r["detection_limits"] = detection_limits_json(float(r["q_refined"]))
            r["detection_limits_restated"] = True
    ordered = sorted(rows.values(), key=lambda r: r["seed"])
    sources = gen.default_sources()
    # the file's seconds_total: the rows' own (not the merge's)
    t0 = time.time() - sum(r.get("seconds_total", 0.0) for r in ordered)
    _write(out, ordered, sources, t0, SEEDS_NOTE,
           note="merged by --merge from " + "; ".join(notes))


def _write(path: str, rows: list[dict[str, Any]], sources: list[gen.Source], t0: float,
           seeds: str, sat_px: int = SAT_PX, note: str | None = None,
           variants: bool = False, flight: bool = False) -> None:
    halves = {h: gen.score([r for r in rows if r["split"] == h])
              for h in ("development", "validation", "extension")
              if any(r["split"] == h for r in rows)}
    out = {"halves": halves, "cases": rows, "seconds_total": time.time() - t0,
           "setup": {"geosim": geosim_location(), "phi": gen.PHI, "q_range": gen.Q_RANGE,
                     "ranges": gen.RANGES,
                     "sources": [{"name": s.name, "gsd_m": s.gsd_m, "note": s.note}
                                 for s in sources],
                     "n_cases": len(rows), "sat_px": sat_px, "seeds": seeds,
                     "variants": ({"choices": gen.VARIANT_CHOICES, "default":
                                   gen.DEFAULT_VARIANT} if variants else False),
                     "flight": {"ranges": gen.FLIGHT_RANGES} if flight else False,
                     "extension_recipes": {k: [[list(e), q] for e, q in v]
                                           for k, v in EXTENSION_RECIPES.items()}}}
    if note:
        out["note"] = note
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=1, default=float))
    print("\n" + table(rows) + "\n")
    for h, s in halves.items():
        print(fmt_summary(h, s))
    print(f"{time.time() - t0:.0f} s")


if __name__ == "__main__":
    main()
