"""Prototype: a transfer model that sees a blur acting before sampling at low Q.

The diagnosis fits a blur as a transfer multiplying the *sampled* simulation,
g · G(Q)(f) · H(f). Below Q ≈ 2 the optics pass content above the product Nyquist and
sampling folds it back: a blur acting on the ground (where a detector box, the atmosphere
or a smear act) damps a component folded from f + k by H(f + k), not H(f). The
**alias-cell** model splits each Q-grid simulation into the pieces folded from each alias
cell k ∈ {−1, 0, 1}² (the UAV image filtered by the cell's mask on the fine grid, complex,
before the optics; the pieces sum to the simulation) and models

    T(f) = g · [G(Q)(f) · H(f) + Σ_{k ≠ 0} G_k(Q)(f) · (H(f + k) − H(f))],

which is exact for any shift-invariant blur and equal to today's model above Q = 2, where
only k = 0 holds content. This script measures both models on scenes the benchmark's
independent generator renders (real ground, a detector box or an atmosphere, whole DN, no
other effect): the χ² gain of the blur over Q alone, and the fitted Q and blur parameter,
against the truth. Round 21's prototype; since round 29 the same model is in the
diagnosis (``geosim.diagnose.alias_cells``, whose cell split this script now uses; see
docs/diagnosis.md, rounds 21 and 29).

Run: python benchmarks/diagnose_alias_cells.py   (writes
benchmarks/results/diagnose_alias_cells.json, prints a markdown table; ~1 min)
"""

from __future__ import annotations

import copy
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.alias_cells import ALIAS_CELLS, cell_parts  # noqa: E402
from geosim.diagnose.fit import SpectralData, build_spectral_data, used_bins  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.spectra import block_origins, hann2d  # noqa: E402
from geosim.physics.otf import atmospheric_otf, detector_otf  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "diagnose_alias_cells.json"
#: the alias cells besides k = 0 (content beyond 1.5 cycles/px, Q < 0.67, joins |k| = 1)
CELLS = list(ALIAS_CELLS)
Q_GRID = np.exp(np.linspace(np.log(0.7), np.log(2.8), 14))
BLOCK_PX = 32
#: (development case whose ground is used, true Q, effect, parameter): every source kind
CASES: list[tuple[int, float, str, float]] = [
    (622, 0.85, "detector_integration", 1.44), (622, 1.0, "detector_integration", 1.2),
    (622, 1.2, "detector_integration", 1.0), (35, 0.9, "detector_integration", 1.3),
    (20, 1.0, "detector_integration", 1.5), (25, 1.1, "detector_integration", 1.1),
    (5, 0.95, "detector_integration", 1.4), (35, 1.5, "detector_integration", 1.3),
    (20, 2.2, "detector_integration", 1.4), (35, 0.9, "atmospheric_blur", 0.45),
    (25, 1.2, "atmospheric_blur", 0.35),
]
PARAM = {"detector_integration": ("pitch_px", (0.2, 3.0), (0.6, 1.2, 2.0)),
         "atmospheric_blur": ("f0_cyc_per_px", (0.05, 3.0), (0.3, 0.6, 1.2))}


