"""Speed and agreement of the diagnosis' native-grid render (round 22).

A resampled product (optics at Q on the 0.05 m grid, each native detector's mean over its
area, cubic convolution onto the 0.5 m grid) rendered three ways from one UAV image's DCT:

* ``dct``: :func:`geosim.physics.native_grid.native_area_dct` on the coefficients below
  the optics' cut-off, then :func:`~geosim.physics.native_grid.native_to_product` — what
  ``QSimulator.native`` does since round 22 (any real pitch, any phase);
* ``idct_opencv``: the inverse DCT of the filtered coefficients onto the fine grid, then
  OpenCV's ``INTER_AREA`` to the native grid and ``INTER_CUBIC`` back — what it did
  before (a whole number of native pixels over the scene, phase 0), and what a user would
  write with OpenCV;
* ``idct_overlap``: the same inverse DCT, then
  :func:`~geosim.physics.native_grid.native_area` (fine pixels constant over their
  extent) at the same pitch as OpenCV's.

Timed per render at a new Q (the refinement's usual step) and at the same Q, new pitch
(the phase and pitch scans); the products' RMS differences are reported (the DCT form
integrates the band-limited image between pixel centres, the others take each fine pixel
as constant). One thread (``OMP_NUM_THREADS=1`` etc. are set before numpy loads).

Run: ``python benchmarks/bench_native_render.py [--sat-px 128] [--repeat 20]``; results
to ``benchmarks/results/bench_native_render.json``.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from geosim.degrade.core import (  # noqa: E402
    blur_coefficients,
    dct_coefficients,
    optics_otf_below_cutoff,
)
from geosim.physics.cubic import cubic_resize  # noqa: E402
from geosim.physics.native_grid import (  # noqa: E402
    native_area,
    native_area_dct,
    native_to_product,
)

PHI = 10
OUT = Path(__file__).resolve().parent / "results" / "bench_native_render.json"


def uav_image(sat_px: int, seed: int = 0) -> np.ndarray:
    """A textured 3-band fine-grid image (smoothed noise with edges), DN."""
    rng = np.random.default_rng(seed)
    n = sat_px * PHI
    img = ndimage.gaussian_filter(rng.normal(0, 1, (3, n, n)), (0, 6, 6))
    img += 0.5 * (rng.random((3, 1, 1)) * (ndimage.uniform_filter(
        rng.random((n, n)), 40) > 0.5))
    return 120 + 40 * img / img.std()


def below_cutoff(coef: np.ndarray, q: float) -> np.ndarray:
    """The optics' image as its DCT below the cut-off (what QSimulator.native keeps)."""
    otf_k = optics_otf_below_cutoff(coef.shape[-2:], q=q, phi=PHI)
    return coef[:, :otf_k.shape[0], :otf_k.shape[1]] * otf_k


def render_dct(coef: np.ndarray, q: float, pitch: float) -> np.ndarray:
    ck = below_cutoff(coef, q)
    nat, cr, cc = native_area_dct(ck, coef.shape[-2:], PHI, pitch)
    n = coef.shape[-1] // PHI
    return native_to_product(nat, cr, cc, (n, n), -0.75)


def render_idct_opencv(coef: np.ndarray, q: float, n_native: int) -> np.ndarray:
    fine = blur_coefficients(coef, q=q, phi=PHI).astype(np.float32)
    n = coef.shape[-1] // PHI
    return np.stack([cubic_resize(cv2.resize(b, (n_native, n_native),
                                             interpolation=cv2.INTER_AREA), (n, n))
                     for b in fine])


def render_idct_overlap(coef: np.ndarray, q: float, pitch: float) -> np.ndarray:
    fine = blur_coefficients(coef, q=q, phi=PHI).astype(np.float32)
    nat, cr, cc = native_area(fine, PHI, pitch)
    n = coef.shape[-1] // PHI
    return native_to_product(nat, cr, cc, (n, n), -0.75)


def timed(fn, repeat: int) -> float:
    t0 = time.perf_counter()
    for k in range(repeat):
        fn(k)
    return (time.perf_counter() - t0) / repeat


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sat-px", type=int, default=128)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    coef = dct_coefficients(uav_image(a.sat_px))
    n_native = int(round(a.sat_px / 1.45))
    pitch = a.sat_px / n_native                     # OpenCV's pitch, for the comparison
    rows = {}
    for q in (0.9, 1.5, 3.0):
        d = render_dct(coef, q, pitch)
        o = render_idct_opencv(coef, q, n_native)
        v = render_idct_overlap(coef, q, pitch)
        rows[f"q{q}"] = {"rms_dct_vs_opencv_dn": float(np.sqrt(np.mean((d - o) ** 2))),
                         "rms_overlap_vs_opencv_dn": float(np.sqrt(np.mean((v - o) ** 2))),
                         "product_std_dn": float(o.std())}
    qs = 1.0 + 0.01 * np.arange(a.repeat)           # a new Q each render
    times = {
        "dct_new_q_s": timed(lambda k: render_dct(coef, qs[k], pitch), a.repeat),
        "idct_opencv_new_q_s": timed(lambda k: render_idct_opencv(coef, qs[k], n_native),
                                     a.repeat),
        "idct_overlap_new_q_s": timed(lambda k: render_idct_overlap(coef, qs[k], pitch),
                                      a.repeat),
    }
    # same Q, new pitch: the DCT form's filtered coefficients (or the fine image) kept
    ck = below_cutoff(coef, 1.0)
    fine = blur_coefficients(coef, q=1.0, phi=PHI).astype(np.float32)
    n = a.sat_px
    times["dct_same_q_s"] = timed(lambda k: native_to_product(
        *native_area_dct(ck, coef.shape[-2:], PHI, 1.3 + 0.01 * k), (n, n), -0.75), a.repeat)
    times["opencv_same_q_s"] = timed(lambda k: np.stack([cubic_resize(cv2.resize(
        b, (n_native - k % 3, n_native - k % 3), interpolation=cv2.INTER_AREA), (n, n))
        for b in fine]), a.repeat)
    res = {"sat_px": a.sat_px, "phi": PHI, "bands": 3, "pitch_px": pitch,
           "repeat": a.repeat, "threads": 1, "agreement": rows, "seconds_per_render": times}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
