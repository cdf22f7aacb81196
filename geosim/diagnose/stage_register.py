"""Co-registration stage: a global sub-pixel shift, then a shift + rotation + scale field
from local shifts when its displacement is clearly above the local shifts' scatter; the
global shift confirmed against the refined model once it is fitted (:func:`confirm_shift`)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from geosim.diagnose.coregister import (
    AffineEstimate,
    ShiftEstimate,
    estimate_affine,
    estimate_shift,
)
from geosim.diagnose.model import Registration
from geosim.diagnose.select import MIN_DELTA_BIC
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.physics.geometry import affine_field, fourier_shift

__all__ = ["coregister", "confirm_shift", "shift_is_clear", "unapplied", "field_sigma_px",
           "MIN_SHIFT_PX", "MIN_FIELD_PX"]

MIN_SHIFT_PX = 0.1
#: smallest rotation/scale displacement (at the corners) worth a local shift field, px;
#: noisy local shifts in small scenes reach ≈ 0.2 px (development half)
MIN_FIELD_PX = 0.3


def coregister(inp: Inputs) -> Registration:
    """Global sub-pixel shift, then a shift + rotation + scale field from local shifts."""
    rows, cols = inp.valid.shape
    bg = grey(inp.base)
    est = estimate_shift(bg, inp.grey, valid=inp.valid, block_px=inp.block_px)
    applied = shift_is_clear(est)
    whole = (float(np.round(est.shift_px[0])), float(np.round(est.shift_px[1])))
    aff = estimate_affine(fourier_shift(bg, whole), inp.grey, valid=inp.valid, block_px=16)
    field_px = None
    if aff.n_blocks >= 6 and np.isfinite(aff.residual_px):
        corners = np.array([[0, 0], [cols, 0], [0, rows], [cols, rows]], float) - \
            np.array(aff.centre_px)
        linear_px = float(np.max(np.hypot(*(aff.matrix @ corners.T))))
        if linear_px >= max(MIN_FIELD_PX, 3.0 * field_sigma_px(aff, corners)):
            dcol, drow = aff.field((rows, cols))
            field_px = (dcol + whole[0], drow + whole[1])
            applied = True
    # invalid pixels take their nearest valid value, so that shifting never pulls fill
    # values (zeros) into the valid area
    fill_idx = None
    if not inp.valid.all():
        fill_idx = ndimage.distance_transform_edt(~inp.valid, return_distances=False,
                                                  return_indices=True)
    # the move is made on the UAV image before the optics and sampling, as the real
    # misregistration acts (QSimulator.shifted, QSimulator.warped); where the simulator
    # cannot (it keeps no UAV image), the sampled simulation is moved
    presampled = None
    shifted = getattr(inp.simulate, "shifted", None)
    warped = getattr(inp.simulate, "warped", None)
    if field_px is not None and callable(warped):
        presampled = warped(affine_field(*field_px))
    elif applied and field_px is None and callable(shifted):
        presampled = shifted(est.shift_px)
    return Registration(estimate=est, affine=aff, applied=applied,
                        shift_px=est.shift_px if applied else (0.0, 0.0), whole_px=whole,
                        field_px=field_px, fill_idx=fill_idx, presampled=presampled)


def shift_is_clear(est: ShiftEstimate) -> bool:
    """A global shift is applied (and claimed) when it is ≥ :data:`MIN_SHIFT_PX`, > 3σ and
    its phase fit's ΔBIC ≥ the claim rule's."""
    mag = float(np.hypot(*est.shift_px))
    return (mag >= MIN_SHIFT_PX and est.delta_bic >= MIN_DELTA_BIC
            and mag > 3 * float(np.hypot(*est.sigma_px)))


def unapplied(reg: Registration) -> Registration:
    """``reg`` with nothing applied: the simulation is not moved."""
    return Registration(estimate=reg.estimate, affine=reg.affine, applied=False,
                        shift_px=(0.0, 0.0), whole_px=reg.whole_px, fill_idx=reg.fill_idx)


def confirm_shift(inp: Inputs, reg: Registration, model_grey: np.ndarray) -> Registration:
    """A global shift found against the baseline, measured again against the refined
    model (``model_grey``: its deterministic simulation, not moved) and kept only if it is
    still clear there (:func:`shift_is_clear`).

    The first estimate compares the scene with the LV baseline, whose Q can be far from the
    scene's (noise and JPEG raise or lower the Laplacian variance): at a Q far too low the
    baseline holds aliased content the scene does not, whose phase moves differently and
    biases the shift (fresh validation c512: noise at Q 3.88, LV Q 0.81, a 0.18 px shift
    where there was none; against the paper's model at the true Q 0.12 px at 3σ = 0.13).
    A shift field (rotation, scale) is kept as found."""
    if not reg.applied or reg.field_px is not None:
        return reg
    est = estimate_shift(model_grey, inp.grey, valid=inp.valid, block_px=inp.block_px)
    return reg if shift_is_clear(est) else unapplied(reg)


def field_sigma_px(aff: AffineEstimate, corners: np.ndarray) -> float:
    """1-σ of the field's displacement at the farthest corner from its linear part: the
    local shifts scatter by ``residual_px``; the 16-px blocks overlap by half in both axes,
    so about a quarter of them are independent."""
    pos = aff.local[:, :2] - np.asarray(aff.centre_px)
    n_eff = max(aff.n_blocks / 4.0, 1.0)
    var_x = max(float(np.mean(pos**2)), 1e-9)
    r_max = float(np.max(np.hypot(corners[:, 0], corners[:, 1])))
    return float(aff.residual_px * r_max / np.sqrt(n_eff * var_x))