def transfer(effect: str, value: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """H(fy, fx) of the effect, frequencies in cycles per product pixel."""
    if effect == "detector_integration":
        return lambda fy, fx: detector_otf(fy, fx, pitch_px=value)
    return lambda fy, fx: atmospheric_otf(fy, fx, f0_cyc_per_px=value)


def alias_transfers(uav_grey: np.ndarray, data: SpectralData, origins: list[tuple[int, int]],
                    f0: np.ndarray, s00: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """G_k(Q)(f) on the bins of ``data``: Welch transfer of each cell's piece (real and
    imaginary parts degraded by the paper model) against the sharpest simulation."""
    w = hann2d(BLOCK_PX)
    fy = np.fft.fftfreq(BLOCK_PX)[:, None] * np.ones((1, BLOCK_PX))
    fx = np.fft.fftfreq(BLOCK_PX)[None, :] * np.ones((BLOCK_PX, 1))
    half = used_bins(fy, fx)

    def ffts(img: np.ndarray) -> np.ndarray:
        # each block less its mean, as build_spectral_data treats the simulations
        return np.stack([np.fft.fft2((b - b.mean()) * w) for b in
                         (img[r:r + BLOCK_PX, c:c + BLOCK_PX] for r, c in origins)])

    out = {}
    for c, im in cell_parts(uav_grey, gen.PHI).items():
        re = QSimulator(im.real[None].astype(np.float32), phi=gen.PHI, q_min=0.6)
        imag = QSimulator(im.imag[None].astype(np.float32), phi=gen.PHI, q_min=0.6)
        out[c] = np.array([(np.sum(ffts(re(q)[0] + 1j * imag(q)[0]) * np.conj(f0), axis=0)
                            / s00)[half] for q in Q_GRID])
    return out


def fit(data: SpectralData, gk: dict[tuple[int, int], np.ndarray], effect: str | None,
        alias: bool) -> dict[str, Any]:
    """Least-squares (Q, g[, parameter]) with the product-grid or the alias-cell model."""
    lq = np.log(Q_GRID)
    wt = 1.0 / np.sqrt(data.var)

    def at(arr: np.ndarray, q: float) -> np.ndarray:
        x = float(np.clip(np.log(q), lq[0], lq[-1]))
        j = int(np.clip(np.searchsorted(lq, x) - 1, 0, len(lq) - 2))
        t = (x - lq[j]) / (lq[j + 1] - lq[j])
        return (1 - t) * arr[j] + t * arr[j + 1]

    def model(x: np.ndarray) -> np.ndarray:
        q, g = float(np.exp(x[0])), x[1]
        if effect is None:
            return g * at(data.g_q, q)
        h = transfer(effect, x[2])
        h0 = h(data.fy, data.fx)
        t = at(data.g_q, q) * h0
        if alias:
            for c in CELLS:
                t = t + at(gk[c], q) * (h(data.fy + c[0], data.fx + c[1]) - h0)
        return g * t

    def res(x: np.ndarray) -> np.ndarray:
        d = (data.t_real - model(x)) * wt
        return np.concatenate([d.real, d.imag])

    lo, hi = np.log(Q_GRID[0]), np.log(Q_GRID[-1])
    best = None
    p_starts = PARAM[effect][2] if effect else (None,)
    for q0 in (0.8, 1.1, 1.5, 2.0):
        for p0 in p_starts:
            x0 = [np.log(q0), 1.0] + ([p0] if effect else [])
            lb = [lo, 0.05] + ([PARAM[effect][1][0]] if effect else [])
            ub = [hi, 5.0] + ([PARAM[effect][1][1]] if effect else [])
            r = least_squares(res, x0, bounds=(lb, ub))
            if best is None or r.cost < best.cost:
                best = r
    return {"chi2": float(2 * best.cost), "q": float(np.exp(best.x[0])),
            "param": float(best.x[2]) if effect else None}


def run_case(index: int, q: float, effect: str, value: float,
             sources: list[gen.Source]) -> dict[str, Any]:
    inp = gen.case_inputs(index, sources)
    truth = {effect: {PARAM[effect][0]: value}}
    uav, real = gen.render(inp.ground, q, truth, copy.deepcopy(inp.rng), margin_px=inp.margin_px)
    uav_g, real_g = gen.luma(uav.astype(float)), gen.luma(real.astype(float))
    sim = QSimulator(uav_g[None].astype(np.float32), phi=gen.PHI, q_min=0.6)
    sims = [sim(qq)[0] for qq in Q_GRID]
    origins = block_origins(real_g.shape, block_px=BLOCK_PX)
    data = build_spectral_data(sims, Q_GRID, real_g, origins=origins, block_px=BLOCK_PX)
    wnd = hann2d(BLOCK_PX)
    f0 = np.stack([np.fft.fft2((b - b.mean()) * wnd) for b in
                   (sims[0][r:r + BLOCK_PX, c:c + BLOCK_PX] for r, c in origins)])
    s00 = np.maximum(np.sum(np.abs(f0) ** 2, axis=0), 1e-30)
    gk = alias_transfers(uav_g, data, origins, f0, s00)
    null = fit(data, gk, None, False)
    old = fit(data, gk, effect, False)
    new = fit(data, gk, effect, True)
    return {"ground_of": inp.label, "source": inp.source, "q_true": q, "effect": effect,
            "param_true": value, "null": null, "product_grid": old, "alias_cells": new,
            "gain_product_grid": null["chi2"] - old["chi2"],
            "gain_alias_cells": null["chi2"] - new["chi2"]}


def main() -> None:
    sources = gen.default_sources()
    rows = [run_case(*c, sources) for c in CASES]
    OUT.write_text(json.dumps({"q_grid": Q_GRID.tolist(), "block_px": BLOCK_PX,
                               "rows": rows}, indent=1))
    print("| ground | effect | true Q / param | Q only: χ² (Q) | product-grid model: χ² gain, Q, "
          "param | alias-cell model: χ² gain, Q, param |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        o, a = r["product_grid"], r["alias_cells"]
        print(f"| {r['ground_of']} ({r['source']}) | {r['effect']} | {r['q_true']:.2f} / "
              f"{r['param_true']:.2f} | {r['null']['chi2']:.0f} ({r['null']['q']:.2f}) | "
              f"{r['gain_product_grid']:.0f}, {o['q']:.2f}, {o['param']:.2f} | "
              f"{r['gain_alias_cells']:.0f}, {a['q']:.2f}, {a['param']:.2f} |")


if __name__ == "__main__":
    main()
