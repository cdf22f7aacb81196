"""Sensor noise from the white, incoherent part of the residual.

A structured residual (a blur shape the model lacks, JPEG blocks, moved objects) is
not noise, but a per-pixel variance cannot tell them apart. Noise is instead measured
in the frequency domain from the part of the real scene that no linear filter of the
model can predict, N(f) = S_rr(f) (1 − γ²(f)) (Welch, against the refined
deterministic model): a blur-shape misfit is absorbed by the per-frequency filter and
leaves N at zero, while sensor noise leaves a flat (white) floor. The floor is read at
high frequencies (0.3–0.5 cycles per pixel, where optics leave little signal) and
compared with mid frequencies (0.1–0.25): white noise gives a ratio near 1, structured
residuals rise towards the frequencies that carry the scene's power. Its brightness
dependence (var = a·s + b) comes from block variances of the high-passed residual
(:func:`geosim.diagnose.fit.fit_noise`), scaled to the white level.

Under JPEG the floor is gone: the quantisation removes the high-frequency power where it
would be read (the steps there are far coarser than the noise) and what remains of the
incoherent power is the JPEG's own error, far from white (mid/high ratios ≈ 10–20 with
and without noise). There the white level comes from the quantised DCT coefficients
instead (:func:`geosim.diagnose.jpeg_noise.jpeg_noise_variance`: how often noise before
the JPEG moved a coefficient out of the bin of its noise-free value), and its whiteness
is the ratio of the estimates from the low-frequency and the other coefficients.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import ndimage

from geosim.diagnose.fit import HANN_CORRELATION, fit_noise
from geosim.diagnose.jpeg_noise import JpegNoiseFit, NoiseLine, jpeg_noise_variance
from geosim.diagnose.model import NoiseEstimate
from geosim.diagnose.spectra import hann2d
from geosim.physics.radiometry import LUMA_WEIGHTS, add_sensor_noise, luma

__all__ = ["estimate_noise", "noise_dither", "MIN_NOISE_VAR_DN2", "MIN_NOISE_VAR_COMPRESSED_DN2",
           "MAX_WHITENESS", "HIGH_BAND", "MID_BAND"]

#: smallest per-band white noise variance worth claiming (DN², rounding removed)
MIN_NOISE_VAR_DN2 = 1.0
#: the same under JPEG (round 5): the DCT-censored estimate reads the coefficients the
#: quantiser kept, where the linearised JPEG model's own residue (a fraction of a
#: quantisation step) is of this size; development: noise-free JPEG scenes read 1.1 and
#: 2.5 DN² and were claimed, real noise under JPEG read ≥ 9 DN²
MIN_NOISE_VAR_COMPRESSED_DN2 = 4.0
#: largest mid/high ratio of the incoherent power still called white
#: (development half: noise + JPEG gave ratios up to ≈ 4.5, JPEG alone ≈ 15; the sample
#: site, real noise under a changed scene, 2.1–5.1)
MAX_WHITENESS = 6.0
#: under JPEG: the largest ratio of the noise variances estimated from the low-frequency
#: and from the other DCT coefficients (white noise: 1; development extension, noise
#: under JPEG: 1.0–1.6)
MAX_WHITENESS_COMPRESSED = 3.0
HIGH_BAND = (0.3, 0.5)
#: the mask of unchanged pixels is eroded by this much and tapered with this Gaussian σ
#: (px) before it multiplies the Welch windows; blocks left with less than this fraction
#: of their window are not used
MASK_ERODE_PX = 2
MASK_TAPER_PX = 1.5
MIN_TAPERED_FRACTION = 0.25
MID_BAND = (0.1, 0.25)


def noise_dither(est: NoiseEstimate | None, seed: int = 0
                 ) -> Callable[[np.ndarray, int], np.ndarray] | None:
    """``dither(img, k)``: ``img`` (bands first, DN, the scene's radiometry) plus noise
    realisation ``k`` of the claimed noise ``est`` (seeded by ``seed`` and ``k``, so
    repeated calls give the same realisation); None when no noise is claimed.

    Used where the JPEG acts on the noisy product and its noise-free simulation would be
    biased: the noise dithers the quantisation (:mod:`geosim.diagnose.jpeg_transfer`)."""
    if est is None or not est.claimed:
        return None

    def dither(img: np.ndarray, k: int) -> np.ndarray:
        rng = np.random.default_rng([int(seed), int(k)])
        return add_sensor_noise(img, gain_dn=est.gain_dn, read_var_dn2=est.read_var_dn2,
                                rng=rng)
    return dither


def masked_incoherent(sim: np.ndarray, real: np.ndarray, mask: np.ndarray,
                      origins: list[tuple[int, int]], block_px: int
                      ) -> tuple[np.ndarray, np.ndarray, int]:
    """Incoherent power S_rr (1 − γ²) of ``real`` against ``sim`` (2-D, DN² per frequency
    bin, the level of white noise of that variance), from Welch blocks whose Hann window
    is multiplied by a taper of ``mask`` (eroded by 2 px, Gaussian σ 1.5 px).

    Moved objects are excluded by ``mask`` but can fill most whole blocks of a small scene
    (development c121: 12 objects in 80 px; every block then held some, and the changed
    content's incoherent power, rising towards low frequencies, read as "not white" —
    mid/high ratio 18 with the true noise 39 DN²). With the taper they leave the estimate
    (0.96); the taper multiplies both images alike, so its own leakage stays coherent.
    Returns (incoherent power, radial frequency in cycles/px, blocks used)."""
    taper = ndimage.gaussian_filter(
        ndimage.binary_erosion(np.asarray(mask, bool), iterations=MASK_ERODE_PX).astype(float),
        MASK_TAPER_PX)
    hann = hann2d(block_px)
    s_rr = np.zeros((block_px, block_px))
    s_ss = np.zeros((block_px, block_px))
    s_rs = np.zeros((block_px, block_px), complex)
    w_sum, n = 0.0, 0
    for r0, c0 in origins:
        w = hann * taper[r0:r0 + block_px, c0:c0 + block_px]
        if w.sum() < MIN_TAPERED_FRACTION * hann.sum():
            continue
        rb = real[r0:r0 + block_px, c0:c0 + block_px]
        sb = sim[r0:r0 + block_px, c0:c0 + block_px]
        fr_ = np.fft.fft2((rb - np.sum(rb * w) / w.sum()) * w)
        fs = np.fft.fft2((sb - np.sum(sb * w) / w.sum()) * w)
        s_rr += np.abs(fr_) ** 2
        s_ss += np.abs(fs) ** 2
        s_rs += fr_ * np.conj(fs)
        w_sum += float(np.sum(w ** 2))
        n += 1
    fy = np.fft.fftfreq(block_px)[:, None]
    fx = np.fft.fftfreq(block_px)[None, :]
    f_radial = np.hypot(fy, fx)
    if n == 0:
        return np.zeros((block_px, block_px)), f_radial, 0
    inc = np.maximum(s_rr - np.abs(s_rs) ** 2 / np.maximum(s_ss, 1e-30), 0.0) / w_sum
    return inc, f_radial, n


def _hp_factor(sigma: float) -> float:
    d = np.zeros((33, 33))
    d[16, 16] = 1.0
    h = d - ndimage.gaussian_filter(d, sigma)
    return float(np.sum(h**2))


def estimate_noise(real: np.ndarray, model: np.ndarray, mask: np.ndarray, *,
                   origins: list[tuple[int, int]], block_px: int, quantized: bool,
                   uncompressed: np.ndarray | None = None,
                   block_offset_px: tuple[int, int] = (0, 0)) -> NoiseEstimate:
    """Noise in ``real`` beyond the deterministic ``model`` (both bands-first, DN).

    Parameters
    ----------
    real, model
        Real scene and refined deterministic model on the 0.5 m grid.
    mask
        Pixels for the brightness dependence (valid, outside changed regions).
    origins, block_px
        Welch blocks for the incoherent spectrum.
    quantized
        The real scene holds whole DN (its rounding, 1/12 DN² per band, is removed).
    uncompressed, block_offset_px
        When the scene was JPEG-compressed after the noise: the deterministic model
        *before* compression and the phase (row, col) of the JPEG block grid. The JPEG's
        quantisation removed the high-frequency floor, so the white level and its
        whiteness come from the censored DCT coefficients instead
        (:func:`geosim.diagnose.jpeg_noise.jpeg_noise_variance`).
    """
    w2 = float(np.sum(np.square(LUMA_WEIGHTS))) if real.shape[0] == 3 else 1.0
    g_real = luma(real) if real.shape[0] == 3 else real[0]
    g_model = luma(model) if model.shape[0] == 3 else model[0]
    incoherent, fr, n_blocks = masked_incoherent(g_model, g_real, mask, origins, block_px)
    hi = (fr >= HIGH_BAND[0]) & (fr <= HIGH_BAND[1])
    mid = (fr >= MID_BAND[0]) & (fr <= MID_BAND[1])
    level_hi = float(np.median(incoherent[hi]))
    level_mid = float(np.median(incoherent[mid]))
    qv = 1.0 / 12.0 if quantized else 0.0
    jf = None
    if uncompressed is None:
        white = max(level_hi / w2 - qv, 0.0)           # per band, DN²
        whiteness = level_mid / max(level_hi, 1e-12)
        limit = MAX_WHITENESS
    else:
        g_unc = luma(uncompressed) if uncompressed.shape[0] == 3 else uncompressed[0]
        jf = jpeg_noise_variance(g_real, g_unc, block_offset_px, mask)
        level_hi = jf.var_dn2
        white = max(jf.var_dn2 / w2 - qv, 0.0)
        lo_hi = sorted((jf.var_low_dn2, jf.var_high_dn2))
        whiteness = lo_hi[1] / max(lo_hi[0], 1e-12)
        limit = MAX_WHITENESS_COMPRESSED
    floor_dn2 = MIN_NOISE_VAR_DN2 if jf is None else MIN_NOISE_VAR_COMPRESSED_DN2
    claimed = bool(white >= floor_dn2 and whiteness <= limit)
    # evidence (reported, not used to decide): Gaussian log-likelihood ratio of the floor
    # against the rounding floor over the independent high-band estimates
    n_ind = max(int(hi.sum()) * n_blocks / (2.0 * HANN_CORRELATION), 2.0)
    floor = max(qv * w2, 1e-3)
    x = max(level_hi / floor, 1.0)
    dbic = float(n_ind * (x - 1 - np.log(x)) - 2 * np.log(n_ind))
    if jf is not None:
        dbic = jf.delta_bic
    # brightness dependence from block variances of the high-passed residual
    resid = real - model
    hp = resid - np.stack([ndimage.gaussian_filter(b, 1.0) for b in resid])
    nf = fit_noise(hp / np.sqrt(_hp_factor(1.0)), model, mask, quantized=quantized)
    s_mean = float(np.mean(model[:, mask])) if mask.any() else float(np.mean(model))
    local = nf.gain_dn * s_mean + nf.read_var_dn2
    if local > 0 and white > 0:
        k = white / local
        gain, read = nf.gain_dn * k, nf.read_var_dn2 * k
        gs, rs = nf.gain_sigma * k, nf.read_sigma * k
    else:
        gain, read, gs, rs = 0.0, white, float("inf"), float("inf")
    brightness_dn, variance_dn2 = nf.brightness_dn, nf.variance_dn2
    by_class = None if jf is None else jpeg_brightness_line(jf, w2, qv)
    if by_class is not None:
        # under JPEG the high-passed residual is the JPEG's error, not the noise: the
        # brightness dependence comes from the censored DCT likelihood by brightness class
        gain, read, gs, rs = (by_class.gain_dn, by_class.read_var_dn2, by_class.gain_sigma,
                              by_class.read_sigma)
        brightness_dn = jf.class_brightness_dn
        variance_dn2 = np.maximum(jf.class_var_dn2 / w2 - qv, 0.0)
    return NoiseEstimate(gain_dn=float(gain), read_var_dn2=float(read), gain_sigma=float(gs),
                         read_sigma=float(rs), white_var_dn2=white, whiteness=float(whiteness),
                         claimed=claimed, quantization_dn2=qv,
                         brightness_dn=brightness_dn, variance_dn2=variance_dn2,
                         mean_variance_sigma=nf.mean_variance_sigma, delta_bic=dbic,
                         estimator="spectral_floor" if jf is None else "jpeg_dct_censored")


def jpeg_brightness_line(jf: JpegNoiseFit, w2: float, qv: float) -> NoiseLine | None:
    """Per-band noise a·s + b under JPEG from the censored DCT likelihood's line over the
    blocks' brightness classes (:attr:`JpegNoiseFit.line`, luma), the rounding ``qv``
    removed from b. Luma noise of bands with variance a·s + b and similar brightness is
    Σ w_b² (a s + b) = ``w2`` (a s + b). None without the line."""
    line = jf.line
    if line is None:
        return None
    return NoiseLine(line.gain_dn / w2, max(line.read_var_dn2 / w2 - qv, 0.0),
                     line.gain_sigma / w2, line.read_sigma / w2)
