"""A scene change's moved objects painted into the UAV ground, for a second pass.

The blur fit measures the transfer between the paper's model and the real scene only
where both show the same ground: changed regions are left out (whole Welch blocks
between them, or tapered out; :mod:`~geosim.diagnose.stage_blur`). Cattle scattered over
a paddock leave few whole 32 px blocks, and the fit falls back to 16 px blocks or a
taper — which costs the blurs their evidence. On development scenes with moved objects
(c1104, c761, c94, c1169, c1209, c278 …) the diagnosis found none of the blurs whose
ideal-observer evidence was Δχ² 2 800–26 000, and found them on the same scenes rendered
without the change, whole 32 px blocks and all (ΔBIC 24–950 against −8 to 1).

The first pass models each claimed change as moved objects (uniform ellipses seen
through the optics, :mod:`~geosim.diagnose.stage_objects`). Here they are painted into
the UAV image on its fine grid — where the ground is, before the optics, so that every
Q, blur and resampling the second pass tries renders them as it renders the ground — at
the place the UAV image has under the first pass's registration, with the first pass's
radiometric gain taken off their contrast (the model applies it after the optics). The
engine (:func:`~geosim.diagnose.engine.diagnose_arrays`) runs the whole diagnosis again
on the painted ground and keeps the second pass only where its refined simulation as
delivered fits the scene's spectrum better over every valid block (the changed areas
included) on every block size either pass used (:func:`second_pass_better`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from geosim.diagnose.context import EvalContext, whole_extents
from geosim.diagnose.model import ForwardModel, Registration
from geosim.diagnose.stage_inputs import Inputs
from geosim.diagnose.stage_objects import MovedObject, ellipse_patch

__all__ = ["uav_position", "paint_objects", "painted_inputs", "SecondPassJudgement",
           "second_pass_better"]


def uav_position(reg: Registration | None, centre_px: tuple[float, float]
                 ) -> tuple[float, float]:
    """Where a point of the real scene (``centre_px``: column, row in product pixels,
    pixel centres at k + 0.5) lies in the UAV image's product-grid coordinates: the
    registration moves the UAV image by a global shift or a field ``d`` (its render at
    x is the UAV image at x − d(x)), so the point is ``centre_px − d(centre_px)`` (the
    field read at the nearest pixel)."""
    col, row = float(centre_px[0]), float(centre_px[1])
    if reg is None or not reg.applied:
        return col, row
    if reg.field_px is not None:
        d_col, d_row = reg.field_px
        r = int(np.clip(np.floor(row), 0, d_col.shape[0] - 1))
        c = int(np.clip(np.floor(col), 0, d_col.shape[1] - 1))
        return col - float(d_col[r, c]), row - float(d_row[r, c])
    return col - float(reg.shift_px[0]), row - float(reg.shift_px[1])


def paint_objects(uav: np.ndarray, objects: Sequence[MovedObject], *, phi: int,
                  gain: np.ndarray, reg: Registration | None = None) -> np.ndarray:
    """The UAV image with the moved ``objects`` painted in (DN, a float32 copy).

    Parameters
    ----------
    uav
        The UAV image, bands first, on its fine grid (``phi`` fine pixels per product
        pixel); not modified.
    objects
        Moved objects in the real scene's product-pixel coordinates, their contrast per
        band in the scene's DN (after the model's radiometry).
    phi
        Fine pixels per product pixel along each axis.
    gain
        Per band, the model's radiometric gain (the contrast is divided by it: the model
        applies it after the optics).
    reg
        The registration the objects were fitted under (:func:`uav_position`); None: none.

    Returns
    -------
    numpy.ndarray
        ``uav`` + Σ contrast / gain × each object's indicator (edges antialiased over one
        fine pixel, :func:`~geosim.diagnose.stage_objects.ellipse_patch`), summed in
        float64 within the objects' bounding box only (a whole orthomosaic window is never
        copied in float64).
    """
    g = np.asarray(gain, float)
    shape_fine = tuple(uav.shape[-2:])
    patches = []
    for o in objects:
        col, row = uav_position(reg, o.centre_px)
        patch = ellipse_patch(shape_fine, (col * phi, row * phi),  # type: ignore[arg-type]
                              (o.semi_axes_px[0] * phi, o.semi_axes_px[1] * phi), o.angle_deg)
        if patch is not None:
            patches.append((np.asarray(o.contrast_dn, float) / g, patch))
    out = np.array(uav, dtype=np.float32, copy=True)
    if not patches:
        return out
    r_lo = min(p[0] for _, p in patches)
    c_lo = min(p[1] for _, p in patches)
    r_hi = max(p[0] + p[2].shape[0] for _, p in patches)
    c_hi = max(p[1] + p[2].shape[1] for _, p in patches)
    layer = np.zeros((g.size, r_hi - r_lo, c_hi - c_lo))
    for coef, (r0, c0, values) in patches:
        h, w = values.shape
        layer[:, r0 - r_lo:r0 - r_lo + h, c0 - c_lo:c0 - c_lo + w] += \
            coef[:, None, None] * values
    box = (slice(None), slice(r_lo, r_hi), slice(c_lo, c_hi))
    out[box] = (np.asarray(uav[box], float) + layer).astype(np.float32)
    return out


def painted_inputs(inp: Inputs, model: ForwardModel) -> Inputs | None:
    """``inp`` with the paper's model rendered from the UAV image with ``model``'s moved
    objects painted in (:func:`paint_objects`; the baseline stays the unpainted one);
    None where the model holds no objects or the simulator cannot render another image
    on its grid (it has no ``with_image`` or keeps no image)."""
    if model.n_objects == 0:
        return None
    with_image = getattr(inp.simulate, "with_image", None)
    uav = getattr(inp.simulate, "uav", None)
    if not callable(with_image) or uav is None:
        return None
    uav = np.asarray(uav)
    uav = uav[np.newaxis] if uav.ndim == 2 else uav
    painted = paint_objects(uav, model.objects.objects,
                            phi=int(inp.simulate.phi),  # type: ignore[attr-defined]
                            gain=model.gain_offset(inp.real.shape[0])[0],
                            reg=model.registration)
    return replace(inp, simulate=with_image(painted))


@dataclass(frozen=True)
class SecondPassJudgement:
    """The two passes' refined simulations judged over every valid block.

    Attributes
    ----------
    better : bool
        Whether the second pass's error is lower at every block size.
    block_px : list of int
        The Welch block sizes judged on, pixels.
    spectral_error_whole : list of tuple of float
        Per block size, (first pass, second pass) spectral error (dimensionless).
    """

    better: bool
    block_px: list[int]
    spectral_error_whole: list[tuple[float, float]]


def second_pass_better(ev: EvalContext, valid: np.ndarray, block_sizes_px: Sequence[int],
                       first: np.ndarray, second: np.ndarray) -> SecondPassJudgement | None:
    """Whether the second pass's refined simulation as delivered (``second``) fits the
    scene's spectrum better than the first's (``first``) over every valid block, the
    changed areas included, on each of ``block_sizes_px`` that holds enough whole blocks
    (:func:`~geosim.diagnose.context.whole_extents`); None where no size holds enough."""
    wholes = whole_extents(ev, valid, block_sizes_px)
    if not wholes:
        return None
    pairs = [(w.spectral_error(first), w.spectral_error(second)) for w in wholes]
    return SecondPassJudgement(better=all(b < a for a, b in pairs),
                               block_px=[w.block_px for w in wholes],
                               spectral_error_whole=pairs)
