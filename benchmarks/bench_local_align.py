"""Benchmark of local co-registration (``align_model = "local"``) against truth.

Case (``tests/warp_case.py``): the real Brazil pasture orthomosaic (EPSG:3395, 0.1 m) is the
reference, with its south-east corner cut away; the moving flight shows the same ground on
an EPSG:4326 grid whose stated position is wrong by a similarity (0.35°, scale 1.004,
(0.63, −0.41) m) plus a smooth displacement of up to ``--amplitude-px`` per axis. The truth
mapping is known analytically, so the residual is measured against it, not against the
code: for every 4th aligned pixel ``p`` the error is ``|W(s) − p|`` where ``s`` is where the
pipeline samples the moving flight. Also measured with scikit-image's phase correlation on
the aligned rasters (256 px windows).

Compared in the same run:

* ``similarity`` — the paper's global model (geosim default);
* ``local`` — geosim's local model (the similarity, then the smooth field);
* ``arosics-style`` — translation-only local shifts in the way AROSICS's local mode works,
  implemented here (arosics itself needs a GDAL/py_tools_ds stack that is not installed):
  tie points from phase correlation in the same 256 px / 128 px windows on the flight as
  stated (no global similarity), rejected by confidence only, interpolated by an exact
  thin-plate spline (GDAL's ``-tps`` warp), extrapolated wherever the flight has data.

The local run is also compared with one bicubic remap of the original moving file through
the composed mapping (``vs_single_remap_oracle``, grey levels): the local model resamples
each flight once, so only rounding is left; and no ``grid/`` copy is written.

Also the sample site (``data/samples``): the local check (residual window shifts, geosim's
kernel) after the similarity and after the local model.

Usage::

    python benchmarks/bench_local_align.py [--amplitude-px 2.5] [--keep DIR]

Writes ``benchmarks/results/bench_local_align.json`` and prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results" / "bench_local_align.json"
REALDATA = Path(os.environ.get("GEOSIM_REALDATA", ROOT.parent / "shared" / "realdata"))


def run_steps(site_path: Path, out: Path) -> dict[str, float]:
    """grid, footprints, align; seconds per step."""
    from geosim.config import load_site
    from geosim.prepare.steps import run_align, run_footprints, run_grid

    site = load_site(site_path)
    times = {}
    for step in (run_grid, run_footprints, run_align):
        t0 = time.perf_counter()
        step(site, out)
        times[step.__name__.removeprefix("run_")] = time.perf_counter() - t0
    return times


def arosics_style(case, out: Path) -> dict[str, float]:
    """Translation-only local tie points + exact TPS on the stated flight (see module doc)."""
    import rasterio
    from affine import Affine
    from scipy.interpolate import RBFInterpolator

    from geosim.align.field import LOW_CONFIDENCE, measure_window_shifts
    from geosim.prepare.onewarp import ComposedWarp, read_grey_on_grid
    from geosim.prepare.steps import read_grid
    from tests.warp_case import GSD_M

    doc = json.loads((out / "alignment.json").read_text())
    aw = doc["aligned_grid"]["window_px"]
    at = Affine(*doc["aligned_grid"]["transform"])
    from rasterio.windows import Window

    win = Window(aw["col_off"], aw["row_off"], aw["width"], aw["height"])
    t0 = time.perf_counter()
    # both flights on the site grid as stated (no similarity), read through the one warp
    grid = read_grid(out)
    ref, rv = read_grey_on_grid(ComposedWarp.for_flight(case.ref_path, grid.crs,
                                                        grid.uav_transform), win)
    mov, mv = read_grey_on_grid(ComposedWarp.for_flight(case.mov_path, grid.crs,
                                                        grid.uav_transform), win)
    s = measure_window_shifts(ref, mov, valid=rv & mv, window_px=256, step_px=128)
    ok = np.isfinite(s.dx_px) & (s.confidence >= 0.1)
    pts = np.stack([s.y_px[ok], s.x_px[ok]], axis=1)
    tps = RBFInterpolator(pts, np.stack([s.dx_px[ok], s.dy_px[ok]], axis=1),
                          kernel="thin_plate_spline", smoothing=0.0, degree=1)
    rows, cols = ref.shape
    r, c = np.mgrid[0:rows:4, 0:cols:4]
    d = tps(np.stack([r.ravel(), c.ravel()], axis=1).astype(float)).reshape(*r.shape, 2)
    elapsed = time.perf_counter() - t0
    # sample point of the stated flight for aligned pixel p: p + d(p) (identity correction)
    px, py = at * (c + 0.5, r + 0.5)
    sx, sy = px + d[..., 0] * GSD_M, py - d[..., 1] * GSD_M
    tx, ty = case.truth(sx, sy)
    err = np.hypot(tx - px, ty - py) / GSD_M
    with rasterio.open(out / "aligned" / "REF.tif") as ds:
        ref_ok = (ds.read_masks(1) > 0)[::4, ::4]
    mov_ok = mv[::4, ::4]
    both, only = ref_ok & mov_ok, ~ref_ok & mov_ok
    k = 64
    worst = max(float(err[i:i + k, j:j + k][both[i:i + k, j:j + k]].mean())
                for i in range(0, both.shape[0] - k + 1, k)
                for j in range(0, both.shape[1] - k + 1, k)
                if both[i:i + k, j:j + k].mean() >= 0.5)
    return {"median_px": float(np.median(err[both])), "worst_window_px": worst,
            "beyond_reference_max_px": float(err[only].max()) if only.any() else None,
            "n_tie_points": int(ok.sum()), "n_low_confidence": int((s.status == LOW_CONFIDENCE)
                                                                   .sum() + (~ok).sum()),
            "time_s": elapsed}


def resampled_once(case, out: Path, n: int = 512) -> dict[str, float]:
    """Grey difference between the aligned moving flight and ONE bicubic remap of the
    original file through the composed mapping (``tests.warp_case.single_remap_oracle``),
    over a central ``n`` px crop: what a second interpolation would add shows here."""
    import rasterio
    from rasterio.windows import Window

    from tests.warp_case import single_remap_oracle

    with rasterio.open(out / "aligned" / "MOV.tif") as ds:
        r0, c0 = ds.height // 2 - n // 2, ds.width // 2 - n // 2 - 300
        got = ds.read([1, 2, 3], window=Window(c0, r0, n, n)).astype(np.float32).mean(axis=0)
        ok = ds.read_masks(1, window=Window(c0, r0, n, n)) > 0
    diff = np.abs(got - single_remap_oracle(case, out, r0, c0, n))[ok]
    return {"mean_abs_grey": float(diff.mean()), "max_abs_grey": float(diff.max()),
            "crop_px": n}


def sample_site(tmp: Path) -> dict[str, dict]:
    """Local check of the sample site after the similarity and after the local model."""
    src = ROOT / "data" / "samples" / "site.toml"
    out = {}
    for model in ("similarity", "local"):
        text = src.read_text().replace("align_window_px = 1024",
                                       f'align_window_px = 1024\nalign_model = "{model}"')
        base = src.parent
        for key in ("flights/", "labels/", "satellite/satellite", "paddocks.geojson"):
            text = text.replace(f'"{key}', f'"{base}/{key}')
        site = tmp / f"sample_{model}.toml"
        site.write_text(text)
        times = run_steps(site, tmp / f"sample_{model}")
        doc = json.loads((tmp / f"sample_{model}" / "alignment.json").read_text())
        out[model] = {"align_s": times["align"],
                      **{f: {k: doc["local_check"][f][k] for k in
                             ("median_shift_px", "p90_shift_px", "max_shift_px")}
                         for f in doc["local_check"]}}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--amplitude-px", type=float, default=2.5)
    ap.add_argument("--keep", type=Path, help="keep the runs in this folder")
    args = ap.parse_args(argv)
    if not (REALDATA / "brazil_pasture_10cm_epsg3395.tif").is_file():
        print(f"real imagery not found at {REALDATA}; set GEOSIM_REALDATA", file=sys.stderr)
        return 2
    from tests.warp_case import evaluate, make_case

    tmp_ctx = tempfile.TemporaryDirectory() if args.keep is None else None
    tmp = Path(tmp_ctx.name) if tmp_ctx else args.keep
    res: dict = {"case": {"amplitude_px": args.amplitude_px, "reference": "EPSG:3395",
                          "moving": "EPSG:4326", "gsd_m": 0.1},
                 "machine": {"python": platform.python_version(), "cpus": os.cpu_count()}}
    for model in ("similarity", "local"):
        folder = tmp / model
        case = make_case(REALDATA, folder, amplitude_px=args.amplitude_px, align_model=model)
        times = run_steps(case.site_path, folder / "run")
        r = evaluate(case, folder / "run")
        res[model] = {**r.__dict__, "align_s": times["align"]}
        if model == "local":
            doc = json.loads((folder / "run" / "alignment.json").read_text())
            rec = doc["flights"]["MOV"]["local_field"]
            res[model]["windows"] = rec["fit"]["n_windows"]
            res[model]["fallback_node_fraction"] = rec["fallback"]["node_fraction"]
            res[model]["vs_single_remap_oracle"] = resampled_once(case, folder / "run")
            res[model]["grid_copies_written"] = sorted(
                p.name for p in (folder / "run" / "grid").glob("*.tif"))
        if model == "similarity":
            res["arosics_style"] = arosics_style(case, folder / "run")
    res["sample_site"] = sample_site(tmp)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(res, indent=2) + "\n")
    print("| model | median (px) | worst 256 px window (px) | beyond reference, max (px) "
          "| skimage median / worst (px) | time (s) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name in ("similarity", "local", "arosics_style"):
        r = res[name]
        img = (f"{r['image_median_px']:.3f} / {r['image_worst_px']:.3f}"
               if "image_median_px" in r else "—")
        t = r.get("align_s", r.get("time_s"))
        print(f"| {name} | {r['median_px']:.3f} | {r['worst_window_px']:.3f} | "
              f"{r['beyond_reference_max_px']:.2f} | {img} | {t:.1f} |")
    print(json.dumps(res["sample_site"], indent=1))
    if tmp_ctx:
        tmp_ctx.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
