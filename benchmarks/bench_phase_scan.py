"""Speed and agreement of the coherent resampling scan's parts (round 41).

Under noise the diagnosis places a resampling's native grid pixel by pixel
(:mod:`geosim.diagnose.stage_resampling_coherent`): every native pitch of the scan is
rendered at 3 × 3 native phases with both cubic kernels, the residual's sum of squares is
interpolated over the phase, and the best pitches are refined. On the sample site this
scan was 44 % of the diagnosis (round 40, profiled). Round 41 changed three parts, each
timed here against the form it replaced, in the same run, on one grey band (as the scan
renders), one thread:

* ``box``: the native pixels' means of the DCT basis (``native_grid._dct_box_matrix``),
  the sines taken once per native edge (round 40: twice, once per side of each pixel);
* ``renders``: a pitch's 3 × 3 phases through ``QSimulator.native``, which keeps the
  native rows' step of a row phase for its column phases (round 40: both matrix products
  per render, :func:`geosim.physics.native_grid.native_area_dct`);
* ``phase_rss``: the residual's RSS at 12 × 12 phases from the 3 × 3 renders as a
  quadratic form in their Gram matrix (:func:`~geosim.diagnose.stage_resampling_coherent.
  phase_harmonics`; round 40: each interpolated residual image made, then summed).

The renders must agree bitwise and the RSS to 1e-9 (relative); the benchmark exits
non-zero where they do not.

Run: ``python benchmarks/bench_phase_scan.py [--sat-px 128 192] [--pitches 12]``; results
to ``benchmarks/results/bench_phase_scan.json``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_native_render import uav_image  # noqa: E402

from geosim.diagnose import stage_resampling_coherent as coherent  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.physics import native_grid  # noqa: E402
from geosim.physics.cubic import KEYS_A, OPENCV_A  # noqa: E402

PHI = 10
Q = 1.7
OUT = Path(__file__).resolve().parent / "results" / "bench_phase_scan.json"


def box_round40(edges: np.ndarray, n: int, n_coef: int) -> np.ndarray:
    """``_dct_box_matrix`` as round 40 wrote it (each pixel's two edges' sines)."""
    k = np.arange(n_coef)[np.newaxis, :]
    s0, s1 = edges[:-1, np.newaxis], edges[1:, np.newaxis]
    width = np.maximum(s1 - s0, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = np.where(k == 0, 1.0, n * (np.sin(np.pi * k * s1 / n)
                                          - np.sin(np.pi * k * s0 / n))
                        / (np.pi * np.maximum(k, 1) * width))
    return np.where(k == 0, np.sqrt(1.0 / n), np.sqrt(2.0 / n)) * mean


def phase_rss_round40(residuals: np.ndarray) -> np.ndarray:
    """The 12 × 12 interpolated RSS as round 40 computed it (the residual images made)."""
    steps, fine_n = coherent.PHASE_STEPS, coherent.PHASE_FINE
    coef = np.fft.fft2(residuals, axes=(0, 1)) / steps ** 2
    harmonic = np.fft.fftfreq(steps, 1.0 / steps)
    t = np.arange(fine_n) * steps / fine_n
    e = np.exp(2j * np.pi * np.outer(t, harmonic) / steps)
    fine = np.einsum("ta,sb,abn->tsn", e, e, coef, optimize=True).real
    return np.sum(fine ** 2, axis=-1)


def render_round40(band_coef: np.ndarray, fine_shape: tuple[int, int], pitch: float,
                   phase: tuple[float, float], cubic_a: float) -> np.ndarray:
    """A native render with both matrix products made for it (round 40's path), from the
    optics' coefficients at Q that ``QSimulator.native`` keeps."""
    nat, cr, cc = native_grid.native_area_dct(band_coef, fine_shape, PHI, pitch, phase)
    n = fine_shape[0] // PHI
    return native_grid.native_to_product(nat, cr, cc, (n, n), cubic_a)


def one_size(sat_px: int, n_pitches: int) -> dict:
    img = uav_image(sat_px)
    grey = img.mean(axis=0)[np.newaxis]
    real = grey.reshape(sat_px, PHI, sat_px, PHI).mean(axis=(1, 3))
    pitches = np.round(np.linspace(1.15, 2.0, n_pitches), 2)
    sim = QSimulator(grey, phi=PHI, q_min=0.5)
    sim.native(Q, 1.5)                               # the DCT made once, outside the timing
    fine_shape = sim._native_coef[1].shape[-2:]      # noqa: SLF001
    n_coef = sim._native_fine[1].shape[-1]           # noqa: SLF001

    # box matrices: every pitch's 3 phases (round 40's formula against today's)
    edges = [np.clip(native_grid.native_edges(sat_px, p, p * j / 3) * PHI, 0.0,
                     sat_px * PHI) for p in pitches for j in range(3)]
    t0 = time.perf_counter()
    old_box = [box_round40(e, fine_shape[0], n_coef) for e in edges]
    t_box_old = time.perf_counter() - t0
    t0 = time.perf_counter()
    new_box = [native_grid._dct_box_matrix(e, fine_shape[0], n_coef)  # noqa: SLF001
               for e in edges]
    t_box_new = time.perf_counter() - t0
    box_equal = all(np.array_equal(a, b) for a, b in zip(old_box, new_box, strict=True))

    # renders: each pitch at 3 × 3 phases, both kernels (as the scan renders them)
    calls = [(float(p), (float(p) * j / 3, float(p) * k / 3), a)
             for a in (OPENCV_A, KEYS_A) for p in pitches for j in range(3) for k in range(3)]
    native_grid._axis_box.cache_clear()              # noqa: SLF001
    t0 = time.perf_counter()
    band_coef = sim._native_fine[1]                   # noqa: SLF001 (kept at Q)
    old = [render_round40(band_coef, fine_shape, p, ph, a) for p, ph, a in calls]
    t_old = time.perf_counter() - t0
    native_grid._axis_box.cache_clear()              # noqa: SLF001
    sim2 = QSimulator(grey, phi=PHI, q_min=0.5)
    sim2.native(Q, 1.5)
    t0 = time.perf_counter()
    new = [sim2.native(Q, p, cubic_a=a, phase_px=ph) for p, ph, a in calls]
    t_new = time.perf_counter() - t0
    renders_equal = all(np.array_equal(a, b) for a, b in zip(old, new, strict=True))

    # the RSS over the phase from each pitch's 9 residuals
    res = [np.stack([real - r[0] for r in new[i:i + 9]]).reshape(3, 3, -1)
           for i in range(0, len(new), 9)]
    t0 = time.perf_counter()
    rss_old = [float(np.min(phase_rss_round40(r))) for r in res]
    t_rss_old = time.perf_counter() - t0
    t0 = time.perf_counter()
    rss_new = [coherent.phase_harmonics(r, 1.5)[0] for r in res]
    t_rss_new = time.perf_counter() - t0
    rss_rel = max(abs(a - b) / abs(a) for a, b in zip(rss_old, rss_new, strict=True))
    return {"sat_px": sat_px, "q": Q, "pitches": len(pitches), "renders": len(calls),
            "box_matrices": len(edges), "box_equal": box_equal,
            "renders_equal": renders_equal, "phase_rss_max_rel_difference": rss_rel,
            "seconds": {"box_round40": t_box_old, "box": t_box_new,
                        "renders_round40": t_old, "renders": t_new,
                        "phase_rss_round40": t_rss_old, "phase_rss": t_rss_new},
            "speedup": {"box": t_box_old / t_box_new, "renders": t_old / t_new,
                        "phase_rss": t_rss_old / t_rss_new}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sat-px", type=int, nargs="+", default=[128, 192])
    ap.add_argument("--pitches", type=int, default=12)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    rows = [one_size(n, a.pitches) for n in a.sat_px]
    doc = {"threads": 1, "phi": PHI, "sizes": rows,
           "note": "round 40's forms written out here, timed in the same run as today's"}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps(doc, indent=1))
    bad = [r["sat_px"] for r in rows if not (r["box_equal"] and r["renders_equal"]
                                             and r["phase_rss_max_rel_difference"] < 1e-9)]
    if bad:
        sys.exit(f"disagreement at {bad} px")


if __name__ == "__main__":
    main()
