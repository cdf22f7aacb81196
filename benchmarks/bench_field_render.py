"""Speed of the diagnosis' renders under a shift + rotation + scale misregistration (round 36).

Where the registration is a field (rotation and scale as well as a shift: the sample
site's flights), round 35 moved every *sampled* candidate render by a cubic-spline warp.
Since round 36 the UAV image is warped once on the fine grid, before the optics
(:meth:`geosim.diagnose.simulate.QSimulator.warped`), and every render comes out moved.
Timed per candidate, both ways, on a generator scene (haze, sensor noise) with the models
the pixel scans try (a resampling at a new pitch and native-grid phase; a motion smear of
a new length), each rendered as the scans render it
(:func:`geosim.diagnose.grey_render.grey_expected`):

* ``sampled``: the registration without a moved simulator (round 35: a warp per render);
* ``fine``: the registration with the warped simulator (its one-off warp of the fine
  image timed apart, ``warp_once_s``).

The two renders differ (the sampled warp moves the aliased content by the wrong phase:
``tests/test_diagnose_field_warp.py`` measures which is right against OpenCV); their
largest difference is reported for scale. One thread (``OMP_NUM_THREADS=1`` etc. set
before numpy loads).

Run: ``python benchmarks/bench_field_render.py [--sat-px 128 192] [--renders 40]``;
results to ``benchmarks/results/bench_field_render.json``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_grey_render import TRUTH, field_registration, time_renders  # noqa: E402

from geosim.diagnose.grey_render import grey_expected  # noqa: E402
from geosim.diagnose.model import ForwardModel, Registration  # noqa: E402
from geosim.physics.geometry import affine_field  # noqa: E402
from tests.generator_cases import scene_inputs  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_field_render.json"


def candidates(reg: Registration, n: int, kind: str) -> list[ForwardModel]:
    """``n`` candidates of a pixel scan: resampling pitches and phases, or smear lengths."""
    rng = np.random.default_rng(1)
    out = []
    for _ in range(n):
        if kind == "resampling":
            pitch = float(rng.uniform(1.15, 2.0))
            out.append(ForwardModel(
                q=1.6, blur={"resampling": {"native_pitch_px": pitch, "cubic_a": -0.5}},
                registration=reg, native_phase_px=(float(rng.uniform(0, pitch)),
                                                   float(rng.uniform(0, pitch)))))
        else:
            out.append(ForwardModel(q=1.6, blur={"motion_smear": {
                "length_px": float(rng.uniform(0.8, 3.0)), "direction_deg": 30.0}},
                registration=reg))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sat-px", type=int, nargs="+", default=[128, 192])
    ap.add_argument("--renders", type=int, default=40)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    rows = []
    for sat_px in args.sat_px:
        inp, _ = scene_inputs(TRUTH, 1.6, 7, sat_px)
        sampled = field_registration(inp.grey.shape)
        t0 = time.perf_counter()
        warped = inp.simulate.warped(affine_field(*sampled.field_px))
        warp_once = time.perf_counter() - t0
        fine = replace(sampled, presampled=warped)
        for kind in ("resampling", "motion_smear"):
            old = candidates(sampled, args.renders, kind)
            new = candidates(fine, args.renders, kind)
            grey_expected(inp, old[0])   # one-off caches (the one-band simulators), untimed
            grey_expected(inp, new[0])
            t_old, a = time_renders(lambda m, i=inp: grey_expected(i, m), old)
            t_new, b = time_renders(lambda m, i=inp: grey_expected(i, m), new)
            diff = max(float(np.max(np.abs(x - y)[8:-8, 8:-8])) for x, y in zip(a, b, strict=True))
            rows.append({"sat_px": sat_px, "candidates": kind, "renders": args.renders,
                         "sampled_ms": round(t_old * 1e3, 2), "fine_ms": round(t_new * 1e3, 2),
                         "speedup": round(t_old / t_new, 2),
                         "warp_once_s": round(warp_once, 3),
                         "max_abs_diff_dn_inner": round(diff, 4)})
            print(json.dumps(rows[-1]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows, "threads": 1}, indent=1) + "\n")


if __name__ == "__main__":
    main()
