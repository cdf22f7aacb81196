"""JPEG and blur fitted together: the blur re-selected with the JPEG linearised around the
blurred model (:func:`joint_jpeg_blur`), the check that an isotropic blur is not the
quality's uncertainty (:func:`jpeg_robust_isotropic`), and the refit with the claimed
noise dithering the quantisation (:func:`dithered_refit`). Each refits within the blur
fit's :class:`~geosim.diagnose.context.FitWindow` (fit mask, Q range, candidate effects,
Q starting values)."""

from __future__ import annotations

import numpy as np

from geosim.diagnose.context import FitWindow
from geosim.diagnose.model import CompressionFit, ForwardModel
from geosim.diagnose.select import BlurSelection
from geosim.diagnose.spectra import spectral_error
from geosim.diagnose.stage_blur import (
    ISOTROPIC,
    SpectralSetup,
    adopt,
    exact_anisotropic,
    select_with_q_room,
)
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.diagnose.stage_jpeg import (
    jpeg_linearised,
    jpeg_quality_for_scale,
    jpeg_step_scale,
)
from geosim.diagnose.stage_noise import estimate_scene_noise, realisations
from geosim.diagnose.stage_radiometry import fit_scene_radiometry

__all__ = ["joint_jpeg_blur", "reselect_at_quality", "robust_then_exact",
           "jpeg_robust_isotropic", "dithered_refit", "delivered_q", "expected_se",
           "JPEG_STEP_MARGIN",
           "DITHER_SEED", "DELIVERED_Q_COARSE", "DELIVERED_Q_FINE"]

#: an isotropic blur claimed under JPEG must still be chosen when the quantisation steps
#: are this much coarser than estimated (set when the quality came from block-edge step
#: energy, which scattered by up to ≈ 25 % in step size on the development half; the
#: lattice's quality is exact since round 16, and the margin stays for the linearised
#: JPEG's own approximation: a too-lossless JPEG model leaves high frequencies that an
#: isotropic blur then removes in its place; not re-tuned)
JPEG_STEP_MARGIN = 1.25
#: seed of the noise realisations that compare the dithered refit with the first fit (the
#: same realisations for both)
DITHER_SEED = 12345
#: Q under JPEG from the delivered spectrum (:func:`delivered_q`): a geometric grid of
#: this ratio over the fit's Q range, then one of :data:`DELIVERED_Q_FINE` around its best
DELIVERED_Q_COARSE = 1.08
DELIVERED_Q_FINE = 1.02


def joint_jpeg_blur(inp: Inputs, model: ForwardModel, setup: SpectralSetup, sel: BlurSelection,
                    window: FitWindow) -> tuple[ForwardModel, SpectralSetup, BlurSelection]:
    """JPEG and blur together: the blur selection redone with the JPEG's transfer
    linearised around the refined (blurred) model (:mod:`geosim.diagnose.jpeg_transfer`),
    where the first selection linearised it around the sharp baseline.

    The quality is the scene's own (its quantisation lattice,
    :func:`~geosim.diagnose.jpeg_quality.lattice_quality`), so it does not move with the
    blur and one re-selection suffices. (Until round 16 the quality was matched to the
    block-edge steps of the re-encoded model and re-estimated on each refined model to a
    fixed point; under very sharp optics that fixed point was a blurry model with a far
    too coarse JPEG: development c331, quality 13 for 27.)"""
    if model.compression is None:
        return model, setup, sel
    return reselect_at_quality(inp, model, model.compression.quality, window)


def reselect_at_quality(inp: Inputs, model: ForwardModel, quality: int, window: FitWindow
                        ) -> tuple[ForwardModel, SpectralSetup, BlurSelection]:
    """The blur selection redone from the baseline Q with the JPEG at ``quality`` (same
    block offset and test), the JPEG's transfer linearised around ``model`` (its Q and
    blur); the model adopts the new selection."""
    c = model.compression
    assert c is not None
    comp = CompressionFit(quality, c.offset_px, c.test)
    jpeg = jpeg_linearised(inp, model.without(compression=comp), window.mask)
    start = model.without(compression=comp, q=inp.q_base, blur={})
    setup, sel = select_with_q_room(inp, start, window, jpeg)
    return adopt(start, sel), setup, sel


def robust_then_exact(inp: Inputs, model: ForwardModel, setup: SpectralSetup,
                      sel: BlurSelection, window: FitWindow
                      ) -> tuple[ForwardModel, SpectralSetup, BlurSelection]:
    """The JPEG-robust isotropic check, then the exact window-aware family decisions; the
    model adopts the exact decision's blur where it changed the fast fit's."""
    model, setup, sel = jpeg_robust_isotropic(inp, model, setup, sel, window)
    fast_final = sel.final
    sel = exact_anisotropic(inp, setup, sel)
    if sel.final is not fast_final:
        model = adopt(model, sel)
    return model, setup, sel


