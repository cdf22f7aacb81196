"""Stage 0 of the diagnosis: the inputs on the 0.5 m grid, and the grey-level helpers.

:class:`Inputs` holds the real scene and the paper's model (bands first); :func:`grey`,
:func:`greys` and :func:`bands` are the image conversions every stage shares.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from geosim.diagnose.spectra import block_origins
from geosim.errors import DiagnosisError
from geosim.physics.radiometry import luma

__all__ = ["Inputs", "make_inputs", "require_blocks", "grey", "greys", "bands", "rmse"]


@dataclass
class Inputs:
    """The real scene and the paper's model, bands first, on the 0.5 m grid."""

    real: np.ndarray
    grey: np.ndarray
    valid: np.ndarray
    simulate: Callable[[float], np.ndarray]
    base: np.ndarray
    q_base: float
    block_px: int
    quantized: bool
    gsd_m: float


def grey(img: np.ndarray) -> np.ndarray:
    """Grey level (luma) of a bands-first image; a 2-D image as it is (float)."""
    return luma(img) if img.ndim == 3 else np.asarray(img, float)


def greys(img: np.ndarray | list[np.ndarray]) -> np.ndarray | list[np.ndarray]:
    """Grey level of an image, or of each image of a list (noise realisations)."""
    return [grey(i) for i in img] if isinstance(img, list) else grey(img)


def bands(img: np.ndarray) -> np.ndarray:
    """A bands-first float array (a 2-D image gets one band)."""
    a = np.asarray(img, float)
    return a[np.newaxis] if a.ndim == 2 else a


def rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Root-mean-square difference of two bands-first images over ``mask``, DN."""
    return float(np.sqrt(np.mean((a[:, mask] - b[:, mask]) ** 2)))


def make_inputs(real: np.ndarray, simulate: Callable[[float], np.ndarray], q_base: float,
                valid: np.ndarray | None, block_px: int | None, quantized: bool | None,
                gsd_m: float) -> Inputs:
    """The :class:`Inputs` of a diagnosis, with the defaults filled in (all valid, Welch
    block 32 px or 64 px from 640 px, quantisation detected from whole DN)."""
    r = bands(real)
    rows, cols = r.shape[-2:]
    valid = np.ones((rows, cols), bool) if valid is None else np.asarray(valid, bool)
    if block_px is None:
        block_px = 64 if min(rows, cols) >= 640 else 32
    if quantized is None:
        quantized = bool(np.all(r[:, valid] == np.round(r[:, valid])))
    return Inputs(real=r, grey=grey(r), valid=valid, simulate=simulate,
                  base=bands(simulate(q_base)), q_base=float(q_base), block_px=block_px,
                  quantized=quantized, gsd_m=gsd_m)


def require_blocks(inp: Inputs) -> None:
    """Refuse a diagnosis whose valid pixels hold no fully valid Welch block (a small or
    ragged common extent: a narrow strip, a turned flight in a small window) before the
    registration needs one. Fewer than the fits need is refused by the spectral setup,
    after it has tried smaller blocks.

    Raises
    ------
    DiagnosisError
        Naming the extent and what to give instead.
    """
    rows, cols = inp.valid.shape
    if not block_origins((rows, cols), block_px=inp.block_px, valid=inp.valid):
        raise DiagnosisError(
            f"real scene: no fully valid {inp.block_px}×{inp.block_px} block on the "
            f"{inp.gsd_m:g} m grid where both images hold data ({int(inp.valid.sum())} of "
            f"{rows}×{cols} pixels); give a larger common extent (a flight whose imaged "
            f"area holds squares of {inp.block_px * inp.gsd_m:g} m)")
