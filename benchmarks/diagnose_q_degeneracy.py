"""How far an isotropic blur is from a slightly wider optical PSF (identifiability with Q).

The transfer fit of ``geosim diagnose`` fits Q (Airy OTF, cut-off 1/Q cycles per product
pixel) and a broadband gain jointly with each blur. An isotropic blur whose in-band
transfer a wider Airy OTF (Q' > Q) times a gain reproduces to within the measurement's
accuracy cannot be told from that Q': it is absorbed into Q. For each true Q and blur this
finds the best (Q', gain) — least squares over the product band 0–0.5 cycles/px,
weighted by f (the number of 2-D frequency bins at radius f) — and reports the largest
difference of the transfers anywhere in the band. Compare it with the fit's error floor
(``geosim.diagnose.fit.TRANSFER_FLOOR``, 0.004 per bin) and with the statistical error
that noise adds.

Independent formulas (numpy only): Airy OTF (2/π)(acos ν − ν √(1 − ν²)), ν = f Q; detector
box sinc(p f); atmosphere exp(−(f/f0)^(5/3)); resampling box sinc(p f) times the transfer
of the Keys (a = −0.75) cubic kernel at p f cycles per native sample (numerical Fourier
transform of the kernel).

Run: python benchmarks/diagnose_q_degeneracy.py  (writes
benchmarks/results/diagnose_q_degeneracy.json, prints a markdown table; < 1 s)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

ROOT = Path(__file__).resolve().parents[1]
F = np.linspace(0.0, 0.5, 401)          # cycles per product pixel
Q_TRUE = (1.5, 2.0, 2.7, 3.5, 4.4)
BLURS = (("detector_integration", "pitch_px", 1.0), ("detector_integration", "pitch_px", 1.6),
         ("resampling", "native_pitch_px", 1.45), ("atmospheric_blur", "f0_cyc_per_px", 0.45))


def airy_otf(f: np.ndarray, q: float) -> np.ndarray:
    """Circular-aperture OTF, cut-off 1/q cycles per product pixel."""
    v = np.clip(f * q, 0.0, 1.0)
    return (2 / np.pi) * (np.arccos(v) - v * np.sqrt(1 - v * v))


def keys_mtf(nu: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Transfer of the Keys cubic interpolation kernel at ``nu`` cycles per sample."""
    x = np.linspace(-2, 2, 4001)
    ax = np.abs(x)
    k = np.where(ax <= 1, (a + 2) * ax**3 - (a + 3) * ax**2 + 1,
                 np.where(ax < 2, a * ax**3 - 5 * a * ax**2 + 8 * a * ax - 4 * a, 0.0))
    dx = x[1] - x[0]
    return np.array([np.sum(k * np.cos(2 * np.pi * n * x)) * dx for n in np.abs(nu)])


def blur_transfer(name: str, value: float) -> np.ndarray:
    if name == "detector_integration":
        return np.sinc(value * F)
    if name == "resampling":
        return np.sinc(value * F) * keys_mtf(value * F)
    return np.exp(-(F / value) ** (5 / 3))


def best_wider_psf(target: np.ndarray, q: float) -> tuple[float, float, float]:
    """(Q', gain, max |difference|) of the best g · Airy(Q') for ``target``."""
    def err(x: np.ndarray) -> float:
        return float(np.sum((target - x[1] * airy_otf(F, x[0])) ** 2 * F))

    r = minimize(err, np.array([1.05 * q, 1.0]), method="Nelder-Mead",
                 options={"xatol": 1e-5, "fatol": 1e-12})
    qb, g = (float(v) for v in r.x)
    return qb, g, float(np.max(np.abs(target - g * airy_otf(F, qb))))


def main() -> None:
    rows = []
    for q in Q_TRUE:
        for name, key, value in BLURS:
            qb, g, d = best_wider_psf(airy_otf(F, q) * blur_transfer(name, value), q)
            rows.append({"q_true": q, "effect": name, key: value, "q_equivalent": qb,
                         "gain": g, "max_abs_difference": d})
    out = ROOT / "benchmarks" / "results" / "diagnose_q_degeneracy.json"
    out.write_text(json.dumps({"band_cyc_per_px": [0.0, 0.5], "weight": "f",
                               "rows": rows}, indent=1))
    head = [f"{n} {v}" for n, _, v in BLURS]
    print("| Q | " + " | ".join(head) + " |")
    print("|---" * (len(head) + 1) + "|")
    for q in Q_TRUE:
        cells = [f"Q' {r['q_equivalent']:.2f}, g {r['gain']:.3f}: "
                 f"{100 * r['max_abs_difference']:.1f} %" for r in rows if r["q_true"] == q]
        print(f"| {q} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
