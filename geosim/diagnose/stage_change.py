"""Scene change: regions of significant residual energy (:func:`changed_regions`, used
to mask the fit and as the final maps' regions), the evidence of a ``scene_change``
claim and the moved objects that model it in the refined simulation
(:func:`model_moved_objects`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import ndimage

from geosim.diagnose import locate
from geosim.diagnose.context import ChangedRegions, EvalContext
from geosim.diagnose.model import Claim, ForwardModel
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.diagnose.stage_objects import fit_moved_objects
from geosim.diagnose.stage_radiometry import affine_residual
from geosim.diagnose.stage_withdraw import delivered_no_worse

__all__ = ["changed_regions", "scene_change_claim", "resampling_phase_dn2",
           "model_moved_objects", "MIN_REGION_DN2"]

#: floor of the residual energy a region must exceed (× ratio threshold), DN²
MIN_REGION_DN2 = 4.0


def changed_regions(inp: Inputs, model_grey: np.ndarray, *, ratio: float,
                    floor_dn2: float = MIN_REGION_DN2, affine: bool = True,
                    extra_dn2: np.ndarray | float = 0.0
                    ) -> tuple[list[locate.Region], np.ndarray, np.ndarray, np.ndarray]:
    """Regions of significant residual energy: (regions, labels, energy map, inner mask).

    ``affine``: match the model's grey level to the scene first (the first pass, before
    the radiometry is fitted); the final pass uses the refined model's residual as it is,
    so that large areas the radiometry does not explain show up as ``global`` regions.
    ``extra_dn2``: residual energy expected on top of the scene-wide level (a map, e.g. the
    compression error, which concentrates in textured blocks).
    """
    e = (affine_residual(model_grey, inp.grey, inp.valid) if affine
         else inp.grey - model_grey)
    inner = ndimage.binary_erosion(inp.valid, np.ones((5, 5)), border_value=0)
    energy = locate.residual_energy_map(np.where(inner, e, 0))
    expected = max(float(np.median(energy[inner])), floor_dn2) + extra_dn2
    regions, labels = locate.find_regions(energy, valid=inner, expected_dn2=expected,
                                          ratio_threshold=ratio)
    return regions, labels, energy, inner


def resampling_phase_dn2(inp: Inputs, model: ForwardModel,
                         plain: np.ndarray) -> np.ndarray | float:
    """Residual energy (map, DN²) that a resampling's unknown native-grid phase leaves.

    The aliasing of a coarser native grid depends on where that grid lies against the
    scene, which nothing in the product tells: the model's grid lies at the phase fitted
    on the power spectrum where a resampling was refined there (round 22), else at the
    product grid's origin; the real one anywhere. Its aliased component is strongest on
    object-sized high-contrast texture and would otherwise read as moved objects
    (development c176 at Q 1.17: ``scene_change`` claimed beside a true resampling and
    a shift; c84 at Q 0.99, whose native pitch is fitted 6 % short, still claims it: a
    wrong pitch changes where the aliases fold, not only their phase).

    Moving the native grid half a cell along one axis against the scene
    (``ForwardModel.native_phase_px``) leaves the pass band as it was and flips the sign
    of the aliases folded along that axis (a sample at (k + ½)·pitch of frequency f,
    reconstructed at f − 1/pitch, turns by π), so the difference from the model is twice
    those aliases. Against a grid of unknown phase θ the expected residual of an alias ``a`` is
    E|a (e^{iθ} − 1)|² = 2|a|²: half the summed energies of the two one-axis differences
    (the aliases folded along both axes counted twice). Taken before compression (its own
    error is :func:`changed_regions`'s other ``extra_dn2``): ``plain`` is the model's
    image without it. 0 without resampling."""
    p = model.blur.get("resampling")
    if p is None:
        return 0.0
    m = model.without(compression=None)
    half = 0.5 * p["native_pitch_px"]
    r0, c0 = model.native_phase_px
    return 0.5 * sum(locate.residual_energy_map(grey(
        plain - m.without(native_phase_px=d).deterministic(inp.simulate)))
        for d in ((r0 + half, c0), (r0, c0 + half)))


def scene_change_claim(inp: Inputs, model: ForwardModel, sc: list[locate.Region],
                       change: ChangedRegions) -> Claim:
    """Evidence: the region pixels have a larger residual variance than the rest.

    ``sc``: the ``scene_change`` regions among ``change.regions``; the variances are taken
    inside ``change.inner``."""
    regions, labels, inner = change.regions, change.labels, change.inner
    e_final = grey(inp.real - model.deterministic(inp.simulate))
    area = sum(g.area_px for g in sc) * inp.gsd_m**2
    in_sc = locate.regions_mask(labels, regions, dilate_px=0) & inner
    out_sc = inner & ~locate.regions_mask(labels, regions, kind=None)
    n_in = max(in_sc.sum() / 4.0, 1.0)
    v_in = float(np.mean(e_final[in_sc] ** 2)) if in_sc.any() else 0.0
    v_out = max(float(np.mean(e_final[out_sc] ** 2)) if out_sc.any() else 1e-12, 1e-12)
    dbic = float(n_in * (v_in / v_out - 1 - np.log(max(v_in / v_out, 1e-12)))
                 - 2 * len(sc) * np.log(max(inner.sum() / 4.0, 2.0)))
    return Claim("scene_change", {"n_regions": len(sc), "area_m2": area}, {}, dbic)


def model_moved_objects(inp: Inputs, model: ForwardModel, change: ChangedRegions,
                        ev: EvalContext, se_wholes: Sequence[Callable[[np.ndarray], float]]
                        ) -> ForwardModel:
    """The refined model with the moved objects of the ``scene_change`` regions
    (:func:`~geosim.diagnose.stage_objects.fit_moved_objects`), fitted on the residual of
    its deterministic image; kept only where the delivered simulation then fits the
    scene's spectrum better over the whole valid extent (every measure of ``se_wholes``,
    the changed areas included: :func:`~geosim.diagnose.context.whole_extents`) and, as
    every refined simulation, no worse than the baseline there and on the evaluation
    blocks (``ev``: outside the changed regions, which the objects do not reach, or the
    fit's blocks where fewer than 4 lie outside them). ``model`` as it is otherwise, and
    always where the scene has fewer than 4 whole blocks (``se_wholes`` empty)."""
    if not se_wholes:
        return model
    det = model.deterministic(inp.simulate)
    objects = fit_moved_objects(inp.real - det, change.inner, change.labels,
                                change.regions, q=float(model.q), blur=model.blur, model=det)
    if objects is None:
        return model
    with_objects = model.without(objects=objects)

    def delivered(m: ForwardModel) -> np.ndarray:
        return m.delivered(inp.simulate, np.random.default_rng(ev.noise_seed),
                           quantized=inp.quantized)

    after, before = delivered(with_objects), delivered(model)
    if (all(se(after) < se(before) for se in se_wholes)
            and delivered_no_worse(inp, ev, se_wholes)(after)):
        return with_objects
    return model