def jpeg_robust_isotropic(inp: Inputs, model: ForwardModel, setup: SpectralSetup,
                          sel: BlurSelection, window: FitWindow
                          ) -> tuple[ForwardModel, SpectralSetup, BlurSelection]:
    """Under JPEG, an isotropic blur must not be explainable by the quality's uncertainty.

    The blur selection is repeated with quantisation steps :data:`JPEG_STEP_MARGIN` times
    coarser than estimated; if no isotropic blur is chosen there, the JPEG's own
    high-frequency loss explains the roll-off and that selection is kept."""
    c = model.compression
    if c is None or not any(n in model.blur for n in ISOTROPIC):
        return model, setup, sel
    q_low = jpeg_quality_for_scale(JPEG_STEP_MARGIN * jpeg_step_scale(c.quality))
    alt, alt_setup, alt_sel = reselect_at_quality(inp, model, q_low, window)
    if any(n in alt_sel.final.effects for n in ISOTROPIC):
        return model, setup, sel
    return alt, alt_setup, alt_sel


def dithered_refit(inp: Inputs, model: ForwardModel, setup: SpectralSetup, sel: BlurSelection,
                   window: FitWindow) -> tuple[ForwardModel, SpectralSetup, BlurSelection]:
    """Under JPEG with noise claimed: the blur refitted with the noise in the model.

    The scene's JPEG encoded a noisy product; noise dithers the quantisation, so the JPEG
    keeps more of the high frequencies than it does on the noise-free model the first fit
    linearised it around. That fit therefore saw the JPEG too lossy and blurred too
    little. The JPEG's linearised transfer, the blur, the radiometry and the noise are
    fitted again with noise realisations of the estimate before the JPEG; the refit is
    kept only if the noise is still claimed against it, else the noise is not claimed
    (development c17: a Q misfit under JPEG read as 2.7 DN² of noise, 0.7 DN² against the
    refit), and only if the delivered refit's expected power spectrum fits the scene no
    worse than the first fit's (development extension: without this check a false
    `resampling` was claimed in two JPEG + noise scenes)."""
    if model.compression is None or model.noise is None or not model.noise.claimed:
        return model, setup, sel
    start = model.without(radiometry=None)
    m2, setup2, sel2 = joint_jpeg_blur(inp, start, setup, sel, window)
    m2, setup2, sel2 = robust_then_exact(inp, m2, setup2, sel2, window)
    m2 = estimate_scene_noise(inp, fit_scene_radiometry(inp, m2.without(seam=None), window.mask),
                              setup2, window.mask)
    if m2.noise is None or not m2.noise.claimed:
        # the noise does not survive a model that accounts for it (a misfit read as noise
        # under the first quality and blur): not claimed, first fit kept
        return model.without(noise=m2.noise), setup, sel

    if expected_se(inp, m2, setup) > expected_se(inp, model, setup):
        # the refit was made for the power the JPEG keeps under noise; it must show there
        return model, setup, sel
    return m2, setup2, sel2


def expected_se(inp: Inputs, m: ForwardModel, setup: SpectralSetup) -> float:
    """Spectral error of ``m``'s delivered simulation (JPEG last, on the noisy product;
    with noise claimed, the mean of the realisations from :data:`DITHER_SEED`) on the
    fit's blocks: its expected spectrum against the scene's (both tapered as the fit's
    images are, :meth:`SpectralSetup.tapered`)."""
    sims = [setup.tapered(grey(r)) for r in realisations(inp, m, DITHER_SEED)]
    return spectral_error(sims, setup.tapered(inp.grey), block_px=setup.block_px,
                          origins=setup.origins)


def delivered_q(inp: Inputs, model: ForwardModel, setup: SpectralSetup) -> ForwardModel:
    """Under JPEG, Q chosen on the simulation as delivered: blur, radiometry, noise, then
    the JPEG last (as the camera encodes), its expected power spectrum against the scene's
    on the fit's blocks; every other part of the model as fitted.

    The transfer fit sees the JPEG through a transfer linearised around a model
    (:mod:`geosim.diagnose.jpeg_transfer`); quantisation is not linear, and with the
    quality read exactly from the scene's lattice that fit puts Q too high under sharp
    optics (development c259: Q 0.82 at JPEG 40 fitted 1.08, the delivered spectrum's
    minimum at 0.8; fresh c491: Q 0.89 at JPEG 60 fitted 2.19). The delivered spectrum
    needs no linearisation. Searched over the fit's Q grid range
    (:data:`DELIVERED_Q_COARSE`, then :data:`DELIVERED_Q_FINE` around the best); the fit's
    Q is kept unless another fits strictly better. The model's noise enters the delivered
    spectrum, so the caller reads the noise again where Q moved (noise missing from the
    model reads as a sharper Q: development c08, Q 1.42 with noise chosen at 1.14 before
    the noise was in the model)."""
    if model.compression is None:
        return model

    def se(q: float) -> float:
        return expected_se(inp, model.without(q=q), setup)

    q_lo, q_hi = float(setup.q_grid[0]), float(setup.q_grid[-1])
    n = int(np.ceil(np.log(q_hi / q_lo) / np.log(DELIVERED_Q_COARSE))) + 1
    scores = {float(q): se(float(q)) for q in np.geomspace(q_lo, q_hi, n)}
    scores[model.q] = se(model.q)
    best = min(scores, key=scores.__getitem__)
    for k in (-2, -1, 1, 2):
        q = float(np.clip(best * DELIVERED_Q_FINE ** k, q_lo, q_hi))
        scores.setdefault(q, se(q))
    best = min(scores, key=scores.__getitem__)
    if scores[best] >= scores[model.q]:
        return model
    return model.without(q=best)
