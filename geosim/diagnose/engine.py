"""The diagnosis on arrays: co-register → locate → attribute → model → refit.

Pure numerics (no files): :func:`diagnose_arrays` takes the real scene on the
0.5 m grid and a callable giving the paper's model at any Q on the same grid, and
returns a :class:`Diagnosis` with the JSON-able summary, the three images
(real, baseline, refined), the mismatch maps and regions, and plot data.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from geosim.diagnose import locate
from geosim.diagnose.coregister import (
    estimate_affine,
    estimate_shift,
    fourier_shift,
    warp_by_field,
)
from geosim.diagnose.effects import BLUR_EFFECTS, get_effect
from geosim.diagnose.fit import (
    build_spectral_data,
    fit_noise,
    fit_radiometry,
    fit_transfer,
)
from geosim.diagnose.seam import find_gain_step
from geosim.diagnose.select import MIN_DELTA_BIC, select_blur, select_radiometry
from geosim.diagnose.spectra import (
    block_origins,
    cross_spectrum,
    radial_profile,
    screen_blocks,
    spectral_error,
)
from geosim.physics import otf
from geosim.physics.radiometry import luma

__all__ = ["Diagnosis", "diagnose_arrays", "blockiness", "PHYSICAL_Q"]

PHYSICAL_Q = (0.5, 2.0)
MIN_NOISE_VAR_DN2 = 0.5
MIN_SHIFT_PX = 0.1
#: floor of the residual energy a region must exceed (× ratio threshold), DN²
MIN_REGION_DN2 = 4.0
#: low-pass σ (px) of the images used for the per-band gain/offset regression
RADIOMETRY_SIGMA_PX = 2.0
#: Welch blocks wanted for a stable transfer-function estimate
MIN_BLOCKS = 16


@dataclass
class Diagnosis:
    """Everything the diagnosis found (arrays on the 0.5 m grid, bands first)."""

    summary: dict[str, Any]
    real: np.ndarray
    baseline: np.ndarray
    refined: np.ndarray
    valid: np.ndarray
    maps: dict[str, np.ndarray] = field(default_factory=dict)
    regions: list[locate.Region] = field(default_factory=list)
    labels: np.ndarray | None = None
    plots: dict[str, Any] = field(default_factory=dict)


def _grey(img: np.ndarray) -> np.ndarray:
    return luma(img) if img.ndim == 3 else np.asarray(img, float)


#: blur effects whose forward model is not shift-invariant (applied with ``apply``, so that
#: the refined simulation carries their aliasing, not only their average transfer)
NON_LSI = ("resampling",)


def _blur_apply(img: np.ndarray, effects: dict[str, dict[str, float]]) -> np.ndarray:
    out = np.asarray(img, float)
    lsi = {n: p for n, p in effects.items() if n not in NON_LSI}
    if lsi:
        tr = otf.compose(*[(lambda fy, fx, n=n, p=p: get_effect(n).transfer(fy, fx, **p))
                           for n, p in lsi.items()])
        out = otf.apply_transfer(out, tr)
    for n, p in effects.items():
        if n in NON_LSI:
            out = get_effect(n).apply(out, **p)
    return out


def blockiness(residual_grey: np.ndarray, mask: np.ndarray, *, period: int = 8
               ) -> dict[str, float]:
    """Excess of squared steps across block edges of size ``period``.

    For each phase p of columns (rows), the mean squared difference between
    neighbouring pixels across boundaries at c ≡ p (mod period); the phase with the
    largest mean is the candidate block edge. Returns the ratio to the mean of the other
    phases, a z-score from the spread of per-line means, the excess in DN², and the
    phases (row, col).
    """
    e = np.where(mask, residual_grey, 0.0)
    m2 = mask[:, 1:] & mask[:, :-1]
    dcol = np.where(m2, (e[:, 1:] - e[:, :-1]) ** 2, np.nan)   # step between c-1 and c
    m2r = mask[1:, :] & mask[:-1, :]
    drow = np.where(m2r, (e[1:, :] - e[:-1, :]) ** 2, np.nan)
    out: dict[str, float] = {}
    for axis, d in (("col", dcol), ("row", drow)):
        with warnings.catch_warnings():  # lines entirely outside the valid area are NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            line = np.nanmean(d, axis=0) if axis == "col" else np.nanmean(d, axis=1)
        idx = np.arange(1, line.size + 1)     # boundary index c (between c-1 and c)
        ok = np.isfinite(line)
        means = np.array([np.mean(line[ok & (idx % period == p)]) for p in range(period)])
        p = int(np.nanargmax(means))
        others = line[ok & (idx % period != p)]
        at = line[ok & (idx % period == p)]
        ratio = float(means[p] / max(np.mean(others), 1e-12))
        z = float((np.mean(at) - np.mean(others)) / max(np.std(others) / np.sqrt(at.size),
                                                         1e-12))
        out[f"{axis}_ratio"] = ratio
        out[f"{axis}_z"] = z
        out[f"{axis}_phase"] = p
        out[f"{axis}_excess_dn2"] = float(np.mean(at) - np.mean(others))
    return out


def _rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a[:, mask] - b[:, mask]) ** 2)))


def _hp_factor(sigma: float) -> float:
    d = np.zeros((33, 33))
    d[16, 16] = 1.0
    h = d - ndimage.gaussian_filter(d, sigma)
    return float(np.sum(h**2))


def diagnose_arrays(real: np.ndarray, simulate: Callable[[float], np.ndarray], *,
                    q_base: float, rng: np.random.Generator, valid: np.ndarray | None = None,
                    gsd_m: float = 0.5, q_lo: float = 0.7, q_hi: float | None = None,
                    block_px: int | None = None, quantized: bool | None = None,
                    blur_candidates: tuple[str, ...] = BLUR_EFFECTS) -> Diagnosis:
    """Diagnose what the paper's model leaves out.

    Parameters
    ----------
    real
        Real satellite scene on the 0.5 m grid, (bands, rows, cols), DN.
    simulate
        ``simulate(q)`` → the paper's model at Q = q on the same grid (bands, rows, cols).
    q_base
        The baseline Q (Laplacian-variance calibration).
    rng
        Generator for the noise realisation of the refined simulation.
    valid
        Bool (rows, cols), True = usable in both images.
    gsd_m
        Pixel size of the grid, metres (for shifts in metres and areas).
    q_lo, q_hi
        Range of Q for the refit (default q_hi: max(2.5, 1.3·q_base)).
    block_px
        Welch block side (default 32, or 64 for scenes of at least 640 px).
    quantized
        Whether the real scene holds whole DN (default: detected).

    Returns
    -------
    Diagnosis
    """
    r = np.asarray(real, dtype=float)
    if r.ndim == 2:
        r = r[np.newaxis]
    rows, cols = r.shape[-2:]
    valid = np.ones((rows, cols), bool) if valid is None else np.asarray(valid, bool)
    if block_px is None:
        block_px = 64 if min(rows, cols) >= 640 else 32
    if quantized is None:
        quantized = bool(np.all(r[:, valid] == np.round(r[:, valid])))
    base = np.asarray(simulate(q_base), float)
    if base.ndim == 2:
        base = base[np.newaxis]
    rg = _grey(r)
    bg = _grey(base)
    effects_out: list[dict[str, Any]] = []

    # 1. co-registration -------------------------------------------------------------
    est = estimate_shift(bg, rg, valid=valid, block_px=block_px)
    mag = float(np.hypot(*est.shift_px))
    sig = float(np.hypot(*est.sigma_px))
    misreg = mag >= MIN_SHIFT_PX and est.delta_bic >= MIN_DELTA_BIC and mag > 3 * sig
    shift = est.shift_px if misreg else (0.0, 0.0)
    # local shifts: rotation / scale between the products (e.g. a UAV georeference error)
    whole = (float(np.round(est.shift_px[0])), float(np.round(est.shift_px[1])))
    aff = estimate_affine(fourier_shift(bg, whole), rg, valid=valid, block_px=16)
    field = None
    if aff.n_blocks >= 6 and np.isfinite(aff.residual_px):
        corners = np.array([[0, 0], [cols, 0], [0, rows], [cols, rows]], float) - \
            np.array(aff.centre_px)
        linear_px = float(np.max(np.hypot(*(aff.matrix @ corners.T))))
        if linear_px >= MIN_SHIFT_PX:
            dcol, drow = aff.field((rows, cols))
            field = (dcol + whole[0], drow + whole[1])
            misreg = True
    comp = get_effect("compression")

    # invalid pixels take their nearest valid value, so that shifting never pulls fill
    # values (zeros) into the valid area
    fill_idx = None
    if not valid.all():
        fill_idx = ndimage.distance_transform_edt(~valid, return_distances=False,
                                                  return_indices=True)

    def raw_at(q: float) -> np.ndarray:
        s = np.asarray(simulate(q), float)
        s = s[np.newaxis] if s.ndim == 2 else s
        if fill_idx is not None:
            s = s[:, fill_idx[0], fill_idx[1]]
        if field is not None:
            return warp_by_field(s, *field)
        return fourier_shift(s, shift) if misreg else s

    # 1b. compression: 8×8 block steps in the baseline residual ------------------------
    def band_affine(model: np.ndarray, mask: np.ndarray) -> np.ndarray:
        out = np.empty_like(model)
        for b in range(model.shape[0]):
            a = np.column_stack([model[b][mask], np.ones(mask.sum())])
            sol, *_ = np.linalg.lstsq(a, r[b][mask], rcond=None)
            out[b] = sol[0] * model[b] + sol[1]
        return out

    base_aff = band_affine(raw_at(q_base), valid)
    blk = blockiness(_grey(r - base_aff), valid)
    compressed = (blk["row_ratio"] > 1.08 and blk["col_ratio"] > 1.08
                  and min(blk["row_z"], blk["col_z"]) > 5.0)
    offset_px = (blk["row_phase"] % 8, blk["col_phase"] % 8)
    quality = None
    if compressed:
        # the right quality removes the block steps from the residual: coarse, then fine
        def steps_left(qual: int) -> float:
            b2 = blockiness(_grey(r - comp.apply(base_aff, quality=qual,
                                                   block_offset_px=offset_px)), valid)
            return abs(b2["row_excess_dn2"] + b2["col_excess_dn2"])

        coarse = min((10, 20, 30, 40, 50, 60, 70, 80, 90, 95), key=steps_left)
        fine = [q for q in range(max(5, coarse - 8), min(100, coarse + 9), 2)]
        quality = min(fine, key=steps_left)

    def sim_at(q: float) -> np.ndarray:
        s = raw_at(q)
        return comp.apply(s, quality=quality, block_offset_px=offset_px) if compressed else s

    # 2. first pass of scene-change regions from the baseline -------------------------
    def affine_residual(model_g: np.ndarray, mask: np.ndarray) -> np.ndarray:
        a = np.column_stack([model_g[mask], np.ones(mask.sum())])
        sol, *_ = np.linalg.lstsq(a, rg[mask], rcond=None)
        return rg - (sol[0] * model_g + sol[1])

    e0 = affine_residual(_grey(sim_at(q_base)), valid)
    inner0 = ndimage.binary_erosion(valid, np.ones((5, 5)), border_value=0)
    en0 = locate.residual_energy_map(np.where(inner0, e0, 0))
    exp0 = max(float(np.median(en0[inner0])), MIN_REGION_DN2)
    regions0, labels0 = locate.find_regions(en0, valid=inner0, expected_dn2=exp0,
                                            ratio_threshold=8.0)
    sc_mask = locate.regions_mask(labels0, regions0, kind=None)
    fit_mask = valid & ~sc_mask

    # 3. spectra against a Q grid of exact simulations --------------------------------
    if q_hi is None:
        q_hi = max(2.5, 1.3 * q_base)
    n_q = int(np.ceil(np.log(q_hi / q_lo) / np.log(1.12))) + 1
    q_grid = np.exp(np.linspace(np.log(q_lo), np.log(q_hi), n_q))
    sims_grey = [_grey(sim_at(q)) for q in q_grid]
    base_g = _grey(sim_at(q_base))
    while True:  # smaller Welch blocks when changes leave too few whole blocks
        origins = block_origins((rows, cols), block_px=block_px, valid=fit_mask)
        origins, rho = screen_blocks(base_g, rg, origins, block_px)
        if len(origins) >= MIN_BLOCKS or block_px <= 16:
            break
        block_px //= 2
    if len(origins) < 8:  # hard minimum
        from geosim.errors import DiagnosisError

        raise DiagnosisError(f"real scene: only {len(origins)} fully valid {block_px}×{block_px} "
                             "blocks on the 0.5 m grid; the diagnosis needs at least 8 — give a "
                             "larger common extent")
    n_screened = len(rho) - len(origins)
    mid = cols / 2.0
    oa = [o for o in origins if o[1] + block_px / 2 < mid]
    ob = [o for o in origins if o[1] + block_px / 2 >= mid]
    full = build_spectral_data(sims_grey, q_grid, rg, origins=origins, block_px=block_px)
    halves = (None, None)
    if len(oa) >= 4 and len(ob) >= 4:
        halves = (build_spectral_data(sims_grey, q_grid, rg, origins=oa, block_px=block_px),
                  build_spectral_data(sims_grey, q_grid, rg, origins=ob, block_px=block_px))

    # 4. blur effects by forward selection ------------------------------------------
    sel = select_blur(full, *halves, candidates=blur_candidates,
                      q_starts=(float(np.clip(q_base, q_lo, q_hi)), 1.5))
    fin = sel.final

    # 5. radiometry on the blurred model -------------------------------------------
    def det_model(q: float, eff: dict[str, dict[str, float]]) -> np.ndarray:
        return _blur_apply(sim_at(q), eff)

    m_blur = det_model(fin.q, fin.effects)
    # gains/offsets from large-scale brightness (σ = 2 px low-pass): a model that carries
    # aliasing or noise the scene does not share would otherwise bias the slope low
    # (regression dilution)
    def lowpass(img: np.ndarray) -> np.ndarray:
        return np.stack([ndimage.gaussian_filter(b, RADIOMETRY_SIGMA_PX) for b in img])

    corr = 4.0 * np.pi * RADIOMETRY_SIGMA_PX**2
    # an exposure seam of the UAV mosaic (one side of a line brighter in every band) gives
    # two radiometric relations; one regression would thread between them and absorb the
    # seam into the satellite's haze: fit the haze on the seam-corrected model instead
    lp_blur, lp_real = lowpass(m_blur), lowpass(r)
    seam = find_gain_step(lp_blur, lp_real, fit_mask, corr_px2=corr)
    if seam is not None:
        seam_gain = np.where(seam.side, seam.factor, 1.0)
        m_blur = m_blur * seam_gain
        lp_blur = lp_blur * seam_gain
    rad = fit_radiometry(lp_blur, lp_real, fit_mask, corr_px2=corr)
    rsel = select_radiometry(rad, corr_px2=corr)
    if rsel["name"] == "haze":
        p = rsel["params"]
        m_rad = get_effect("haze").apply(m_blur, **p)  # type: ignore[arg-type]
    elif rsel["name"] == "colour_response":
        p = rsel["params"]
        m_rad = m_blur * np.asarray(p["gain"])[:, None, None]  # type: ignore[index]
        if "offset_dn" in p:  # type: ignore[operator]
            m_rad = m_rad + np.asarray(p["offset_dn"])[:, None, None]  # type: ignore[index]
    else:
        m_rad = m_blur

    resid = r - m_rad
    # 7. noise from the high-passed residual ----------------------------------------
    hp = resid - np.stack([ndimage.gaussian_filter(b, 1.0) for b in resid])
    nf = fit_noise(hp / np.sqrt(_hp_factor(1.0)), m_rad, fit_mask, quantized=quantized)
    sigma_floor = 1.0 / 12.0 if quantized else 0.05
    x = (nf.mean_variance_dn2 + nf.quantization_dn2) / sigma_floor
    n_px = int(fit_mask.sum()) * r.shape[0]
    noise_dbic = float(n_px * (x - 1 - np.log(x)) - 2 * np.log(n_px)) if x > 1 else 0.0
    noisy = (nf.mean_variance_dn2 >= MIN_NOISE_VAR_DN2 and noise_dbic >= MIN_DELTA_BIC
             and nf.mean_variance_dn2 > 5 * max(nf.mean_variance_sigma, 1e-9))

    # 8. final model, regions, metrics ----------------------------------------------
    refined_det = m_rad
    refined = m_rad
    if noisy:
        refined = get_effect("sensor_noise").apply(m_rad, rng=rng, gain_dn=nf.gain_dn,
                                                   read_var_dn2=nf.read_var_dn2)
    if quantized:  # delivered like the real product, in whole DN
        refined = np.round(refined)
    e_final = _grey(r - refined_det)
    inner = ndimage.binary_erosion(valid, np.ones((5, 5)), border_value=0)
    energy = locate.residual_energy_map(np.where(inner, e_final, 0))
    expected = max(float(np.median(energy[inner])), MIN_REGION_DN2,
                   0.447 * (nf.mean_variance_dn2 + nf.quantization_dn2))
    regions, labels = locate.find_regions(energy, valid=inner, expected_dn2=expected,
                                          ratio_threshold=6.0)
    # metrics over the pixels where both images show the same scene: outside every region
    sc_final = locate.regions_mask(labels, regions, kind=None)
    eval_mask = ndimage.binary_erosion(valid, np.ones((5, 5)), border_value=0) & ~sc_final
    ev_origins = block_origins((rows, cols), block_px=block_px, valid=eval_mask)
    if len(ev_origins) < 4:
        ev_origins = origins

    def metrics(img: np.ndarray) -> tuple[float, float]:
        """RMSE of the expected image; spectral error of the image as delivered (whole DN
        when the real product is quantized, so both carry the same rounding floor)."""
        delivered = np.round(img) if quantized else img
        return (_rmse(img, r, eval_mask),
                spectral_error(_grey(delivered), rg, block_px=block_px, origins=ev_origins))

    base_rmse, base_se = metrics(base)
    # cumulative effect list with metrics after each
    steps: list[tuple[str, dict[str, Any], float, dict[str, Any], np.ndarray, np.ndarray]] = []
    if misreg:
        if field is not None:
            d = (aff.shift_px[0] + whole[0], aff.shift_px[1] + whole[1])
            mparams: dict[str, Any] = {
                "shift_px": [d[0], d[1]], "shift_m": [d[0] * gsd_m, -d[1] * gsd_m],
                "rotation_deg": aff.rotation_deg, "scale": aff.scale,
                "local_residual_px": aff.residual_px, "at_px": list(aff.centre_px)}
        else:
            d = est.shift_px
            mparams = {"shift_px": [d[0], d[1]], "shift_m": list(est.shift_m(gsd_m))}
        m0 = sim_at(q_base)
        # image-domain evidence: grey residual (after an affine radiometric match) before and
        # after moving the simulation; residuals correlate over ≈ 4 px
        n_ind = max(eval_mask.sum() / 4.0, 3.0)
        rss0 = float(np.sum(affine_residual(bg, eval_mask)[eval_mask] ** 2))
        rss1 = float(np.sum(affine_residual(_grey(m0), eval_mask)[eval_mask] ** 2))
        k = 6 if field is not None else 2
        m_dbic = float(n_ind * np.log(max(rss0, 1e-12) / max(rss1, 1e-12)) - k * np.log(n_ind))
        steps.append(("misregistration", mparams, m_dbic,
                      {"shift_px": list(est.sigma_px)}, m0, m0))
    if compressed:
        det = sim_at(q_base)
        steps.append(("compression", {"quality": quality, "block_offset_px": list(offset_px)},
                      float(min(blk["row_z"], blk["col_z"]) ** 2), dict(blk), det, det))
    for st in sel.steps:
        m = det_model(st.fit.q, st.fit.effects)
        steps.append((st.name, dict(st.fit.effects[st.name]), st.delta_bic,
                      {**st.fit.sigmas.get(st.name, {}), "heldout_gain": st.heldout_gain,  # type: ignore[dict-item]
                       "q": st.fit.q, "alternatives": st.alternatives}, m, m))
    if seam is not None:
        steps.append(("exposure_seam", {
            "factor": seam.factor, "normal_deg": seam.normal_deg, "offset_px": seam.offset_px,
            "fraction": seam.fraction, "line_px": seam.endpoints_px()}, seam.delta_bic,
            {"explained": seam.explained}, m_blur, m_blur))
    if rsel["name"]:
        steps.append((str(rsel["name"]), dict(rsel["params"]),  # type: ignore[arg-type]
                      float(rsel["delta_bic"]), dict(rsel.get("sigmas", {})),  # type: ignore[arg-type]
                      m_rad, m_rad))
    if noisy:
        steps.append(("sensor_noise", {"gain_dn": nf.gain_dn, "read_var_dn2": nf.read_var_dn2},
                      noise_dbic, {"gain_dn": nf.gain_sigma, "read_var_dn2": nf.read_sigma},
                      refined_det, refined))
    sc_regions = [g for g in regions if g.kind == "scene_change"]
    if sc_regions:
        area = sum(g.area_px for g in sc_regions) * gsd_m**2
        # evidence: region pixels have a larger residual variance than the rest
        in_sc = locate.regions_mask(labels, regions, dilate_px=0) & inner
        out_sc = inner & ~sc_final
        n_in = max(in_sc.sum() / 4.0, 1.0)
        v_in = float(np.mean(e_final[in_sc] ** 2)) if in_sc.any() else 0.0
        v_out = max(float(np.mean(e_final[out_sc] ** 2)) if out_sc.any() else 1e-12, 1e-12)
        sc_dbic = float(n_in * (v_in / v_out - 1 - np.log(max(v_in / v_out, 1e-12)))
                        - 2 * len(sc_regions) * np.log(max(inner.sum() / 4.0, 2.0)))
        steps.append(("scene_change", {"n_regions": len(sc_regions), "area_m2": area},
                      sc_dbic, {}, refined_det, refined))
    for name, params, dbic, sigmas, det, sto in steps:
        rm, _ = metrics(det)
        _, se = metrics(sto)
        alts = sigmas.pop("alternatives", []) if isinstance(sigmas, dict) else []
        entry = {"name": name, "params": params, "uncertainty": sigmas,
                 "explanation": get_effect(name).describe(params),
                 "signature": get_effect(name).signature,
                 "delta_bic": dbic, "rmse_after": rm, "spectral_error_after": se}
        if alts:
            entry["indistinguishable_from"] = alts
        effects_out.append(entry)
    ref_rmse, _ = metrics(refined_det)
    _, ref_se = metrics(refined)
    ambiguities = [{"claimed": st.name, "alternatives": st.alternatives,
                    "note": (f"{st.name} and {', '.join(st.alternatives)} explain the measured "
                             "transfer function about equally well (ΔBIC within 6); the data "
                             "cannot tell them apart")}
                   for st in sel.steps if st.alternatives]
    lv_real = locate.laplacian_variance(rg, valid)
    lv_base = locate.laplacian_variance(bg, valid)
    qs = fin.sigmas.get("q", float("nan"))
    summary: dict[str, Any] = {
        "baseline": {"q": float(q_base), "lv_satellite": lv_real, "lv_simulated": lv_base,
                     "rmse": base_rmse, "spectral_error": base_se},
        "effects": effects_out,
        "refined": {"q": float(fin.q), "q_sigma": float(qs),  # type: ignore[arg-type]
                    "q_in_physical_range": bool(PHYSICAL_Q[0] <= fin.q <= PHYSICAL_Q[1]),
                    "q_at_fit_bound": bool(fin.q <= q_grid[0] * 1.01 or fin.q >= q_grid[-1] / 1.01),
                    "physical_q_range": list(PHYSICAL_Q),
                    "rmse": ref_rmse, "spectral_error": ref_se,
                    "rmse_note": "rmse of the noise-free models; spectral_error of the "
                                 "simulations as delivered (with the refined noise realisation, "
                                 "rounded to whole DN when the real scene is)"},
        "ambiguities": ambiguities,
        "candidates_delta_bic": {k: float(v) for k, v in sel.tried.items()},
        "candidates_at_bound": sorted(sel.at_bound),
        "coregistration": {"shift_px": list(est.shift_px), "sigma_px": list(est.sigma_px),
                           "delta_bic": float(est.delta_bic), "applied": bool(misreg)},
        "noise": {"gain_dn": nf.gain_dn, "read_var_dn2": nf.read_var_dn2,
                  "variance_at_mean_dn2": nf.mean_variance_dn2,
                  "variance_at_mean_sigma_dn2": nf.mean_variance_sigma, "claimed": bool(noisy),
                  "quantized": bool(quantized)},
        "compression_test": blk,
        "radiometry_bic": rsel["bic"],
        "settings": {"block_px": block_px, "q_grid": [float(q) for q in q_grid],
                     "n_blocks": full.n_blocks, "held_out": halves[0] is not None,
                     "blocks_screened_out": n_screened},
    }
    # maps (against the co-registered baseline, so that a global shift does not show up as
    # local blur or loss of gain everywhere) --------------------------------------------
    bg_al = _grey(sim_at(q_base))  # baseline after co-registration
    maps = {
        "residual_energy": np.where(valid, energy, np.nan),
        "blur_ratio": locate.local_blur_ratio(bg_al, rg, valid=valid),
    }
    gmap, omap = locate.local_gain_offset(bg_al, rg, valid=valid)
    maps["gain"], maps["offset"] = gmap, omap
    # plot data -------------------------------------------------------------------
    # Transfer functions, all on the fit's Welch blocks and relative to the sharpest
    # simulation: the real scene's H1 = S_rs/S_ss, and the models *as fitted to it*, i.e.
    # times the broadband gain g of the spectral fit. g (< 1) holds the contrast loss of the
    # radiometry (haze) and the coherence loss from content the two images do not share
    # (other shadows, moved cattle, sub-pixel local shifts), which lowers H1 at all
    # frequencies; without it the model curves would sit above the real one although they
    # fit it (see the README's note on this plot).
    g_base = fit_transfer(full, [], fix_q=float(np.clip(q_base, q_grid[0], q_grid[-1]))).gain
    cs_real = cross_spectrum(sims_grey[0], rg, block_px=block_px, origins=origins)
    fy, fx = cs_real.fy, cs_real.fx
    t_real = np.abs(cs_real.transfer)
    t_var = (1.0 - np.clip(cs_real.coherence, 1e-6, 1 - 1e-9)) / (
        2.0 * cs_real.n_blocks * np.clip(cs_real.coherence, 1e-6, 1.0)) * t_real**2
    g_base_t = g_base * np.abs(full_transfer(sims_grey[0], bg_al, block_px, origins))
    blur_only = _grey(det_model(fin.q, fin.effects))
    g_ref_t = fin.gain * np.abs(full_transfer(sims_grey[0], blur_only, block_px, origins))
    # power spectra of the images as delivered (what spectral_error compares)
    delivered_base = np.round(base) if quantized else base
    p_real = cross_spectrum(rg, rg, block_px=block_px, origins=ev_origins).s_ss
    p_base = cross_spectrum(_grey(delivered_base), rg, block_px=block_px,
                            origins=ev_origins).s_ss
    p_ref = cross_spectrum(_grey(np.round(refined) if quantized else refined), rg,
                           block_px=block_px, origins=ev_origins).s_ss
    plots = {"fy": fy, "fx": fx, "t_real": t_real, "t_real_var": t_var, "t_base": g_base_t,
             "t_refined": g_ref_t, "gain_base": float(g_base), "gain_refined": float(fin.gain),
             "coherence_base": cs_real.coherence,
             "p_real": p_real, "p_base": p_base, "p_refined": p_ref,
             "spectral_error": (base_se, ref_se),
             "noise_brightness": nf.brightness_dn, "noise_variance": nf.variance_dn2,
             "noise_model": (nf.gain_dn, nf.read_var_dn2 + nf.quantization_dn2),
             "noise_claimed": bool(noisy), "quantized": bool(quantized),
             "q_ref": float(q_grid[0]), "q_base": float(q_base), "q_refined": float(fin.q)}
    f, prof = radial_profile(t_real, fy, fx)
    plots["radial_f"] = f
    plots["radial_real"] = prof
    return Diagnosis(summary=summary, real=r, baseline=base, refined=refined, valid=valid,
                     maps=maps, regions=regions, labels=labels, plots=plots)


def full_transfer(ref: np.ndarray, other: np.ndarray, block_px: int,
                  origins: list[tuple[int, int]]) -> np.ndarray:
    """Transfer function other / ref on the full block FFT grid."""
    return cross_spectrum(ref, other, block_px=block_px, origins=origins).transfer
