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

**Only where the reference holds content.** H_J is a ratio, and where the reference has
(almost) no power, beyond its optical cut-off, it is 0/0: on a generator scene JPEG'd at
quality 30 the ratio measured at 0.35–0.5 cycles/px was 0.06 on a reference at Q 1.0 and
0.43–0.50 on references at Q 2.5–3.5 (529 blocks; the JPEG's block-edge power there,
≈ 10⁶ against the reference's 10¹–10², is incoherent with it), i.e. the clipped ratio of
two noises. Those values made the blurrier reference pass *more* of a sharper
simulation's high frequencies, a positive feedback on Q (round 16: Q 2.47 for 2.0) and
room for a resampling that was not there (development c413, c487). Each bin's H_J
therefore carries its standard error (regression of the JPEG'd block spectra on the
reference's, ``se² = Σ|F(J) − H F(m)|² / (n Σ|F(m)|²)``, halved for the conjugate pair
the sign quadrants share), and bins where H_J is not at least :data:`MEASURED_Z` standard
error above zero are left out of the transfer fits (``measured``): the linearisation says
nothing there. (Tried on the development JPEG scenes and not kept: a 3 σ mask, and the
relative variance (se / H)² added to every bin's: each also left out the bins where a
strong JPEG keeps a little of the scene, and lost more true resamplings and smears; and
also requiring H_J consistent with a pass ≤ 1, which changed 5 of 122 rows, for the worse.)
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
#: a bin's H_J is used only where it is this many standard errors above zero: an
#: estimate under one standard error is a ratio of noises (chosen on the development
#: JPEG scenes against 3, which left out bins that a strong JPEG measurably passes)
MEASURED_Z = 1.0


@dataclass(frozen=True)
class JpegTransfer:
    """H_J on the quadrant |fy|, |fx| ∈ [0, 0.5] cycles/px (DCT quantisation is even in
    the sign of each frequency), ``grid[i, j]`` at |fy| = i / block_px, |fx| = j / block_px."""

    grid: np.ndarray
    block_px: int
    #: bins where H_J is measured (``grid`` more than :data:`MEASURED_Z` standard errors
    #: above zero); None: every bin
    measured: np.ndarray | None = None

    def __call__(self, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        """H_J at any frequencies (cycles/px), bilinear between the block's bins."""
        iy = np.clip(np.abs(fy) * self.block_px, 0, self.grid.shape[0] - 1)
        ix = np.clip(np.abs(fx) * self.block_px, 0, self.grid.shape[1] - 1)
        iy, ix = np.broadcast_arrays(iy, ix)
        return ndimage.map_coordinates(self.grid, [iy.ravel(), ix.ravel()], order=1,
                                       mode="nearest").reshape(iy.shape)

    def measured_at(self, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        """Whether H_J was measured at frequencies ``fy``, ``fx`` (cycles/px; its nearest
        bin): the bins a transfer fit through this linearisation may use."""
        iy = np.clip(np.rint(np.abs(fy) * self.block_px), 0, self.grid.shape[0] - 1)
        ix = np.clip(np.rint(np.abs(fx) * self.block_px), 0, self.grid.shape[1] - 1)
        iy, ix = np.broadcast_arrays(iy.astype(int), ix.astype(int))
        if self.measured is None:
            return np.ones(iy.shape, bool)
        return self.measured[iy, ix]

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
    four sign quadrants and clipped to [0, 1]: a coherent loss, never a gain; ``measured``
    where it is more than :data:`MEASURED_Z` standard errors above zero.

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
    fas, fbs = [], []
    for r, c in origins:
        a = ref_g[r:r + block_px, c:c + block_px]
        fas.append(np.fft.fft2((a - a.mean()) * w))
        fbs.append([np.fft.fft2((b - b.mean()) * w)
                    for b in (jp_g[r:r + block_px, c:c + block_px] for jp_g in jpegs)])
    fa = np.array(fas)                      # (block, fy, fx)
    fb = np.array(fbs)                      # (block, realisation, fy, fx)
    den = np.maximum(np.sum(np.abs(fa) ** 2, axis=0), 1e-30)
    num = np.mean(np.sum(fb * np.conj(fa)[:, None], axis=0), axis=0)
    h = np.real(num) / den
    # regression of the JPEG'd spectra on the reference's: residual power per bin
    resid = np.mean(np.sum(np.abs(fb - h * fa[:, None]) ** 2, axis=0), axis=0)
    var = resid / (len(origins) * den)
    quad, quad_var = _sign_quadrants(h, block_px), _sign_quadrants(var, block_px) / 2.0
    quad[0, 0], quad_var[0, 0] = 1.0, 0.0
    measured = quad > MEASURED_Z * np.sqrt(quad_var)
    return JpegTransfer(np.clip(quad, 0.0, 1.0), block_px, measured)


def _sign_quadrants(a: np.ndarray, block_px: int) -> np.ndarray:
    """``a`` (block_px², FFT order) averaged over the four sign quadrants, on
    |fy|, |fx| ≤ 0.5 cycles/px."""
    idx = np.arange(block_px // 2 + 1)
    return np.mean([a[np.ix_(si * idx % block_px, sj * idx % block_px)]
                    for si in (1, -1) for sj in (1, -1)], axis=0)
