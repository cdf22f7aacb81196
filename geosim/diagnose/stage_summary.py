"""What the diagnosis reports besides the claims: the JSON-able summary
(:func:`make_summary`), the mismatch maps (:func:`mismatch_maps`) and the plot data
(:func:`plot_data`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from geosim.diagnose import locate
from geosim.diagnose.context import EvalContext
from geosim.diagnose.detection_limits import MeasuredTransfer, detection_limits_json
from geosim.diagnose.fit import fit_transfer
from geosim.diagnose.model import Claim, ForwardModel
from geosim.diagnose.select import BlurSelection, bic_evidence
from geosim.diagnose.spectra import cross_spectrum, radial_profile
from geosim.diagnose.stage_aliasing import resampling_detection_limit
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs, grey, rmse
from geosim.diagnose.stage_jpeg import blockiness
from geosim.diagnose.stage_radiometry import band_affine

__all__ = ["make_summary", "mismatch_maps", "plot_data", "full_transfer", "PHYSICAL_Q"]

PHYSICAL_Q = (0.5, 2.0)


def _ambiguity_note(claim: Claim) -> str:
    """Why a claim has alternatives: blurs tie on held-out blocks, radiometric names on
    BIC (their alternatives carry ``delta_bic``, not ``heldout_gain``)."""
    names = ", ".join(a["name"] for a in claim.alternatives)
    if all("heldout_gain" not in a for a in claim.alternatives):
        return (f"{claim.name} and {names} explain the pixels about equally well (BIC "
                "within the claiming margin); the data cannot tell them apart")
    named = [a["delta_bic"] for a in claim.alternatives if a.get("delta_bic") is not None]
    if not named:
        return (f"{claim.name} and {names} predict the held-out blocks about equally well "
                "(same family); the data cannot tell them apart")
    d = min(named)
    return (f"{claim.name} and {names} predict the held-out blocks about equally well "
            f"(same family); {claim.name} is named because its fit on all blocks is better "
            f"by ΔBIC {d:.1f}, evidence {bic_evidence(d)} (Kass & Raftery)")


def make_summary(inp: Inputs, model: ForwardModel, sel: BlurSelection, setup: SpectralSetup,
                 claims: list[Claim], ev: EvalContext, refined: np.ndarray,
                 withdrawn: list[dict[str, str]], *, resampling_tested: bool = True,
                 whole: EvalContext | None = None) -> dict[str, Any]:
    """The JSON-able summary written to ``diagnosis.json`` (baseline, effects, refined
    fit, ambiguities, detection limits at the delivered Q, withdrawals, candidates,
    co-registration, noise, settings); RMSEs
    over ``ev.mask``, spectral errors on ``ev``'s blocks. ``resampling_tested``: whether
    resampling was among the candidates (its detection limit is then stated too);
    ``whole``: the judgement over every valid block, the changed regions included
    (:func:`~geosim.diagnose.context.whole_extents`; ``spectral_error_whole`` of the
    baseline and the refined simulation, NaN without)."""
    eval_mask, se_of = ev.mask, ev.spectral_error
    base_rmse = rmse(inp.base, inp.real, eval_mask)
    base_se = se_of(np.round(inp.base) if inp.quantized else inp.base)
    ref_rmse = rmse(model.deterministic(inp.simulate), inp.real, eval_mask)
    ref_se = se_of(refined)
    whole_base, whole_ref = ((whole.spectral_error(np.round(inp.base) if inp.quantized
                                                   else inp.base),
                              whole.spectral_error(refined)) if whole is not None
                             else (float("nan"), float("nan")))
    ambiguities = [{"claimed": c.name, "alternatives": [a["name"] for a in c.alternatives],
                    "note": _ambiguity_note(c)} for c in claims if c.alternatives]
    reg, n = model.registration, model.noise
    qs = sel.final.sigmas.get("q", float("nan"))
    q_grid = setup.q_grid
    # at the delivered Q, weighed by how well this scene measures the transfer (and, for
    # resampling, its power spectrum)
    limits = detection_limits_json(
        float(model.q),  # type: ignore[arg-type]
        MeasuredTransfer.of(setup.full, float(model.q), model.blur))  # type: ignore[arg-type]
    if resampling_tested:
        limits["resampling"] = resampling_detection_limit(inp, model, setup, ev).to_json()
    return {
        "baseline": {"q": inp.q_base, "lv_satellite": locate.laplacian_variance(inp.grey,
                                                                                inp.valid),
                     "lv_simulated": locate.laplacian_variance(grey(inp.base), inp.valid),
                     "rmse": base_rmse, "spectral_error": base_se,
                     "spectral_error_whole": whole_base},
        "effects": [c.to_json() for c in claims],
        "refined": {"q": float(model.q), "q_sigma": float(qs),  # type: ignore[arg-type]
                    "q_in_physical_range": bool(PHYSICAL_Q[0] <= model.q <= PHYSICAL_Q[1]),
                    "q_at_fit_bound": bool(model.q <= q_grid[0] * 1.01
                                           or model.q >= q_grid[-1] / 1.01),
                    "physical_q_range": list(PHYSICAL_Q),
                    "rmse": ref_rmse, "spectral_error": ref_se,
                    "spectral_error_whole": whole_ref,
                    "rmse_note": "rmse of the noise-free models; spectral_error of the "
                                 "simulations as delivered (with the refined noise realisation, "
                                 "rounded to whole DN when the real scene is) on the blocks "
                                 "outside the changed regions, spectral_error_whole on every "
                                 "valid block (the changed regions included) of "
                                 "settings.block_px_whole",
                    # scene change modelled: the moved objects in the refined simulation
                    "moved_objects": ([o.to_json(inp.gsd_m) for o in model.objects.objects]
                                      if model.objects is not None else [])},
        "ambiguities": ambiguities,
        "detection_limits": limits,
        "withdrawn": withdrawn,
        "candidates_delta_bic": {k: float(v) for k, v in sel.tried.items()},
        "candidates_heldout_gain": {k: float(v) for k, v in sel.cv_gain.items()},
        "candidates_at_bound": sorted(sel.at_bound),
        "candidates_too_small": sorted(sel.too_small),
        "candidates_implausible": sorted(sel.implausible),
        "coregistration": {"shift_px": list(reg.estimate.shift_px),
                           "sigma_px": list(reg.estimate.sigma_px),
                           "delta_bic": float(reg.estimate.delta_bic),
                           "applied": bool(reg.applied)},
        "noise": {"gain_dn": n.gain_dn if n else 0.0, "read_var_dn2": n.read_var_dn2 if n else 0.0,
                  "white_variance_dn2": n.white_var_dn2 if n else 0.0,
                  "whiteness": n.whiteness if n else float("nan"),
                  "estimator": n.estimator if n else None,
                  "claimed": bool(n is not None and n.claimed), "quantized": inp.quantized},
        "compression_test": (model.compression.test if model.compression is not None
                             else blockiness(grey(inp.real - band_affine(
                                 reg.move(inp.base), inp.real, inp.valid)), inp.valid)),
        "radiometry_bic": model.radiometry.bic if model.radiometry is not None else {},
        "settings": {"block_px": setup.block_px,
                     "block_px_whole": whole.block_px if whole is not None else None,
                     "q_grid": [float(q) for q in q_grid],
                     "n_blocks": setup.full.n_blocks, "cv_folds": len(setup.folds),
                     "held_out": bool(setup.folds), "blocks_screened_out": setup.n_screened},
    }


def mismatch_maps(inp: Inputs, model: ForwardModel, energy: np.ndarray) -> dict[str, np.ndarray]:
    """Mismatch maps against the co-registered baseline (a global shift would otherwise
    show up as local blur or loss of gain everywhere)."""
    bg_al = grey(model.without(q=inp.q_base).sim_at(inp.simulate))
    maps = {"residual_energy": np.where(inp.valid, energy, np.nan),
            "blur_ratio": locate.local_blur_ratio(bg_al, inp.grey, valid=inp.valid)}
    maps["gain"], maps["offset"] = locate.local_gain_offset(bg_al, inp.grey, valid=inp.valid)
    return maps


def plot_data(inp: Inputs, model: ForwardModel, sel: BlurSelection, setup: SpectralSetup,
              ev: EvalContext, refined: np.ndarray, summary: dict[str, Any]
              ) -> dict[str, Any]:
    """Plot data. Transfer functions on the fit's blocks, relative to the sharpest
    simulation; the models *as fitted*, i.e. times the broadband gain g of the spectral
    fit (g < 1 holds haze contrast loss and coherence loss from unshared content). Power
    spectra on the evaluation blocks (``ev.origins``)."""
    ev_origins = ev.origins
    q_grid, bp, org = setup.q_grid, setup.block_px, setup.origins
    g_base = fit_transfer(setup.full, [], fix_q=float(np.clip(inp.q_base, q_grid[0],
                                                              q_grid[-1]))).gain
    sharpest = setup.tapered(setup.sims_grey[0])
    cs_real = cross_spectrum(sharpest, setup.tapered(inp.grey), block_px=bp, origins=org)
    t_real = np.abs(cs_real.transfer)
    t_var = (1.0 - np.clip(cs_real.coherence, 1e-6, 1 - 1e-9)) / (
        2.0 * cs_real.n_blocks * np.clip(cs_real.coherence, 1e-6, 1.0)) * t_real**2
    bg_al = setup.tapered(grey(model.without(q=inp.q_base).sim_at(inp.simulate)))
    g_base_t = g_base * np.abs(full_transfer(sharpest, bg_al, bp, org))
    blur_only = setup.tapered(grey(model.without(seam=None).blurred(inp.simulate)))
    g_ref_t = sel.final.gain * np.abs(full_transfer(sharpest, blur_only, bp, org))
    delivered_base = np.round(inp.base) if inp.quantized else inp.base
    p_real = cross_spectrum(inp.grey, inp.grey, block_px=bp, origins=ev_origins).s_ss
    p_base = cross_spectrum(grey(delivered_base), inp.grey, block_px=bp,
                            origins=ev_origins).s_ss
    p_ref = cross_spectrum(grey(refined), inp.grey, block_px=bp, origins=ev_origins).s_ss
    n = model.noise
    plots = {"fy": cs_real.fy, "fx": cs_real.fx, "t_real": t_real, "t_real_var": t_var,
             "t_base": g_base_t, "t_refined": g_ref_t, "gain_base": float(g_base),
             "gain_refined": float(sel.final.gain), "coherence_base": cs_real.coherence,
             "p_real": p_real, "p_base": p_base, "p_refined": p_ref,
             "spectral_error": (summary["baseline"]["spectral_error"],
                                summary["refined"]["spectral_error"]),
             "noise_brightness": n.brightness_dn if n else np.zeros(0),
             "noise_variance": n.variance_dn2 if n else np.zeros(0),
             "noise_model": ((n.gain_dn, n.read_var_dn2 + n.quantization_dn2) if n
                             else (0.0, 0.0)),
             "noise_claimed": bool(n is not None and n.claimed), "quantized": inp.quantized,
             "q_ref": float(q_grid[0]), "q_base": inp.q_base, "q_refined": float(model.q)}
    f, prof = radial_profile(t_real, cs_real.fy, cs_real.fx)
    plots["radial_f"] = f
    plots["radial_real"] = prof
    return plots


def full_transfer(ref: np.ndarray, other: np.ndarray, block_px: int,
                  origins: list[tuple[int, int]]) -> np.ndarray:
    """Transfer function other / ref on the full block FFT grid."""
    return cross_spectrum(ref, other, block_px=block_px, origins=origins).transfer
