"""The claimed effects in order, each with the fit after adding it (:func:`claim_effects`)."""

from __future__ import annotations

import numpy as np

from geosim.diagnose.context import ChangedRegions, EvalContext
from geosim.diagnose.model import Claim, ForwardModel
from geosim.diagnose.select import BlurSelection
from geosim.diagnose.stage_change import scene_change_claim
from geosim.diagnose.stage_inputs import Inputs, grey, rmse
from geosim.diagnose.stage_radiometry import affine_residual

__all__ = ["claim_effects"]


def claim_effects(inp: Inputs, model: ForwardModel, sel: BlurSelection,
                  change: ChangedRegions, ev: EvalContext) -> list[Claim]:
    """The claimed effects in order, each with the fit after adding it (cumulative).

    ``change``: the final pass's changed regions (a ``scene_change`` claim from its
    ``scene_change`` regions); ``ev``: each claim's RMSE over ``ev.mask`` and spectral
    error of the realisation of ``ev.noise_seed`` after adding it."""
    sim = inp.simulate
    eval_mask = ev.mask
    reg = model.registration
    empty = ForwardModel(q=inp.q_base, blur={}, registration=reg)
    out: list[tuple[Claim, ForwardModel]] = []
    if reg.applied:
        m0 = empty
        n_ind = max(eval_mask.sum() / 4.0, 3.0)  # residuals correlate over ≈ 4 px
        rss0 = float(np.sum(affine_residual(grey(inp.base), inp.grey, eval_mask)[eval_mask]
                            ** 2))
        rss1 = float(np.sum(affine_residual(grey(m0.sim_at(sim)), inp.grey,
                                            eval_mask)[eval_mask] ** 2))
        k = 6 if reg.field_px is not None else 2
        dbic = float(n_ind * np.log(max(rss0, 1e-12) / max(rss1, 1e-12)) - k * np.log(n_ind))
        out.append((Claim("misregistration", reg.params(inp.gsd_m),
                          {"shift_px": list(reg.estimate.sigma_px)}, dbic), m0))
    cur = empty
    if model.compression is not None:
        c = model.compression
        cur = cur.without(compression=c)
        # read from the scene's quantisation lattice, not fitted: no σ for the quality, and
        # the evidence in place of a ΔBIC is twice the lattice's log-likelihood gain over none
        out.append((Claim("compression", {"quality": c.quality,
                                          "block_offset_px": list(c.offset_px)},
                          {}, 2.0 * float(c.test["lattice_log_lik_gain"]),
                          test=dict(c.test)), cur))
    for st in sel.steps:
        if st.name not in model.blur:
            continue
        cur = cur.without(q=st.fit.q, blur={n: p for n, p in st.fit.effects.items()
                                            if n in model.blur})
        # 1-σ of the effect's parameters and of Q fitted with it (Q's σ, not its value;
        # none where the step held Q fixed, e.g. resampling's pitch scanned at the model's Q)
        unc = dict(st.fit.sigmas.get(st.name, {}))  # type: ignore[arg-type]
        q_sigma = float(st.fit.sigmas.get("q", 0.0))  # type: ignore[arg-type]
        if q_sigma > 0:
            unc["q"] = q_sigma
        alts = [{"name": a.name, "heldout_gain": a.cv_gain, "params": a.params,
                 **({} if a.delta_bic is None else {"delta_bic": a.delta_bic})}
                for a in st.alternatives]
        out.append((Claim(st.name, dict(st.fit.effects[st.name]), unc, st.delta_bic,
                          st.heldout_gain, alts, test=st.test), cur))
    cur = cur.without(q=model.q, blur=model.blur)
    if model.seam is not None:
        s = model.seam
        cur = cur.without(seam=s)
        out.append((Claim("exposure_seam", {
            "factor": s.factor, "normal_deg": s.normal_deg, "offset_px": s.offset_px,
            "fraction": s.fraction, "line_px": s.endpoints_px()}, {"explained": s.explained},
            s.delta_bic), cur))
    if model.radiometry is not None and model.radiometry.name:
        r = model.radiometry
        cur = cur.without(radiometry=r)
        out.append((Claim(r.name, r.params, r.sigmas, r.delta_bic,  # type: ignore[arg-type]
                          alternatives=r.alternatives), cur))
    if model.noise is not None and model.noise.claimed:
        n = model.noise
        cur = cur.without(noise=n)
        out.append((Claim("sensor_noise", {"gain_dn": n.gain_dn, "read_var_dn2": n.read_var_dn2},
                          {"gain_dn": n.gain_sigma, "read_var_dn2": n.read_sigma},
                          n.delta_bic), cur))
    sc = [g for g in change.regions if g.kind == "scene_change"]
    if sc:
        out.append((scene_change_claim(inp, model, sc, change), cur))
    claims = []
    for c, m in out:
        c.rmse_after = rmse(m.deterministic(sim), inp.real, eval_mask)
        c.spectral_error_after = ev.spectral_error(
            m.delivered(sim, np.random.default_rng(ev.noise_seed), quantized=inp.quantized))
        claims.append(c)
    return claims
