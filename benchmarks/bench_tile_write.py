"""Benchmark: CPU per 5000 px tile of the tiles step (``write_tile``), before / after.

A 5000 × 5000 RGB aligned raster with a mask (real Brazil pasture imagery mirrored out,
synthetic texture without it) is written once; then ``geosim.prepare.tiles.write_tile``
cuts the whole 5000² window into a tile (read the aligned raster, write the tile COG with
its mask and overviews), in child processes that import either this tree or a baseline
git revision (``git archive``), alternating round by round so both see the same load.
The two trees' tiles are compared: decoded pixels, mask, georeference and tags equal,
``LAYOUT=COG``; file sizes are reported.

Usage: ``python benchmarks/bench_tile_write.py --baseline-rev main [--rounds 3]``;
results to ``benchmarks/results/bench_tile_write.json``.
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

OUT = ROOT / "benchmarks" / "results" / "bench_tile_write.json"

_CHILD = """
import json, sys, time
sys.path.insert(0, {src!r})
import geosim
assert geosim.__file__.startswith({src!r}), geosim.__file__
from affine import Affine
from rasterio.windows import Window
from geosim.prepare.tiles import TileSpec, write_tile
t = Affine(*{transform!r})
spec = TileSpec(0, 0, Window(0, 0, 5000, 5000), t)
c0 = time.process_time()
write_tile({aligned!r}, {dst!r}, spec, tags={{"GEOSIM_TILE_ID": "r000_c000"}})
print(json.dumps({{"cpu_s": time.process_time() - c0}}))
"""


def child(src: Path, aligned: Path, dst: Path, transform: Affine) -> float:
    code = _CHILD.format(src=str(src), aligned=str(aligned), dst=str(dst),
                         transform=tuple(transform)[:6])
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                          text=True, env={**env, "GEOSIM_THREADS": "1"}, cwd=src)
    return json.loads(done.stdout.strip().splitlines()[-1])["cpu_s"]


def same_tile(a: Path, b: Path) -> None:
    with rasterio.open(a) as x, rasterio.open(b) as y:
        assert x.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert y.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        assert np.array_equal(x.read(), y.read()), "decoded pixels differ"
        assert np.array_equal(x.read_masks(1), y.read_masks(1)), "masks differ"
        assert x.transform == y.transform and x.crs == y.crs, "georeference differs"
        assert x.tags() == y.tags(), "tags differ"
        assert len(x.overviews(1)) == len(y.overviews(1)), "overview count differs"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline-rev", default="main")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    from geosim.io.raster import write_geotiff

    tile, source = make_tile(5000)
    mask = np.ones(tile.shape[1:], bool)
    mask[:, :300] = False
    t = Affine(0.05, 0, 300000.0, 0, -0.05, 6200000.0)
    cpu: dict[str, list[float]] = {"baseline": [], "this tree": []}
    loads = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        base_src = d / "baseline"
        base_src.mkdir()
        commit = _export_revision(args.baseline_rev, base_src)
        aligned = d / "aligned.tif"
        write_geotiff(aligned, tile, transform=t, crs="EPSG:32756", mask=mask)
        outs = {"baseline": d / "tile_baseline.tif", "this tree": d / "tile_here.tif"}
        for _ in range(args.rounds):
            loads.append(round(os.getloadavg()[0], 2))
            for which, src in (("baseline", base_src), ("this tree", ROOT)):
                outs[which].unlink(missing_ok=True)
                cpu[which].append(child(src, aligned, outs[which], t))
        same_tile(outs["baseline"], outs["this tree"])
        sizes = {w: p.stat().st_size for w, p in outs.items()}
    res = {"imagery": source, "baseline_revision": args.baseline_rev, "baseline_commit": commit,
           "rounds": args.rounds, "load_average_per_round": loads,
           "identical_decoded_pixels_mask_georef_tags": True,
           "cases": {w: {"cpu_s": [round(x, 3) for x in v], "cpu_s_min": round(min(v), 3),
                         "cpu_s_median": round(statistics.median(v), 3),
                         "file_mb": round(sizes[w] / 1e6, 2)} for w, v in cpu.items()}}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(res, indent=2) + "\n")
    print("| write_tile, 5000² RGB + mask | CPU s (min / median) | file MB |\n|---|---|---|")
    for w, r in res["cases"].items():
        name = f"{args.baseline_rev} ({commit[:8]})" if w == "baseline" else w
        print(f"| {name} | {r['cpu_s_min']} / {r['cpu_s_median']} | {r['file_mb']} |")
    print(f"load average per round: {loads}; identical decoded tiles; "
          f"{OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
