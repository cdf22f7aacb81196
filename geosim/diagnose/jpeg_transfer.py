"""The coherent transfer of a JPEG, measured on the blurred model it compresses.

JPEG acts last, on the blurred product: quantisation zeroes the DCT coefficients that
are weaker than half their step, so the high frequencies a JPEG removes depend on how
much the scene still holds there. A blurred scene loses more to the same quantisation
than a sharp one. Comparing the real scene with simulations JPEG'd *sharp* (before any
blur) therefore misstates the blur: the JPEG'd sharp simulation keeps high frequencies
that the JPEG'd blurred scene lost, and the transfer between them is not the blur's
transfer (on the development half a 1.9 px smear under JPEG quality 30 was fitted below
0.8 px and not claimed; a resampled scene's roll-off was not found under JPEG).

:class:`JpegTransfer` linearises the JPEG around a reference model (the paper's model
with the blur found so far, matched to the scene's radiometry): its Welch transfer
H_J(f) = S_{J(m) m} / S_{m m} on the scene's blocks is the fraction of each frequency
the JPEG passes *for content as blurred as the scene*. Simulations filtered by H_J
stand in for "blur, then JPEG" in the transfer fit; the reference is updated as the
blur is refined (:func:`geosim.diagnose.stage_jpeg_refit.joint_jpeg_blur`).

**Noise dithers the quantisation.** Noise added before the JPEG moves coefficients that
would be zeroed across their bin edges, so on average the JPEG of (model + noise) keeps
more of the model's high frequencies than the JPEG of the model alone (Pillow, quality 30,
σ 6 DN: transfer at 0.25–0.3 cycles/px 0.456 without noise, 0.490 with it). When noise is
claimed, H_J is therefore measured on noise realisations, H_J = Σ F(J(m + n)) F(m)* /
Σ |F(m)|² (``dither``): the noise is independent of m, so the cross-spectrum keeps only
the part of the JPEG'd noisy product that is coherent with the model.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from geosim.diagnose.spectra import hann2d
from geosim.physics import otf

__all__ = ["JpegTransfer", "jpeg_transfer", "DITHER_REALISATIONS"]

#: noise realisations averaged when the JPEG's transfer is measured under noise
DITHER_REALISATIONS = 2


@dataclass(frozen=True)
class JpegTransfer:
    """H_J on the quadrant |fy|, |fx| ∈ [0, 0.5] cycles/px (DCT quantisation is even in
    the sign of each frequency), ``grid[i, j]`` at |fy| = i / block_px, |fx| = j / block_px."""

    grid: np.ndarray
    block_px: int

    def __call__(self, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        """H_J at any frequencies (cycles/px), bilinear between the block's bins."""
        iy = np.clip(np.abs(fy) * self.block_px, 0, self.grid.shape[0] - 1)
        ix = np.clip(np.abs(fx) * self.block_px, 0, self.grid.shape[1] - 1)
        iy, ix = np.broadcast_arrays(iy, ix)
        return ndimage.map_coordinates(self.grid, [iy.ravel(), ix.ravel()], order=1,
                                       mode="nearest").reshape(iy.shape)

    def apply(self, img: np.ndarray) -> np.ndarray:
        """``img`` (2-D or bands first) filtered by H_J."""
        return otf.apply_transfer(np.asarray(img, float), self)


def jpeg_transfer(reference: np.ndarray, compress: Callable[[np.ndarray], np.ndarray],
                  origins: Sequence[tuple[int, int]], block_px: int,
                  grey: Callable[[np.ndarray], np.ndarray], *,
                  dither: Callable[[np.ndarray, int], np.ndarray] | None = None,
                  n_dither: int = DITHER_REALISATIONS) -> JpegTransfer:
    """Measure H_J of ``compress`` on ``reference`` (bands first, DN, in the scene's
    radiometry) over the Welch blocks at ``origins``.

    H_J = Re Σ F(J(m)) F(m)* / Σ |F(m)|² (grey, Hann-windowed blocks), averaged over the
    four sign quadrants and clipped to [0, 1]: a coherent loss, never a gain.

    ``dither(m, k)``: ``m`` with noise realisation ``k`` added (and rounded as the product
    is), when the product is noisy before its JPEG; H_J is then the coherent transfer of
    J(m + n) averaged over ``n_dither`` realisations (noise dithers the quantisation).
    """
    ref = np.asarray(reference, float)
    ref_g = grey(ref)
    if dither is None:
        jpegs = [grey(np.asarray(compress(ref), float))]
    else:
        jpegs = [grey(np.asarray(compress(dither(ref, k)), float)) for k in range(n_dither)]
    w = hann2d(block_px)
    num = np.zeros((block_px, block_px), complex)
    den = np.zeros((block_px, block_px))
    for r, c in origins:
        a = ref_g[r:r + block_px, c:c + block_px]
        fa = np.fft.fft2((a - a.mean()) * w)
        den += np.abs(fa) ** 2
        for jp_g in jpegs:
            b = jp_g[r:r + block_px, c:c + block_px]
            num += np.fft.fft2((b - b.mean()) * w) * np.conj(fa) / len(jpegs)
    h = np.real(num) / np.maximum(den, 1e-30)
    half = block_px // 2
    quad = np.zeros((half + 1, half + 1))
    for i in range(half + 1):
        for j in range(half + 1):
            quad[i, j] = np.mean([h[si * i % block_px, sj * j % block_px]
                                  for si in (1, -1) for sj in (1, -1)])
    quad[0, 0] = 1.0
    return JpegTransfer(np.clip(quad, 0.0, 1.0), block_px)
