"""The paper's degradation model as seen by the diagnosis.

``paper_model(uav, q=, phi=)`` is I_sat = (I_uav ⊛ PSF(Q)) ↓φ with bicubic
downsampling. It delegates to :func:`geosim.degrade.core.degrade_array` (the
project's implementation) when that module is importable, and otherwise uses an
equivalent Fourier-domain implementation (analytic circular-aperture OTF,
reflect padding, OpenCV bicubic resize), so the diagnosis kernels can be tested
on their own.
"""

from __future__ import annotations

import cv2
import numpy as np

from geosim.physics import otf

__all__ = ["paper_model", "QSimulator"]


def _fallback(uav: np.ndarray, q: float, phi: int) -> np.ndarray:
    img = np.asarray(uav, dtype=np.float32)
    if img.ndim == 2:
        img = img[np.newaxis]
    blurred = otf.apply_transfer(img, lambda fy, fx: otf.optics_otf(fy, fx, q=q, phi=phi))
    rows, cols = img.shape[-2:]
    out_shape = (cols // phi, rows // phi)
    return np.stack([cv2.resize(b[: out_shape[1] * phi, : out_shape[0] * phi], out_shape,
                                interpolation=cv2.INTER_CUBIC) for b in blurred]).astype(float)


def paper_model(uav: np.ndarray, *, q: float, phi: int, valid: np.ndarray | None = None
                ) -> np.ndarray:
    """Simulated satellite image (bands, rows/phi, cols/phi) in DN, float64.

    Parameters
    ----------
    uav
        UAV image, bands first, on the fine grid (phi pixels per satellite pixel).
    q
        Q of the simulated optics (dimensionless, λ f / (D p)).
    phi
        Ratio satellite GSD / UAV GSD (whole number).
    """
    try:
        from geosim.degrade.core import degrade_array
    except ImportError:
        return _fallback(uav, q, phi)
    out, _ = degrade_array(np.asarray(uav), q=q, phi=phi, valid=valid)
    return np.asarray(out, dtype=float)


class QSimulator:
    """Cache of paper-model simulations at several Q for one UAV image.

    Calling ``sim(q)`` returns the (cached) paper model at that Q.
    """

    def __init__(self, uav: np.ndarray, *, phi: int, valid: np.ndarray | None = None,
                 q_min: float = 0.5) -> None:
        self.uav = np.asarray(uav)
        self.phi = int(phi)
        self.valid = valid
        self.q_min = float(q_min)
        self._cache: dict[float, np.ndarray] = {}
        self._fast = None
        try:
            from geosim.degrade.core import SpectralDegrader
        except ImportError:
            pass
        else:
            self._fast = SpectralDegrader(self.uav, phi=self.phi, q_min=self.q_min, valid=valid)

    def __call__(self, q: float) -> np.ndarray:
        key = round(float(q), 4)
        if key not in self._cache:
            if self._fast is not None and key >= self.q_min:
                out = np.asarray(self._fast.degrade(key), dtype=float)
                self._cache[key] = out[np.newaxis] if out.ndim == 2 else out
            else:
                self._cache[key] = paper_model(self.uav, q=key, phi=self.phi, valid=self.valid)
        return self._cache[key]
