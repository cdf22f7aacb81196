"""The diagnosis on arrays: co-register → locate → attribute → model → refit.

Pure numerics (no files): :func:`diagnose_arrays` takes the real scene on the
0.5 m grid and a callable giving the paper's model at any Q on the same grid, and
returns a :class:`Diagnosis` with the JSON-able summary, the three images
(real, baseline, refined), the mismatch maps and regions, and plot data.

This module is the orchestrator; each stage lives in its own module (see the code map in
``docs/diagnosis.md``): :func:`~geosim.diagnose.stage_register.coregister` →
:func:`~geosim.diagnose.stage_jpeg.find_compression` →
:func:`~geosim.diagnose.stage_change.changed_regions` →
:func:`~geosim.diagnose.stage_blur.select_with_q_room` (Q grid, Welch blocks, block
cross-validation folds, forward blur selection) →
:mod:`~geosim.diagnose.stage_jpeg_refit` (JPEG quality and blur together) →
:func:`~geosim.diagnose.stage_radiometry.fit_scene_radiometry` →
:func:`~geosim.diagnose.stage_noise.estimate_scene_noise` →
:func:`~geosim.diagnose.stage_jpeg_refit.delivered_q` (Q under JPEG on the delivered spectrum) →
:func:`~geosim.diagnose.stage_register.confirm_shift` (the shift against the refined model) →
:mod:`~geosim.diagnose.stage_aliasing`, :mod:`~geosim.diagnose.stage_resampling_coherent`
(under noise, a resampling by its aliasing in the pixels),
:mod:`~geosim.diagnose.stage_anisotropic_member` (the anisotropic member the transfer
named, checked against the other in the pixels),
:mod:`~geosim.diagnose.stage_isotropic_pixels` (beside a resampling or alone, an
isotropic blur by its trace in the pixels), :mod:`~geosim.diagnose.stage_anisotropic_pixels`
(an anisotropic blur by its trace in the pixels, alone or beside the model's other blurs),
:mod:`~geosim.diagnose.stage_jpeg_blur` (under JPEG, a resampling at high Q checked on the
scene's quantisation intervals, then a blur by them),
:mod:`~geosim.diagnose.stage_isotropic_refine` (a lone detector's or atmosphere's value
and Q refined on the delivered power spectrum) and
:mod:`~geosim.diagnose.stage_withdraw` (checks on the delivered spectrum; the refined
simulation may not fit worse than the baseline) →
:func:`~geosim.diagnose.stage_claims.claim_effects` →
:func:`~geosim.diagnose.stage_change.model_moved_objects` (a claimed scene change modelled
as moved objects, :mod:`~geosim.diagnose.stage_objects`), these three in
:func:`judge_refined`, judged again on the configured Welch blocks where the fit's were
smaller and the refined simulation is worse there (:func:`~geosim.diagnose.context.whole_extents`) →
:func:`~geosim.diagnose.stage_summary.make_summary`.

Where the first pass claims a scene change and models it as moved objects, the whole pass
runs again with those objects painted into the UAV ground
(:mod:`~geosim.diagnose.stage_painted`), and is kept where its refined simulation fits the
scene's spectrum better over every valid block.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from geosim.diagnose import locate
from geosim.diagnose.context import ChangedRegions, EvalContext, FitWindow, whole_extents
from geosim.diagnose.effects import BLUR_EFFECTS
from geosim.diagnose.model import Claim, ForwardModel
from geosim.diagnose.select import BlurSelection
from geosim.diagnose.spectra import block_origins
from geosim.diagnose.stage_aliasing import aliasing_test
from geosim.diagnose.stage_anisotropic_member import pixel_member
from geosim.diagnose.stage_anisotropic_pixels import pixel_anisotropic
from geosim.diagnose.stage_blur import SpectralSetup, adopt, select_with_q_room
from geosim.diagnose.stage_change import (
    MIN_REGION_DN2,
    changed_regions,
    model_moved_objects,
    resampling_phase_dn2,
)
from geosim.diagnose.stage_claims import claim_effects
from geosim.diagnose.stage_inputs import Inputs, grey, make_inputs, require_blocks
from geosim.diagnose.stage_isotropic_pixels import lone_possible, pixel_isotropic
from geosim.diagnose.stage_isotropic_refine import refine_lone_isotropic
from geosim.diagnose.stage_jpeg import blockiness, find_compression, jpeg_linearised
from geosim.diagnose.stage_jpeg_blur import censored_blur, censored_resampling_check
from geosim.diagnose.stage_jpeg_refit import (
    delivered_q,
    dithered_refit,
    joint_jpeg_blur,
    robust_then_exact,
)
from geosim.diagnose.stage_noise import estimate_scene_noise, noise_helps
from geosim.diagnose.stage_painted import (
    SecondPassJudgement,
    painted_inputs,
    second_pass_better,
)
from geosim.diagnose.stage_radiometry import fit_scene_radiometry
from geosim.diagnose.stage_register import confirm_shift, coregister, unapplied
from geosim.diagnose.stage_resampling_coherent import coherent_resampling
from geosim.diagnose.stage_summary import PHYSICAL_Q, make_summary, mismatch_maps, plot_data
from geosim.diagnose.stage_withdraw import (
    blur_at_q_floor,
    delivered_no_worse,
    jpeg_delivered_isotropic,
    jpeg_resampling_beyond_optics,
    never_worse,
)

__all__ = ["Diagnosis", "diagnose_arrays", "blockiness", "PHYSICAL_Q"]


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


@dataclass
class JudgedRefinement:
    """What :func:`judge_refined` keeps: the refined model, the effects it withdrew
    (``{"name", "reason"}``) and the claims made from what it kept."""

    model: ForwardModel
    withdrawn: list[dict[str, str]]
    claims: list[Claim]


def judge_refined(inp: Inputs, model: ForwardModel, sel: BlurSelection, setup: SpectralSetup,
                  ev: EvalContext, change: ChangedRegions, found: ForwardModel,
                  se_wholes: list[Callable[[np.ndarray], float]]) -> JudgedRefinement:
    """The refined model no worse than the baseline on ``ev``'s blocks and by every
    measure of ``se_wholes`` (:func:`~geosim.diagnose.stage_withdraw.never_worse`), the
    claims made from what it keeps (registration, compression, seam and radiometry as
    ``found``: the model the stages found, before any withdrawal), and a claimed scene
    change modelled as moved objects where they fit better by the same measures."""
    model, withdrawn = never_worse(inp, model, sel, setup, ev, se_wholes)
    claims = claim_effects(inp, model.without(registration=found.registration,
                                              compression=found.compression,
                                              seam=found.seam, radiometry=found.radiometry),
                           sel, change, ev)
    if any(c.name == "scene_change" for c in claims):
        # the claimed change modelled: moved objects in the refined simulation
        model = model_moved_objects(inp, model, change, ev, se_wholes)
        for c in claims:
            if c.name == "scene_change":
                c.params["n_objects_modelled"] = model.n_objects
    return JudgedRefinement(model=model, withdrawn=withdrawn, claims=claims)


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
    inp = make_inputs(real, simulate, q_base, valid, block_px, quantized, gsd_m)
    require_blocks(inp)
    if q_hi is None:
        q_hi = max(2.5, 1.3 * q_base)
    rng_first = copy.deepcopy(rng)
    first = _one_pass(inp, rng, q_lo, q_hi, blur_candidates)
    final, refit = first, None
    # a claimed change modelled as moved objects: the blurs measured again with the objects
    # painted into the UAV ground, on the whole scene (stage_painted)
    painted = (painted_inputs(inp, first.model)
               if any(c.name == "scene_change" for c in first.claims) else None)
    if painted is not None:
        # the noise measured where the ground did not move (painted objects may misfit)
        second = _one_pass(painted, rng, q_lo, q_hi, blur_candidates,
                           exclude=locate.regions_mask(first.labels, first.regions, kind=None),
                           defer_lone=False)
        refit = second_pass_better(
            first.ev, inp.valid, (inp.block_px, first.setup.block_px, second.setup.block_px),
            first.refined, second.refined)
        if refit is not None and refit.better:
            final, inp = _merge_passes(first, second), painted
    refit_json = _refit_json(painted is not None, refit, final is not first, first)
    refit_json["lone_isotropic_retested"] = final is first and first.lone_deferred
    if refit_json["lone_isotropic_retested"]:
        # no second pass kept to test a lone isotropic blur: the first pass again, with
        # the test and the same noise seed (development c278: a detector beside 40 moved
        # objects, the painted pass worse)
        first = final = _one_pass(inp, rng_first, q_lo, q_hi, blur_candidates,
                                  defer_lone=False)
    model, sel, setup, ev, claims = final.model, final.sel, final.setup, final.ev, final.claims
    summary = make_summary(inp, model, sel, setup, claims, ev, final.refined, final.withdrawn,
                           resampling_tested="resampling" in blur_candidates,
                           whole=final.wholes[0] if final.wholes else None)
    if final is not first:
        painted_objects = [o.to_json(inp.gsd_m) for o in first.model.objects.objects]
        summary["refined"]["moved_objects"] = (painted_objects
                                               + summary["refined"]["moved_objects"])
    summary["scene_change_refit"] = refit_json
    maps = mismatch_maps(inp, model, final.energy)
    plots = plot_data(inp, model, sel, setup, ev, final.refined, summary)
    return Diagnosis(summary=summary, real=inp.real, baseline=inp.base, refined=final.refined,
                     valid=inp.valid, maps=maps, regions=final.regions, labels=final.labels,
                     plots=plots)


@dataclass
class _Pass:
    """One pass of the diagnosis over the scene: the model it keeps, its claims and what
    the summary, maps and plots are made from."""

    model: ForwardModel
    sel: BlurSelection
    setup: SpectralSetup
    ev: EvalContext
    claims: list[Claim]
    refined: np.ndarray
    withdrawn: list[dict[str, str]]
    wholes: list[EvalContext]
    regions: list[locate.Region]
    labels: np.ndarray
    energy: np.ndarray
    lone_deferred: bool = False


def _one_pass(inp: Inputs, rng: np.random.Generator, q_lo: float, q_hi: float,
              blur_candidates: tuple[str, ...], exclude: np.ndarray | None = None,
              defer_lone: bool = True) -> _Pass:
    """Co-register → locate → attribute → model → refit, once, on ``inp``. ``exclude``:
    pixels (rows, cols) the noise is not measured on (the first pass's changed regions,
    where a second pass's painted objects may misfit); None: none. ``defer_lone``: the
    pixel test for a lone isotropic blur left out where moved objects are located
    (``_Pass.lone_deferred`` then says so)."""
    reg = coregister(inp)
    model = ForwardModel(q=inp.q_base, blur={}, registration=reg)
    model = model.without(compression=find_compression(inp, reg))
    regions0, labels0, _, _ = changed_regions(inp, grey(model.sim_at(inp.simulate)), ratio=8.0)
    fit_mask = inp.valid & ~locate.regions_mask(labels0, regions0, kind=None)
    window = FitWindow(mask=fit_mask, q_lo=q_lo, q_hi=q_hi, candidates=blur_candidates,
                       q_starts=(float(np.clip(inp.q_base, q_lo, q_hi)), 1.5))
    setup, sel = select_with_q_room(inp, model, window, jpeg_linearised(inp, model, fit_mask))
    model = adopt(model, sel)
    model, setup, sel = joint_jpeg_blur(inp, model, setup, sel, window)
    model, setup, sel = robust_then_exact(inp, model, setup, sel, window)
    model = fit_scene_radiometry(inp, model, fit_mask)
    noise_mask = fit_mask if exclude is None else fit_mask & ~exclude
    model = estimate_scene_noise(inp, model, setup, noise_mask)
    model, setup, sel = dithered_refit(inp, model, setup, sel, window)
    if model.compression is not None:
        # under JPEG, Q on the delivered spectrum; then the noise read again against that
        # model (a Q misfit reads as noise) and Q chosen again with it (noise missing from
        # the model reads as a sharper Q)
        q_fit = model.q
        model = delivered_q(inp, model, setup)
        if model.q != q_fit:
            model = delivered_q(inp, estimate_scene_noise(inp, model, setup, noise_mask), setup)
    # the global shift measured again against the refined model (the baseline's Q can be
    # far off, and its aliasing then biases the shift)
    reg = confirm_shift(inp, reg, grey(model.without(
        registration=unapplied(reg), compression=None).deterministic(inp.simulate)))
    model = model.without(registration=reg)
    # metrics over the pixels where both images show the same scene: outside every region
    noise_var = model.noise.white_var_dn2 if model.noise is not None else 0.0
    det = model.deterministic(inp.simulate)
    plain = det   # the model image before compression
    jpeg_dn2: np.ndarray | float = 0.0
    if model.compression is not None:
        # the real scene's JPEG error and the model's are independent where the pixels
        # differ (noise, texture): their residual carries both, ≈ twice the model's own
        plain = model.without(compression=None).deterministic(inp.simulate)
        jpeg_dn2 = 2.0 * locate.residual_energy_map(grey(det - plain))
    # and the aliasing of a resampling's native grid, whose phase is unknown
    regions, labels, energy, inner = changed_regions(
        inp, grey(det), ratio=6.0, floor_dn2=max(MIN_REGION_DN2, 0.447 * noise_var),
        affine=False, extra_dn2=jpeg_dn2 + resampling_phase_dn2(inp, model, plain))
    change = ChangedRegions(regions=regions, labels=labels, inner=inner)
    eval_mask = inner & ~locate.regions_mask(labels, regions, kind=None)
    ev_origins = block_origins(inp.valid.shape, block_px=setup.block_px, valid=eval_mask)
    if len(ev_origins) < 4:
        ev_origins = setup.origins
    ev = EvalContext(mask=eval_mask, origins=ev_origins, block_px=setup.block_px,
                     real_grey=inp.grey, noise_seed=int(rng.integers(0, 2**31 - 1)))
    model, withdrawn_noise = noise_helps(inp, model, ev)
    before = model
    model = aliasing_test(inp, model, sel, setup, ev, window.candidates)
    if before.noise is not None and before.noise.claimed and model.noise is None:
        # the resampling's aliasing took the noise's place: the noise judged again
        # against it, by the same rules
        model, withdrawn_again = noise_helps(
            inp, estimate_scene_noise(inp, model, setup, noise_mask), ev)
        withdrawn_noise = withdrawn_noise + withdrawn_again
    # under noise, a resampling by its aliasing in the pixels, where the spectrum cannot
    model = coherent_resampling(inp, model, sel, setup, ev, window.candidates)
    # an anisotropic member named by the transfer, checked against the other in the pixels
    model = pixel_member(inp, model, sel, setup, ev, window.candidates)
    # beside a resampling, an isotropic roll-off by its trace in the pixels; alone, not
    # where moved objects are located unless told (the second pass, on the ground with
    # them painted in, tests it; in the first it had preempted that pass: development
    # c304's atmosphere lost, c319's named a detector, c1104's fit no longer halved)
    deferred = (defer_lone and any(r.kind == "scene_change" for r in regions)
                and lone_possible(model, window.candidates))
    model = pixel_isotropic(inp, model, sel, setup, ev, window.candidates, lone=not deferred)
    # where the model holds no anisotropic member and no JPEG, such a blur by its pixels
    # (alone or beside the model's other blurs)
    model = pixel_anisotropic(inp, model, sel, setup, ev, window.candidates)
    # under JPEG at high Q, a resampling kept only where the quantisation intervals want it;
    # then a blur by those intervals, where the transfer cannot (not the one just withdrawn)
    model, withdrawn_censored = censored_resampling_check(inp, model, window, ev)
    model = censored_blur(inp, model, sel, setup, replace(window, candidates=tuple(
        n for n in window.candidates
        if n not in {w["name"] for w in withdrawn_censored})), ev)
    model, withdrawn_floor = blur_at_q_floor(inp, model, sel, setup, window.q_lo)
    model, withdrawn_alias = jpeg_resampling_beyond_optics(inp, model, sel, setup)
    # a lone detector or atmosphere: its value and Q refined on the delivered spectrum
    model = refine_lone_isotropic(inp, model, sel, setup, ev)
    found = model
    model, withdrawn_iso = jpeg_delivered_isotropic(inp, model, sel, setup, ev)
    # the same judgement over every valid block (the changed regions included) on the
    # fit's Welch blocks; where changes put the fit on smaller blocks than the configured
    # ones and the refined simulation as delivered is worse there, judged again on both
    wholes = whole_extents(ev, inp.valid, (inp.block_px, setup.block_px))
    fit_whole = [w for w in wholes if w.block_px == setup.block_px]
    judged = judge_refined(inp, model, sel, setup, ev, change, found,
                           [w.spectral_error for w in fit_whole])
    refined = judged.model.delivered(inp.simulate, np.random.default_rng(ev.noise_seed),
                                     quantized=inp.quantized)
    every = [w.spectral_error for w in wholes]
    if len(wholes) > len(fit_whole) and not delivered_no_worse(inp, ev, every)(refined):
        judged = judge_refined(inp, model, sel, setup, ev, change, found, every)
        refined = judged.model.delivered(inp.simulate, np.random.default_rng(ev.noise_seed),
                                         quantized=inp.quantized)
    model, claims = judged.model, judged.claims
    withdrawn = (withdrawn_noise + withdrawn_censored + withdrawn_floor + withdrawn_alias
                 + withdrawn_iso + judged.withdrawn)
    return _Pass(model=model, sel=sel, setup=setup, ev=ev, claims=claims, refined=refined,
                 withdrawn=withdrawn, wholes=wholes, regions=regions, labels=labels,
                 energy=energy, lone_deferred=deferred)


def _merge_passes(first: _Pass, second: _Pass) -> _Pass:
    """The second pass (moved objects painted into the ground) as the diagnosis, with the
    first's account of the change: its ``scene_change`` claim (the objects counted with
    any the second pass modelled on top) and its changed regions and residual energy
    (where the ground moved against the UAV image as flown)."""
    change = next(c for c in first.claims if c.name == "scene_change")
    change = replace(change, params={
        **change.params, "n_objects_modelled": first.model.n_objects + second.model.n_objects})
    claims = [c for c in second.claims if c.name != "scene_change"] + [change]
    return replace(second, claims=claims, regions=first.regions, labels=first.labels,
                   energy=first.energy)


def _refit_json(ran: bool, refit: SecondPassJudgement | None, kept: bool, first: _Pass
                ) -> dict[str, Any]:
    """``scene_change_refit`` of diagnosis.json: whether a second pass ran with the first
    pass's moved objects painted into the UAV ground, its measures (None where the valid
    extent holds too few whole blocks to judge it) and whether it was kept."""
    out: dict[str, Any] = {"ran": ran, "kept": kept,
                           "n_objects_painted": first.model.n_objects if ran else 0}
    if ran:
        out["first_pass_effects"] = [c.name for c in first.claims]
    if refit is not None:
        out.update(block_px=refit.block_px,
                   spectral_error_whole=[list(p) for p in refit.spectral_error_whole],
                   note="spectral_error_whole: [first pass, second pass] of the refined "
                        "simulation as delivered over every valid block, per block_px; "
                        "the second pass is kept only where it is lower on every one")
    return out
