"""Ideal observer: could any method have told each true blur from a Q change?

The benchmark's recall counts every true effect, also those a scene cannot reveal: a
detector box or an atmosphere at high Q that a 2-4 % larger Q imitates. The diagnosis
states such limits itself (``detection_limits``), but that is the tool grading itself.
This script measures them with the benchmark's own generator (nothing from geosim) and
an observer that knows everything the diagnosis has to estimate: the exact ground (with
the moved objects where they really are), every other effect with its true parameters,
the noise and JPEG error variance. For each true blur effect of a case it renders the
noise-free product with all true effects (``render(..., noise_free=True)``) and the best
alternative without that effect: Q refitted (log grid, then bounded Brent) and a per-band
gain and offset fitted, by least squares on the pixels. Its evidence is

    delta_chi2 = sum over bands and pixels of (with - without)^2 / sigma_b^2,

sigma_b^2 the variance of what the case's noise, whole DN and JPEG add to the noise-free
product in band b (measured on the case itself: its delivered scene minus the noise-free
one). This is the log-likelihood ratio (x 2) of the two hypotheses for white Gaussian
errors of that variance: an upper bound on what any test can see, since the observer
knows what the diagnosis must estimate (the ground behind moved objects, the other
effects' parameters, the shift) and JPEG errors are structured, not white. An effect with
delta_chi2 below ``THRESHOLD`` (25: five standard deviations for one added parameter) is
"ideally undetectable" here: a Q change explains it within the noise for anyone.

Blur effects only (detector_integration, atmospheric_blur, motion_smear,
off_nadir_anisotropy, resampling); the other effects (radiometric, noise, JPEG, shift,
moved objects) are found in 97-100 % of development cases and count as detectable. For
the anisotropic pair the observer also weighs the *name*: the best render with the other
member in its place (width and Q fitted, the true direction held), ``naming_delta_chi2``;
below THRESHOLD the smear and the off-nadir Gaussian are ideally indistinguishable
(``nameable`` False), and an exact-name score there counts a coin flip.

Run: python benchmarks/diagnose_ideal.py [--only development|validation]
     [--indices I,J] [--processes 2] [--out FILE]
     (default: both halves, benchmarks/results/diagnose_ideal.json, and a summary against
     the halves' results in benchmarks/results/diagnose_independent.json)
     python benchmarks/diagnose_ideal.py --summary FILE   (the summary of a results file)
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from collections.abc import Callable
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize, minimize_scalar

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "diagnose_ideal.json"
HALVES = ROOT / "benchmarks" / "results" / "diagnose_independent.json"
#: the effects assessed (each can be absorbed into a wider optical PSF)
BLURS = ("detector_integration", "atmospheric_blur", "motion_smear",
         "off_nadir_anisotropy", "resampling")
#: delta_chi2 below which an effect is ideally undetectable (5 sigma, one parameter)
THRESHOLD = 25.0
#: a signature below this many times the paper model's implementation mismatch
#: (``paper_model_mismatch_rms_dn``) is below the implementation floor
IMPLEMENTATION_FACTOR = 2.0
#: renders the anisotropic naming fit may spend (Q and one width)
NAMING_EVALUATIONS = 40
#: the summary also reports these bars
BARS = (25.0, 100.0, 400.0)
#: the signature and mismatch RMS leave out this many product pixels at each edge
#: (boundary handling differs between implementations)
INNER_EDGE_PX = 4
#: the halves' last case index (seed 1000 + i)
N_LAST = gen.VALIDATION_LAST_SEED - 1000


def affine_fit(target: np.ndarray, model: np.ndarray) -> np.ndarray:
    """``model`` with a per-band gain and offset fitted to ``target`` by least squares."""
    out = np.empty_like(model)
    for b, (t, m) in enumerate(zip(target, model, strict=True)):
        a = np.column_stack([m.ravel(), np.ones(m.size)])
        coef, *_ = np.linalg.lstsq(a, t.ravel(), rcond=None)
        out[b] = (a @ coef).reshape(m.shape)
    return out


def weighted_rss(target: np.ndarray, model: np.ndarray, inv_var: np.ndarray) -> float:
    """sum_b |target_b - model_b|^2 / sigma_b^2."""
    return float(np.sum(np.square(target - model).reshape(len(inv_var), -1).sum(axis=1)
                        * inv_var))


def inner_rms(diff: np.ndarray, edge_px: int = INNER_EDGE_PX) -> float:
    """RMS of ``diff`` (bands, rows, cols) more than ``edge_px`` from the window's edge."""
    return float(np.sqrt(np.mean(np.square(diff[:, edge_px:-edge_px, edge_px:-edge_px]))))


