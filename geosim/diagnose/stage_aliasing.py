"""Resampling by its aliasing: claimed when the power it predicts (which the transfer fit
does not see) brings the delivered spectrum clearly closer (:func:`aliasing_test`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from geosim.diagnose.context import EvalContext
from geosim.diagnose.fit import TransferFit, evaluate_chi2, fit_transfer
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.resampling_limit import ResamplingLimit, resampling_limit
from geosim.diagnose.resampling_refine import refine_resampling
from geosim.diagnose.select import (
    AcceptedEffect,
    BlurSelection,
    at_bound,
    clearly_present,
    cv_chi2,
    delta_bic,
)
from geosim.diagnose.spectra import block_origins, spectral_error
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs, greys
from geosim.diagnose.stage_noise import realisations
from geosim.diagnose.stage_withdraw import Q_FLOOR_REL, jpeg_native_floor_px
from geosim.physics.cubic import KEYS_A, OPENCV_A

__all__ = ["aliasing_test", "refined_from", "split_halves", "resampling_detection_limit",
           "with_resampling", "pinned_in_scan", "PITCH_SCAN", "PITCH_STEP",
           "ALIASING_SPECTRAL_GAIN", "ALIASING_SPECTRAL_GAIN_SPLIT"]

#: resampling not chosen by the transfer fit is still claimed when its aliasing, which the
#: transfer fit does not see, brings the refined power spectrum this much closer (fraction
#: of the spectral error without it; set on the development half)
ALIASING_SPECTRAL_GAIN = 0.8
#: the same for a native pitch fitted on the power spectrum: on each held-out half of the
#: blocks (pitch chosen on the other half)
ALIASING_SPECTRAL_GAIN_SPLIT = 0.9
#: step of the native pitches scanned on the power spectrum, px
PITCH_STEP = 0.05
#: native pitches (0.5 m product pixels) scanned on the power spectrum: 1.15-2.0 px
PITCH_SCAN = np.round(np.arange(1.15, 2.0 + PITCH_STEP / 5, PITCH_STEP), 2)
#: the scan's best pairs refined on the power spectrum, and how far apart their pitches
#: must be, px
REFINE_STARTS = 2
REFINE_START_SEP_PX = 0.1


def split_halves(origins: list[tuple[int, int]], block_px: int, cols: int
                 ) -> list[list[tuple[int, int]]] | None:
    """Route 2's two halves of the Welch blocks: left and right of the scene's middle
    column (by block centre); None when either holds fewer than two blocks."""
    halves = [[o for o in origins if o[1] + block_px / 2 < cols / 2],
              [o for o in origins if o[1] + block_px / 2 >= cols / 2]]
    return None if min(len(h) for h in halves) < 2 else halves


def aliasing_test(inp: Inputs, model: ForwardModel, sel: BlurSelection, setup: SpectralSetup,
                  ev: EvalContext, candidates: tuple[str, ...]) -> ForwardModel:
    """Resampling leaves two traces: a roll-off of the coherent transfer, which Q and the
    isotropic blurs imitate (so forward selection on the transfer often takes those
    instead), and power the transfer fit does not see: aliasing and the spectral images
    of the cubic interpolation above the native Nyquist, incoherent with the scene.

    1. Resampling fitted on the transfer (jointly with the chosen blur; clearly present,
       not at a bound, not worse on the held-out blocks) is added when the power spectrum
       it predicts fits the real scene's clearly better (:data:`ALIASING_SPECTRAL_GAIN`).
    2. When the transfer cannot see it (optics at high Q cut the band where its roll-off
       lies), its native pitch and kernel (OpenCV's a = −0.75 or Keys' −0.5) are fitted on
       the power spectrum itself, by split halves: the pair chosen on the left half of the
       blocks must improve the right half's spectral error by the same margin, and vice
       versa. Each scanned pair is rendered with Q refitted on the transfer with that
       resampling held (:func:`with_resampling`): Q had taken up the resampling's
       roll-off, and the two at the Q fitted without it blur twice.
    3. A pitch the transfer gave (route 1, or forward selection) is moved to the scanned
       pitch of lowest spectral error (:func:`_pitch_on_spectrum`; not under JPEG).
    4. Pitch, Q and the native grid's phase are then refined together on the power
       spectrum (:func:`_on_spectrum`; in route 2 each half's choice on that half, before
       it is scored on the other); not under JPEG, where a resampling's spectrum is the
       mean over four native phases (:func:`phase_realisations`). Where noise is claimed
       each candidate is also scored without it (:func:`scan_on_transfer`); route 2 uses
       every valid block where ``ev``'s leave too few for its halves.

    Spectral errors on ``ev``'s blocks (route 2: its left and right halves), noise
    realisations from ``ev.noise_seed``; ``candidates``: the effects the fit may add
    (nothing is tested unless ``resampling`` is among them).
    """
    name = "resampling"
    if name not in candidates:
        return model

    def delivered(m: ForwardModel) -> list[np.ndarray]:
        # with noise claimed, the expected spectrum (mean of the realisations): one
        # realisation's scatter (±0.08 on small JPEG scenes) can pass for aliased power;
        # under JPEG, where the native phase is not fitted, over the phase as well
        if m.compression is not None and name in m.blur:
            return phase_realisations(inp, m, ev.noise_seed)
        return realisations(inp, m, ev.noise_seed)

    def se_all(m: ForwardModel) -> float:
        return ev.spectral_error(delivered(m))

    if name in model.blur:  # chosen by forward selection on the transfer
        moved = _selected_pitch_on_spectrum(sel, setup, model, se_all)
        return _refine_selected(sel, setup, moved, se_all)

    names = [*model.blur, name]
    fit = fit_transfer(setup.full, names, q_starts=(model.q, inp.q_base))
    params = fit.effects[name]
    prev = sel.steps[-1].fit if sel.steps else sel.null
    if not at_bound(name, params) and clearly_present(name, params):
        gain = float("nan")
        if setup.folds:
            cur = fit_transfer(setup.full, list(model.blur), q_starts=(model.q,)) \
                if model.blur else sel.null
            cv0 = cv_chi2(setup.folds, list(model.blur), cur)
            gain = 1.0 - cv_chi2(setup.folds, names, fit) / max(cv0, 1e-300)
        with_r = model.without(q=fit.q, blur=dict(fit.effects))
        se_r = ev.spectral_error(delivered(with_r))
        if gain >= 0 and se_r <= ALIASING_SPECTRAL_GAIN * se_all(model):
            fit, with_r = _pitch_on_spectrum(setup, fit, with_r, se_r, se_all)
            refined = _on_spectrum(setup, with_r, se_all)
            if refined is not with_r:
                fit, with_r = _moved_fit(setup, fit, refined), refined
            n_values = 2 * setup.full.t_real.size
            sel.steps.append(AcceptedEffect(name, delta_bic(prev, fit, n_values), gain, [], fit))
            sel.cv_gain[name] = gain
            sel.final = fit
            return with_r
    # route 2: the native pitch from the power spectrum, validated on split halves
    halves = split_halves(ev.origins, setup.block_px, inp.valid.shape[1])
    if halves is None:
        # too few blocks outside the changed regions: every valid block's (development
        # c692: regions flagged where the unmodelled aliasing of a true resampling was
        # strongest left 5 blocks; moved objects shift power between places, not
        # between frequencies, so the whole scene's spectrum still holds)
        halves = split_halves(block_origins(inp.valid.shape, block_px=setup.block_px,
                                            valid=inp.valid), setup.block_px,
                              inp.valid.shape[1])
    if halves is None:
        return model

    def se_on(img: list[np.ndarray], origins: list[tuple[int, int]]) -> float:
        return spectral_error(greys(img), inp.grey, block_px=setup.block_px, origins=origins)

    # each (kernel, pitch) at its own Q: the simulator keeps the fine image's DCT for the scan
    fitted = scan_on_transfer(setup, model)
    grid = list(fitted)
    imgs = [delivered(fitted[g][0]) for g in grid]
    none = delivered(model)
    se_h = np.array([[se_on(im, h) for h in halves] for im in imgs])   # (kernel·pitch, half)
    se0 = [se_on(none, h) for h in halves]

    def best(scores: np.ndarray, origins: list[tuple[int, int]]) -> ForwardModel:
        # the scan's best pairs with pitch, Q and phase refined together on these
        # blocks' spectrum, the lowest kept; under JPEG (as _pitch_on_spectrum) the
        # scan's best pair as scanned
        if model.compression is not None:
            return fitted[grid[int(np.argmin(scores))]][0]

        def score(m: ForwardModel) -> float:
            return se_on(delivered(m), origins)

        starts = [fitted[grid[j]][0] for j in refine_starts(scores, grid)]
        return refined_from(setup, starts, score)[0]

    heldout = []
    for k in (0, 1):  # choose (and refine) on half k, validate on the other
        heldout.append(1.0 - se_on(delivered(best(se_h[:, k], halves[k])), halves[1 - k])
                       / max(se0[1 - k], 1e-12))
    if min(heldout) < 1.0 - ALIASING_SPECTRAL_GAIN_SPLIT:
        return model
    j = int(np.argmin(se_h.sum(axis=1)))
    chosen = best(se_h.sum(axis=1), halves[0] + halves[1])
    fit_p = (fitted[grid[j]][1] if chosen is fitted[grid[j]][0]
             else _moved_fit(setup, fitted[grid[j]][1], chosen))
    if pinned_in_scan(chosen.blur[name]["native_pitch_px"]):
        # pinned at an end of the scan: the pitch stands in for a shape resampling does
        # not have (as a fitted parameter at a bound, never claimed by name; development:
        # 1.15 px where the truth was atmosphere at Q 4)
        return model
    # the transfer's view (reported): Q refitted with the spectrally fitted resampling
    # held; its uncertainty the scan's steps: 0.05 px in pitch, the kernel one of two
    # (0.25 apart)
    sigmas = {**prev.sigmas, **fit_p.sigmas,
              name: {"native_pitch_px": PITCH_STEP, "cubic_a": 0.25}}
    # parameters: the previous fit's (the other blurs held at its values) and the two
    # scanned here
    step_fit = replace(fit_p, sigmas=sigmas, n_params=prev.n_params + 2)
    # heldout_gain here: the held-out drop of the spectral error (the weaker half)
    sel.steps.append(AcceptedEffect(name, delta_bic(prev, step_fit, 2 * setup.full.t_real.size),
                                    float(min(heldout)), [], step_fit))
    sel.cv_gain[name] = float(min(heldout))
    sel.final = step_fit
    return chosen


def phase_realisations(inp: Inputs, m: ForwardModel, rng_seed: int) -> list[np.ndarray]:
    """The delivered simulation of ``m`` (which holds a resampling) with its native grid at
    four phases, half a cell apart along each axis (with noise claimed, one noise
    realisation each): their mean Welch power is the expected spectrum over a phase the
    model does not fit. Under JPEG one phase's render decides by its quantisation too: a
    0.01 DN change of the render (round 22's renderer) moved route 2's held-out gains by
    up to 0.4 (development c468, c682)."""
    half = 0.5 * float(m.blur["resampling"]["native_pitch_px"])
    r0, c0 = m.native_phase_px
    out: list[np.ndarray] = []
    for k, (dr, dc) in enumerate(((0.0, 0.0), (half, 0.0), (0.0, half), (half, half))):
        out += m.without(native_phase_px=(r0 + dr, c0 + dc)).delivered_realisations(
            inp.simulate, [np.random.default_rng(rng_seed + k)], quantized=inp.quantized)
    return out


def pinned_in_scan(pitch_px: float) -> bool:
    """At (within 0.01 px of) an end of :data:`PITCH_SCAN`."""
    return pitch_px <= PITCH_SCAN[0] + 0.01 or pitch_px >= PITCH_SCAN[-1] - 0.01


def scan_on_transfer(setup: SpectralSetup, model: ForwardModel
                     ) -> dict[tuple, tuple[ForwardModel, TransferFit]]:
    """Route 2's scan: each (kernel, pitch) of the two kernels processors use (OpenCV's
    a = −0.75, Keys' −0.5; the power spectrum barely constrains the kernel, and where the
    transfer cannot see resampling its fit of the kernel is arbitrary) × :data:`PITCH_SCAN`,
    with Q refitted on the transfer (:func:`with_resampling`); keys (kernel, pitch).

    Where ``model`` claims noise, each pair also without it (keys (kernel, pitch,
    "no noise")): power beyond the optics' reach that the model read as noise may be the
    native grid's aliases (development c252, c574, c692: noise claimed in noise-free
    scenes at Q 0.95-1.35, hiding the resampling); the engine judges the noise again
    against the model chosen."""
    out: dict[tuple, tuple[ForwardModel, TransferFit]] = {
        (float(a), float(p)): with_resampling(setup, model, {"native_pitch_px": float(p),
                                                             "cubic_a": float(a)})
        for a in (OPENCV_A, KEYS_A) for p in PITCH_SCAN}
    if model.noise is not None and model.noise.claimed:
        out |= {(*g, "no noise"): (m.without(noise=None), f) for g, (m, f) in list(out.items())}
    return out


def refine_starts(scores: np.ndarray, grid: list[tuple],
                  n: int = REFINE_STARTS, min_sep_px: float = REFINE_START_SEP_PX) -> list[int]:
    """Indices of the ``n`` lowest ``scores`` of the scan ``grid`` ((kernel, pitch, ...)
    keys) whose pitches lie at least ``min_sep_px`` apart: the aliasing's spectral minimum is
    narrow (±0.05 px) and the scan's Q only roughly right, so the lowest scanned pair may
    sit on a side minimum."""
    out: list[int] = []
    for j in np.argsort(scores, kind="stable"):
        if all(abs(grid[j][1] - grid[i][1]) >= min_sep_px for i in out):
            out.append(int(j))
        if len(out) == n:
            break
    return out


def refined_from(setup: SpectralSetup, starts: list[ForwardModel],
                 se_of: Callable[[ForwardModel], float]) -> tuple[ForwardModel, float]:
    """The lowest-scoring of ``starts`` (models with a resampling) and of their pitch, Q
    and native-grid phase refined together on the power spectrum
    (:func:`~geosim.diagnose.resampling_refine.refine_resampling`, within the pitch scan
    and the Q grid; each start's kernel and other blurs held).

    Neither a start nor a refinement at a bound (Q at the bottom of the grid, the pitch at
    an end of the scan) is taken; where every start is, the first is returned.

    Returns
    -------
    model, spectral error
        The best model (one of ``starts`` itself where no refinement scores lower) and
        its score.
    """
    name = "resampling"

    def at_bound(q: float, pitch_px: float) -> bool:
        # the search or the scan there stands in for something else (as blur_at_q_floor
        # and route 2's pinned pitch): development c16, c177 (Q 1.64, 0.85) had Q driven
        # to the bottom of the grid, with a false atmosphere held or the noise dropped
        return q <= Q_FLOOR_REL * float(setup.q_grid[0]) or pinned_in_scan(pitch_px)

    free = [m for m in starts if not at_bound(m.q, m.blur[name]["native_pitch_px"])]
    if not free:
        return starts[0], se_of(starts[0])
    se_best, i = min((se_of(m), i) for i, m in enumerate(free))
    best = free[i]
    for m in free:
        a = float(m.blur[name].get("cubic_a", OPENCV_A))

        def at(p: float, q: float, ph: tuple[float, float], m: ForwardModel = m,
               a: float = a) -> ForwardModel:
            return m.without(q=q, blur={**m.blur, name: {"native_pitch_px": p, "cubic_a": a}},
                             native_phase_px=ph)

        r = refine_resampling(lambda p, q, ph, at=at: se_of(at(p, q, ph)),
                              float(m.blur[name]["native_pitch_px"]), float(m.q),
                              m.native_phase_px,
                              pitch_bounds=(float(PITCH_SCAN[0]), float(PITCH_SCAN[-1])),
                              q_bounds=(float(setup.q_grid[0]), float(setup.q_grid[-1])))
        if r.spectral_error < se_best and not at_bound(r.q, r.native_pitch_px):
            best, se_best = at(r.native_pitch_px, r.q, r.phase_px), r.spectral_error
    return best, se_best


def _on_spectrum(setup: SpectralSetup, model: ForwardModel,
                 se_of: Callable[[ForwardModel], float]) -> ForwardModel:
    """A resampling the transfer chose (route 1, or forward selection), its pitch and Q
    refined together on the power spectrum from its own values and from the best pairs of
    route 2's scan (:func:`scan_on_transfer`, :func:`refine_starts`): the transfer, made
    incoherent by the aliasing below Q ≈ 2, can hold pitch and Q far from the spectrum's
    minimum (development c09: 1.26 px at Q 1.76 for 1.63 px at Q 1.01). ``model`` itself
    where nothing scores lower, and under JPEG (as :func:`_pitch_on_spectrum`)."""
    name = "resampling"
    if model.compression is not None:
        return model
    fitted = scan_on_transfer(setup, model)
    grid = list(fitted)
    scores = np.array([se_of(fitted[g][0]) for g in grid])
    a0 = float(model.blur[name].get("cubic_a", OPENCV_A))
    own = [model] if a0 in (OPENCV_A, KEYS_A) else [
        model.without(blur={**model.blur, name: {**model.blur[name], "cubic_a": a}})
        for a in (OPENCV_A, KEYS_A)]   # a kernel at the fit's bound: each real one
    if model.noise is not None and model.noise.claimed:   # as scan_on_transfer
        own += [m.without(noise=None) for m in own]
    best, se_best = refined_from(setup, own + [fitted[grid[j]][0]
                                               for j in refine_starts(scores, grid)], se_of)
    return best if se_best < se_of(model) else model


def _moved_fit(setup: SpectralSetup, fit: TransferFit, model: ForwardModel) -> TransferFit:
    """``fit`` with ``model``'s Q and resampling (refined on the spectrum)
    (:func:`_fit_with`)."""
    return _fit_with(setup, fit, float(model.q), model.blur["resampling"])


def _fit_with(setup: SpectralSetup, fit: TransferFit, q: float, params: dict[str, float]
              ) -> TransferFit:
    """``fit`` at Q ``q`` with resampling ``params`` moved there on the spectrum, its χ²
    re-evaluated; the pitch's uncertainty the scan's step (:data:`PITCH_STEP`)."""
    name = "resampling"
    eff = {**fit.effects, name: dict(params)}
    chi2 = evaluate_chi2(setup.full, q=q, gain=fit.gain, effects=eff)
    sigmas = {**fit.sigmas, name: {**fit.sigmas.get(name, {}),  # type: ignore[dict-item]
                                   "native_pitch_px": PITCH_STEP}}
    return replace(fit, q=q, effects=eff, chi2=chi2, sigmas=sigmas)


def _refine_selected(sel: BlurSelection, setup: SpectralSetup, model: ForwardModel,
                     se_of: Callable[[ForwardModel], float]) -> ForwardModel:
    """:func:`_on_spectrum` for a resampling that forward selection chose (its pitch already
    moved by :func:`_selected_pitch_on_spectrum`): where the spectrum puts pitch and Q
    elsewhere, ``sel``'s final fit and its steps from the resampling's on move there."""
    if not any(st.name == "resampling" for st in sel.steps):
        return model
    refined = _on_spectrum(setup, model, se_of)
    if refined is model:
        return model
    _move_steps(sel, lambda f: _moved_fit(setup, f, refined))
    sel.final = _moved_fit(setup, sel.final, refined)
    return refined


def _move_steps(sel: BlurSelection, moved: Callable[[TransferFit], TransferFit]) -> None:
    """Replace the fits of ``sel``'s steps from the resampling's on (their claims) that
    hold a resampling by ``moved(fit)``."""
    k = next(i for i, st in enumerate(sel.steps) if st.name == "resampling")
    for j in range(k, len(sel.steps)):
        st = sel.steps[j]
        if "resampling" in st.fit.effects:
            sel.steps[j] = replace(st, fit=moved(st.fit))


def with_resampling(setup: SpectralSetup, model: ForwardModel, params: dict[str, float]
                    ) -> tuple[ForwardModel, TransferFit]:
    """``model`` with resampling ``params`` (native pitch, px; cubic a) in place of any it
    holds and Q refitted on the transfer with it and the other blurs held: the model
    route 2 scores for these parameters. The other blurs are not refitted: their shapes
    are the transfer's, and held they keep one fine-grid render for the whole scan.

    Returns
    -------
    model, fit
        The model and the transfer fit (its ``effects``: every blur of the model).
    """
    held = {**{n: p for n, p in model.blur.items() if n != "resampling"},
            "resampling": dict(params)}
    fit = fit_transfer(setup.full, [], q_starts=(model.q,), fixed=held)
    return model.without(q=fit.q, blur=dict(fit.effects)), fit


def _pitch_on_spectrum(setup: SpectralSetup, fit: TransferFit, model: ForwardModel,
                       se_fit: float, se_of: Callable[[ForwardModel], float]
                       ) -> tuple[TransferFit, ForwardModel]:
    """A native pitch fitted on the transfer moved to where the power spectrum puts it.

    The transfer fit sees resampling's coherent roll-off only, and fits its pitch short
    (development, seeds 1000-1415, the 70 true resamplings claimed: 0.04 px short on
    average, RMS error 0.12 px; c144: 1.47 px for 1.64), so the aliased power the claim
    rests on is under-predicted. The pitch is scanned over
    :data:`PITCH_SCAN` at the fitted Q, kernel and other blurs, and the one with the lowest
    spectral error (``se_of``) kept where it is lower than the fitted pitch's ``se_fit``
    and not at an end of the scan. Not under JPEG (``model.compression``): there the
    power above the block frequency is the JPEG's as much as the aliasing's, and the scan
    moved pitches away from the truth (development c132: 1.23 → 1.65 px for 1.32) and
    carried three resamplings that were not there past the rules that withdrew them
    (c44, c157, c183).

    Returns
    -------
    fit, model
        The transfer fit with the pitch replaced (its χ² re-evaluated at it) and the model
        with that pitch; ``fit`` and ``model`` unchanged where no scanned pitch does better.
    """
    name = "resampling"
    if model.compression is not None:
        return fit, model
    params = model.blur[name]
    scan = {float(p): se_of(model.without(blur={**model.blur,
                                                name: {**params, "native_pitch_px": float(p)}}))
            for p in PITCH_SCAN}
    best = min(scan, key=scan.__getitem__)
    if scan[best] >= se_fit or best in (PITCH_SCAN[0], PITCH_SCAN[-1]):
        # an end of the scan stands in for a pitch beyond it (as route 2 refuses it)
        return fit, model
    moved = {**params, "native_pitch_px": best}
    return (_fit_with(setup, fit, fit.q, moved),
            model.without(blur={**model.blur, name: moved}))


def _selected_pitch_on_spectrum(sel: BlurSelection, setup: SpectralSetup,
                                model: ForwardModel, se_of: Callable[[ForwardModel], float]
                                ) -> ForwardModel:
    """:func:`_pitch_on_spectrum` for a resampling that forward selection chose: the pitch
    moved in ``sel``'s final fit and in its steps from the resampling's on (their claims)."""
    name = "resampling"
    if not any(st.name == name for st in sel.steps):
        return model
    fit, moved = _pitch_on_spectrum(setup, sel.final, model, se_of(model), se_of)
    if moved is model:
        return model
    params = dict(moved.blur[name])
    _move_steps(sel, lambda f: replace(f, effects={**f.effects, name: dict(params)}))
    sel.final = fit
    return moved


def resampling_detection_limit(inp: Inputs, model: ForwardModel, setup: SpectralSetup,
                               ev: EvalContext) -> ResamplingLimit:
    """The native pitch from which a resampling is testable on this scene
    (:func:`geosim.diagnose.resampling_limit.resampling_limit`): on route 2's halves of
    ``ev``'s blocks against its held-out gain, or, with too few blocks for halves, on all
    of them against route 1's. The renders are ``model`` as delivered (noise realisations
    from ``ev.noise_seed`` where noise is claimed) without any resampling it holds, and
    with each tested one. Under JPEG the limit is at least Q / (2 · 1.15), where
    :func:`~geosim.diagnose.stage_withdraw.jpeg_resampling_beyond_optics` withdraws any
    resampling."""
    base = model.without(blur={k: v for k, v in model.blur.items() if k != "resampling"})

    def render(params: dict[str, float] | None) -> list[np.ndarray]:
        # as route 2 scores a resampling: Q refitted with it held
        m = base if params is None else with_resampling(setup, base, params)[0]
        return greys(realisations(inp, m, ev.noise_seed))

    halves = split_halves(ev.origins, setup.block_px, inp.valid.shape[1])
    sets, need = ((halves, 1.0 - ALIASING_SPECTRAL_GAIN_SPLIT) if halves is not None
                  else ([ev.origins], 1.0 - ALIASING_SPECTRAL_GAIN))
    return resampling_limit(render, inp.grey, sets, block_px=setup.block_px,
                            q=float(model.q), need=need,
                            rule_floor_px=None if model.compression is None
                            else jpeg_native_floor_px(float(model.q)))
