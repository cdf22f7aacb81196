"""The grey level of a forward model's expected image, rendered as one band.

Before compression, everything :class:`geosim.diagnose.model.ForwardModel` does to the UAV
image is linear and the same in every band (optics, sampling, the blurs, a resampling's
native grid, the move onto the real scene, the seam's factor), then affine per band (haze,
colour response) plus an additive layer (moved objects). The luma of the result is
therefore the one-band render of the UAV image weighted by luma weight × band gain, plus
a constant image (the offsets' and the objects' luma). Stages that score only the grey
level over many candidate models (the coherent resampling scan, the isotropic pixel scan)
render one band where the full model renders three, and move it once where a local warp
(rotation, scale) would move three.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from geosim.diagnose.model import ForwardModel
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.physics.radiometry import luma_weights

__all__ = ["grey_expected"]


def grey_expected(inp: Inputs, m: ForwardModel) -> np.ndarray:
    """``grey(m.deterministic(inp.simulate))`` (DN, rows × cols), rendered as one band
    where the simulator can (:meth:`geosim.diagnose.simulate.QSimulator.weighted`; equal
    up to rounding); the full render's luma otherwise (JPEG, which is not linear, or a
    simulator without the UAV image)."""
    reg = m.registration
    source, _ = reg.fine_source(inp.simulate)   # a field's move is in its warped simulator
    weighted = getattr(source, "weighted", None)
    uav = getattr(source, "uav", None)
    if m.compression is not None or not callable(weighted) or uav is None:
        return grey(m.deterministic(inp.simulate))
    n_bands = uav.shape[0] if uav.ndim == 3 else 1
    w = luma_weights(n_bands)
    gain, offset = m.gain_offset(n_bands)
    one = weighted(tuple(w * gain))
    if one is None:
        return grey(m.deterministic(inp.simulate))
    if reg.presampled is not None:
        reg = replace(reg, presampled=one if reg.field_px is not None
                      else one.shifted(reg.shift_px))
    out = m.without(radiometry=None, objects=None, registration=reg).deterministic(one)[0]
    out = out + float(np.dot(w, offset))
    return out + grey(m.objects.layer) if m.objects is not None else out