def fitted_render(inp: gen.CaseInputs, q: float, truth: dict[str, dict[str, Any]],
                  target: np.ndarray) -> np.ndarray:
    """The case's noise-free product at ``q`` with ``truth`` (same ground, moved objects
    and implementation), a gain and offset per band fitted to ``target``."""
    _, sat = gen.render(inp.ground, q, truth, copy.deepcopy(inp.rng), margin_px=inp.margin_px,
                        variant=inp.variant, noise_free=True)
    return affine_fit(target, sat)


def best_without(inp: gen.CaseInputs, effect: str, target: np.ndarray,
                 inv_var: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(delta_chi2, Q', difference) of the best render without ``effect``: Q' on a log
    grid around the true Q, then refined by bounded Brent between the grid neighbours of
    the best; the difference is ``target`` minus that render (after its affine fit)."""
    truth = {k: v for k, v in inp.truth.items() if k != effect}

    def rss(q: float) -> float:
        return weighted_rss(target, fitted_render(inp, q, truth, target), inv_var)

    grid = inp.q * np.geomspace(0.85, 2.6, 9)
    vals = [rss(q) for q in grid]
    k = int(np.argmin(vals))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    res = minimize_scalar(rss, bounds=(lo, hi), method="bounded",
                          options={"xatol": 2e-3 * inp.q, "maxiter": 14})
    d2, q_best = min((res.fun, res.x), (vals[k], grid[k]))
    return float(d2), float(q_best), target - fitted_render(inp, q_best, truth, target)


#: the anisotropic pair: (parameter, direction key) of each member
ANISOTROPIC = {"motion_smear": ("length_px", "direction_deg"),
               "off_nadir_anisotropy": ("sigma_px", "azimuth_deg")}
#: each anisotropic member's other member
OTHER_MEMBER = {"motion_smear": "off_nadir_anisotropy", "off_nadir_anisotropy": "motion_smear"}


def naming_evidence(inp: gen.CaseInputs, effect: str, target: np.ndarray,
                    inv_var: np.ndarray) -> tuple[float, dict[str, float]]:
    """(delta_chi2, its parameters) of the best render with the *other* anisotropic member
    in place of ``effect``: its width and Q fitted (Nelder-Mead from the equal second
    moment, L² / 12 = σ²), its direction held at the true one (a refitted direction could
    only fit better: the evidence for the name is, if anything, overstated)."""
    other = OTHER_MEMBER[effect]
    key, dkey = ANISOTROPIC[other]
    own_key, own_dkey = ANISOTROPIC[effect]
    width = inp.truth[effect][own_key]
    start = width / np.sqrt(12.0) if other == "off_nadir_anisotropy" else width * np.sqrt(12.0)
    base = {k: v for k, v in inp.truth.items() if k != effect}
    direction = inp.truth[effect][own_dkey]

    def rss(x: np.ndarray) -> float:
        truth = {**base, other: {key: float(max(x[1], 0.05)), dkey: direction}}
        return weighted_rss(target, fitted_render(inp, float(np.exp(x[0])), truth, target),
                            inv_var)

    res = minimize(rss, np.array([np.log(inp.q), start]), method="Nelder-Mead",
                   options={"maxfev": NAMING_EVALUATIONS, "xatol": 1e-3, "fatol": 0.5})
    return float(res.fun), {"q": float(np.exp(res.x[0])), key: float(res.x[1])}


def geosim_paper_model_mismatch(inp: gen.CaseInputs) -> float:
    """RMS (DN, away from the edges) of geosim's paper model at the true Q minus the
    generator's, both noise-free and without effects: how closely two implementations of
    the same model agree on this ground. An effect whose signature is not well above it
    cannot be told from implementation detail by a tool that is not the generator itself.
    (The one use of geosim here, for this column only.)"""
    from geosim.diagnose.simulate import QSimulator

    uav, plain = gen.render(inp.ground, inp.q, {}, copy.deepcopy(inp.rng),
                            margin_px=inp.margin_px, noise_free=True)
    return inner_rms(QSimulator(uav, phi=gen.PHI, q_min=0.6)(inp.q) - plain)


#: the mismatch column's function (None: left out)
paper_model_mismatch: Callable[[gen.CaseInputs], float] | None = geosim_paper_model_mismatch


def assess(i: int) -> dict[str, Any]:
    """The ideal observer's evidence for each true blur effect of case ``i``."""
    return assess_inputs(gen.case_inputs(i, gen.default_sources()),
                         mismatch=paper_model_mismatch)


def assess_inputs(inp: gen.CaseInputs, *,
                  mismatch: Callable[[gen.CaseInputs], float] | None = None,
                  naming: bool = True) -> dict[str, Any]:
    """:func:`assess` for given case inputs; ``mismatch``: a function of them giving the
    paper-model implementation mismatch (DN) recorded beside (None: not recorded);
    ``naming``: also the evidence for an anisotropic blur's name (:func:`naming_evidence`)."""
    row: dict[str, Any] = {"case": inp.label, "seed": inp.seed, "q_true": inp.q,
                           "truth": inp.truth, "ideal": {}}
    blurs = [e for e in BLURS if e in inp.truth]
    if not blurs:
        return row
    t0 = time.time()
    _, clean = gen.render(inp.ground, inp.q, inp.truth, copy.deepcopy(inp.rng),
                          margin_px=inp.margin_px, variant=inp.variant, noise_free=True)
    _, real = gen.render(inp.ground, inp.q, inp.truth, copy.deepcopy(inp.rng),
                         margin_px=inp.margin_px, variant=inp.variant)
    err_var = np.maximum((real - clean).reshape(3, -1).var(axis=1), 1.0 / 12.0)
    row["error_var_dn2"] = err_var.tolist()
    for e in blurs:
        d2, q_alt, diff = best_without(inp, e, clean, 1.0 / err_var)
        row["ideal"][e] = {"delta_chi2": d2, "q_without": q_alt,
                           "detectable": d2 >= THRESHOLD, "signature_rms_dn": inner_rms(diff)}
        if e in ANISOTROPIC and naming:
            n2, fitted = naming_evidence(inp, e, clean, 1.0 / err_var)
            row["ideal"][e].update({"naming_delta_chi2": n2, "other_member_fit": fitted,
                                    "nameable": n2 >= THRESHOLD})
    if mismatch is not None:
        row["paper_model_mismatch_rms_dn"] = mismatch(inp)
    row["seconds"] = time.time() - t0
    return row


def summary(ideal_rows: list[dict[str, Any]], halves: dict[str, Any]) -> dict[str, Any]:
    """Per half: the blur effects by ideal evidence, and the tool's recall within each
    class; the exact-name recall over the effects that are ideally detectable."""
    claimed = {r["case"]: set(r["claimed"]) for r in halves["cases"]}
    split = {r["case"]: r["split"] for r in halves["cases"]}
    truth_of = {r["case"]: set(r["truth"]) for r in halves["cases"]}
    out: dict[str, Any] = {}
    for half in ("development", "validation"):
        rows = [r for r in ideal_rows if split.get(r["case"]) == half]
        if not rows:
            continue
        cases = {r["case"] for r in rows}
        blur = [(r["case"], e, v["delta_chi2"]) for r in rows for e, v in r["ideal"].items()]
        s: dict[str, Any] = {"cases": len(rows), "blur_effects": len(blur)}
        for bar in BARS:
            det = [(c, e) for c, e, d in blur if d >= bar]
            und = [(c, e) for c, e, d in blur if d < bar]
            s[f"bar_{bar:g}"] = {
                "detectable": len(det), "found": sum(e in claimed[c] for c, e in det),
                "undetectable": len(und),
                "undetectable_found": sum(e in claimed[c] for c, e in und)}
        tp = sum(len(truth_of[c] & claimed[c]) for c in cases)
        fn = sum(len(truth_of[c] - claimed[c]) for c in cases)
        s["recall"] = tp / (tp + fn) if tp + fn else 1.0
        hidden = {(c, e) for c, e, d in blur if d < THRESHOLD}
        s["recall_ideally_detectable"] = _recall_without(cases, truth_of, claimed, hidden)
        # also hidden: a signature not above twice what two implementations of the
        # paper's model differ by on the same ground
        floor = {r["case"]: r.get("paper_model_mismatch_rms_dn") for r in rows}
        below = {(r["case"], e) for r in rows for e, v in r["ideal"].items()
                 if floor[r["case"]] is not None
                 and v["signature_rms_dn"] < IMPLEMENTATION_FACTOR * floor[r["case"]]}
        s["blur_effects_below_implementation_floor"] = len(below - hidden)
        s["recall_above_implementation_floor"] = _recall_without(cases, truth_of, claimed,
                                                                 hidden | below)
        s["missed_detectable"] = sorted(
            f"{c} {e} ({d:.0f}{', below the implementation floor' if (c, e) in below else ''})"
            for c, e, d in blur if d >= THRESHOLD and e not in claimed[c])
        by_effect: dict[str, list[int]] = {}
        for c, e, d in blur:
            v = by_effect.setdefault(e, [0, 0, 0, 0])
            v[0 if d >= THRESHOLD else 2] += 1
            v[1 if d >= THRESHOLD else 3] += e in claimed[c]
        s["by_effect_detectable_found_undetectable_found"] = by_effect
        anis = [(r["case"], e, v) for r in rows for e, v in r["ideal"].items()
                if "naming_delta_chi2" in v]
        if anis:
            s["anisotropic_naming"] = _naming_counts(anis, claimed)
        out[half] = s
    return out


def _naming_counts(anis: list[tuple[str, str, dict[str, Any]]],
                   claimed: dict[str, set[str]]) -> dict[str, int]:
    """The anisotropic effects by whether their name is ideally determined, and how often
    the tool named them right or as the other member."""
    out = {"effects": len(anis)}
    for label, flag in (("nameable", True), ("not_nameable", False)):
        sel = [(c, e) for c, e, v in anis if v["nameable"] == flag]
        out[label] = len(sel)
        out[f"{label}_named_right"] = sum(e in claimed[c] for c, e in sel)
        out[f"{label}_named_other"] = sum(OTHER_MEMBER[e] in claimed[c] for c, e in sel)
    return out


def _recall_without(cases: set[str], truth_of: dict[str, set[str]],
                    claimed: dict[str, set[str]], hidden: set[tuple[str, str]]) -> float:
    """Exact-name recall over the true effects of ``cases`` not in ``hidden``."""
    tp = sum(len({e for e in truth_of[c] & claimed[c] if (c, e) not in hidden}) for c in cases)
    fn = sum(len({e for e in truth_of[c] - claimed[c] if (c, e) not in hidden}) for c in cases)
    return tp / (tp + fn) if tp + fn else 1.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=("development", "validation"))
    ap.add_argument("--indices", help="comma-separated case indices (seed 1000 + i)")
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--out", type=Path, default=OUT)
    ap.add_argument("--summary", type=Path, help="summarise this results file only")
    args = ap.parse_args()
    halves = json.loads(HALVES.read_text())
    if args.summary:
        rows = json.loads(args.summary.read_text())["cases"]
        print(json.dumps(summary(rows, halves), indent=1))
        return
    if args.indices:
        idx = [int(x) for x in args.indices.split(",")]
    else:
        idx = [i for i in range(N_LAST + 1)
               if args.only is None
               or (gen.is_validation_seed(1000 + i)) == (args.only == "validation")]
    t0 = time.time()
    with Pool(args.processes) as pool:
        rows = pool.map(assess, idx, chunksize=1)
    result = {"threshold_delta_chi2": THRESHOLD, "cases": rows,
              "seconds_total": time.time() - t0, "summary": summary(rows, halves)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(json.dumps(result["summary"], indent=1))


if __name__ == "__main__":
    main()
