"""Speed and agreement of the diagnosis' one-band grey render (round 35).

The scans that score only the grey level of a forward model (the coherent resampling scan,
the isotropic pixel scan) render each candidate model. Timed per candidate, two ways, on a
generator scene (haze, sensor noise) with the models those scans try (a resampling at a
new pitch and native-grid phase, Q and the other blurs held):

* ``full``: the luma of the three-band expected image,
  ``grey(m.deterministic(inp.simulate))`` — what the scans did before round 35 and what a
  user would write;
* ``grey``: :func:`geosim.diagnose.grey_render.grey_expected` — the UAV image weighted by
  luma weight × band gain rendered as one band, plus the offsets' luma.

Each with the simulation moved by a global sub-pixel shift (before sampling, as the
generator's scenes) and by a local warp (rotation 0.4°, scale 0.997, as the sample site's
flights: a cubic-spline warp per band of every render). The largest difference between
the two renders is reported. One thread (``OMP_NUM_THREADS=1`` etc. set before numpy loads).

Run: ``python benchmarks/bench_grey_render.py [--sat-px 128 192] [--renders 60]``; results
to ``benchmarks/results/bench_grey_render.json``.
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

from geosim.diagnose.grey_render import grey_expected  # noqa: E402
from geosim.diagnose.model import ForwardModel, RadiometryChoice, Registration  # noqa: E402
from geosim.diagnose.stage_inputs import grey  # noqa: E402
from tests.generator_cases import no_registration, scene_inputs  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_grey_render.json"
TRUTH = {"haze": {"transmission": [0.9, 0.85, 0.8], "path_radiance_dn": [6.0, 8.0, 12.0]},
         "sensor_noise": {"gain_dn": 0.05, "read_var_dn2": 2.0}}


def field_registration(shape: tuple[int, int]) -> Registration:
    """Rotation 0.4° and scale 0.997 about the centre plus a shift (column, row), as the
    sample site's flights, applied after sampling (no moved simulator)."""
    rows, cols = shape
    rr, cc = np.mgrid[0:rows, 0:cols].astype(float)
    t = np.radians(0.4)
    x, y = cc - cols / 2, rr - rows / 2
    return replace(no_registration(), applied=True, field_px=(
        1.6 + (0.997 * np.cos(t) - 1) * x - 0.997 * np.sin(t) * y,
        2.4 + 0.997 * np.sin(t) * x + (0.997 * np.cos(t) - 1) * y))


def models(inp, n: int, warp: bool) -> list[ForwardModel]:
    """``n`` candidates of a resampling scan: pitch 1.15-2.0 px, phases across it."""
    if warp:
        reg = field_registration(inp.grey.shape)
    else:
        reg = replace(no_registration(), applied=True, shift_px=(0.37, -0.61),
                      presampled=inp.simulate.shifted((0.37, -0.61)))
    haze = RadiometryChoice("haze", {"transmission": [0.92, 0.86, 0.81],
                                     "path_radiance_dn": [6.5, 8.2, 11.0]}, {}, 9.0, {})
    rng = np.random.default_rng(1)
    out = []
    for _ in range(n):
        pitch = float(rng.uniform(1.15, 2.0))
        out.append(ForwardModel(
            q=1.6, blur={"resampling": {"native_pitch_px": pitch, "cubic_a": -0.5}},
            registration=reg, radiometry=haze,
            native_phase_px=(float(rng.uniform(0, pitch)), float(rng.uniform(0, pitch)))))
    return out


def time_renders(render, ms: list[ForwardModel]) -> tuple[float, list[np.ndarray]]:
    """(seconds per render, the renders)."""
    t0 = time.perf_counter()
    out = [render(m) for m in ms]
    return (time.perf_counter() - t0) / len(ms), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sat-px", type=int, nargs="+", default=[128, 192])
    ap.add_argument("--renders", type=int, default=60)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    rows = []
    for sat_px in args.sat_px:
        inp, _ = scene_inputs(TRUTH, 1.6, 7, sat_px)
        for warp in (False, True):
            ms = models(inp, args.renders, warp)
            # caches built once, untimed: the one-band simulator, each path's moved DCT
            grey_expected(inp, ms[0])
            grey(ms[0].deterministic(inp.simulate))
            t_full, full = time_renders(lambda m, i=inp: grey(m.deterministic(i.simulate)), ms)
            t_grey, one = time_renders(lambda m, i=inp: grey_expected(i, m), ms)
            diff = max(float(np.max(np.abs(a - b))) for a, b in zip(full, one, strict=True))
            rows.append({"sat_px": sat_px, "move": "local warp" if warp else "global shift",
                         "renders": args.renders, "full_ms": round(t_full * 1e3, 2),
                         "grey_ms": round(t_grey * 1e3, 2),
                         "speedup": round(t_full / t_grey, 2), "max_abs_diff_dn": diff})
            print(json.dumps(rows[-1]), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": rows, "threads": 1}, indent=1) + "\n")


if __name__ == "__main__":
    main()
