"""Benchmark: CPU to write one 5000 px tile as the tiles step does (``write_tile``), before / after.

A 5000 × 5000 RGB raster (real Brazil pasture imagery mirrored out, synthetic texture
without it) is written once with a full mask and once with a partial one (300 columns
without data, a tile at a flight's edge); child processes that import either this tree or
a baseline git revision (``git archive``) read it and time
``geosim.prepare.tiles.write_tile`` writing it as a tile (the COG with its mask and
overviews), alternating round by round so both see the same load. The two trees' tiles
are compared: decoded pixels, mask, georeference and tags equal (but for
``OPTIONAL_TAGS``), ``LAYOUT=COG``, the same overview sizes; the largest difference between
their overview pixels is reported per level.

Usage: ``python benchmarks/bench_tile_write.py --baseline-rev main [--rounds 3] [--out F]``;
results to ``benchmarks/results/bench_tile_write.json`` or ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_augment import _export_revision  # noqa: E402
from bench_degrade import make_tile  # noqa: E402

from geosim.io.overviews import LEVEL1_TAG  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_tile_write.json"

_CHILD = """
import json, sys, time
sys.path.insert(0, {src!r})
import geosim
assert geosim.__file__.startswith({src!r}), geosim.__file__
from types import SimpleNamespace as NS
import rasterio
from affine import Affine
from geosim.prepare.tiles import write_tile
with rasterio.open({aligned!r}) as ds:
    img, valid = ds.read(), ds.dataset_mask() > 0
    reader = NS(count=ds.count, dtype=ds.dtypes[0], crs=ds.crs, descriptions=ds.descriptions,
                colorinterp=ds.colorinterp)
task = NS(tile=NS(transform=Affine(*{transform!r})), tags={{"GEOSIM_TILE_ID": "r000_c000"}},
          compression="deflate")
c0 = time.process_time()
write_tile(reader, task, {dst!r}, img, valid)
print(json.dumps({{"cpu_s": time.process_time() - c0}}))
"""


def child(src: Path, aligned: Path, dst: Path, transform: Affine) -> float:
    """CPU seconds of ``write_tile`` in a child importing the geosim code at ``src``."""
    code = _CHILD.format(src=str(src), aligned=str(aligned), dst=str(dst),
                         transform=tuple(transform)[:6])
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, env={**env, "GEOSIM_THREADS": "1"}, cwd=src)
    return json.loads(done.stdout.strip().splitlines()[-1])["cpu_s"]


#: Tags one tree may write and the other not: the binomial first overview's (28 Nov).
OPTIONAL_TAGS = {LEVEL1_TAG}


def same_tile(a: Path, b: Path) -> list[int]:
    """Check two tiles decode alike; return the largest pixel difference (DN) per overview
    level (the first differs where one tree writes the binomial level, tagged)."""
    with rasterio.open(a) as x, rasterio.open(b) as y:
        assert x.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert y.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert np.array_equal(x.read(), y.read()), "decoded pixels differ"
        assert np.array_equal(x.read_masks(1), y.read_masks(1)), "masks differ"
        assert x.transform == y.transform and x.crs == y.crs, "georeference differs"
        tx, ty = x.tags(), y.tags()
        assert set(tx) ^ set(ty) <= OPTIONAL_TAGS, "tags differ"
        assert all(tx[k] == ty[k] for k in set(tx) & set(ty)), "tags differ"
        assert x.overviews(1) == y.overviews(1), "overview sizes differ"
        levels = len(x.overviews(1))
    per_level = []
    for i in range(levels):
        with rasterio.open(a, overview_level=i) as x, rasterio.open(b, overview_level=i) as y:
            assert np.array_equal(x.dataset_mask(), y.dataset_mask()), "overview masks differ"
            per_level.append(int(np.abs(x.read().astype(int) - y.read().astype(int)).max()))
    return per_level


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-rev", default="main")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    from geosim.io.raster import write_geotiff

    tile, source = make_tile(5000)
    masks = {"full": np.ones(tile.shape[1:], bool)}
    masks["partial"] = masks["full"].copy()
    masks["partial"][:, :300] = False
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    trees = ("baseline", "this tree")
    cpu = {(m, w): [] for m in masks for w in trees}
    loads, cases = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        base_src = d / "baseline"
        base_src.mkdir()
        commit = _export_revision(args.baseline_rev, base_src)
        aligned = {m: write_geotiff(d / f"aligned_{m}.tif", tile, transform=t,
                                    crs="EPSG:32756", mask=mask) for m, mask in masks.items()}
        outs = {(m, w): d / f"tile_{m}_{w.replace(' ', '_')}.tif" for m, w in cpu}
        for _ in range(args.rounds):
            loads.append(round(os.getloadavg()[0], 2))
            for m in masks:
                for which, src in zip(trees, (base_src, ROOT), strict=True):
                    outs[m, which].unlink(missing_ok=True)
                    cpu[m, which].append(child(src, aligned[m], outs[m, which], t))
        for m in masks:
            per_level = same_tile(outs[m, "baseline"], outs[m, "this tree"])
            cases[m] = {"overview_max_diff_dn": max(per_level, default=0),
                        "overview_max_diff_dn_per_level": per_level, **{
                w: {"cpu_s": [round(x, 3) for x in cpu[m, w]],
                    "cpu_s_min": round(min(cpu[m, w]), 3),
                    "cpu_s_median": round(statistics.median(cpu[m, w]), 3),
                    "file_mb": round(outs[m, w].stat().st_size / 1e6, 2)} for w in trees}}
    res = {"imagery": source, "baseline_revision": args.baseline_rev, "baseline_commit": commit,
           "rounds": args.rounds, "load_average_per_round": loads,
           "identical_full_resolution_pixels_mask_georef_tags_overview_sizes_and_masks": True,
           "tags_allowed_to_differ": sorted(OPTIONAL_TAGS),
           "cases": cases}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print("| write_tile, 5000² RGB + mask | CPU s (min / median) | file MB |\n|---|---|---|")
    for m, case in cases.items():
        for w in trees:
            r = case[w]
            name = f"{args.baseline_rev} ({commit[:8]})" if w == "baseline" else w
            print(f"| {m}: {name} | {r['cpu_s_min']} / {r['cpu_s_median']} | {r['file_mb']} |")
        print(f"{m}: overview pixels differ by at most "
              f"{case['overview_max_diff_dn_per_level']} DN per level")
    print(f"load average per round: {loads}; identical full-resolution tiles; {args.out}")


if __name__ == "__main__":
    main()
