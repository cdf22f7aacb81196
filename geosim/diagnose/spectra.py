"""Welch-averaged power and cross spectra on the 0.5 m grid.

The transfer function between a simulation ``s`` and the real scene ``r`` is
estimated from the cross-spectrum, H(f) = S_rs(f) / S_ss(f), and its magnitude-
squared coherence γ²(f) = |S_rs|² / (S_ss S_rr) (Bendat & Piersol, *Random Data*,
ch. 9). Additive noise in ``r`` that is independent of ``s`` does not bias H (it
only lowers γ²), which is what lets the diagnosis tell noise from blur.

Conventions: frequencies in cycles per pixel (``numpy.fft.fftfreq``), ``fx``
along columns (east), ``fy`` along rows (south). The orientation of a frequency
vector is given as an angle clockwise from grid north in [0, 180), the same
convention as ``direction_deg`` in :mod:`geosim.physics.otf`: a ripple whose
wave vector points along θ has frequency component ``along_direction(fy, fx, θ)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "CrossSpectrum", "block_origins", "screen_blocks", "cross_spectrum", "frequency_angle_deg",
    "polar_bin_mean", "power_spectrum", "radial_profile", "directional_profiles",
    "spectral_error", "log_power_ratio", "hann2d", "unexplained_power",
    "block_ffts",
]


def hann2d(n: int) -> np.ndarray:
    """Separable 2-D Hann window of side ``n`` (periodic form), unit RMS."""
    w1 = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n)
    w = np.outer(w1, w1)
    return w / np.sqrt(np.mean(w**2))


def block_origins(shape: tuple[int, int], *, block_px: int, valid: np.ndarray | None = None,
                  overlap: float = 0.5, min_valid_fraction: float = 1.0
                  ) -> list[tuple[int, int]]:
    """Top-left (row, col) of Welch blocks that lie inside the valid area.

    Parameters
    ----------
    shape
        (rows, cols) of the image.
    block_px
        Block side in pixels.
    valid
        Bool mask, True = usable pixel; blocks with a smaller valid fraction than
        ``min_valid_fraction`` are skipped.
    overlap
        Fractional overlap of neighbouring blocks (0.5 for Welch with Hann).
    """
    rows, cols = shape
    step = max(1, int(round(block_px * (1.0 - overlap))))
    out = []
    for r0 in range(0, rows - block_px + 1, step):
        for c0 in range(0, cols - block_px + 1, step):
            if valid is not None:
                frac = valid[r0:r0 + block_px, c0:c0 + block_px].mean()
                if frac < min_valid_fraction:
                    continue
            out.append((r0, c0))
    return out


@dataclass
class CrossSpectrum:
    """Welch estimates of auto and cross spectra for a (simulation, real) pair.

    Arrays are full 2-D FFT grids of shape (block_px, block_px) in ``fftfreq`` order.

    Attributes
    ----------
    s_ss, s_rr
        Power spectra of simulation and real scene (DN² per unit frequency area, up to a
        constant common to both).
    s_rs
        Cross spectrum E[R · conj(S)].
    n_blocks
        Number of averaged blocks (the degrees of freedom are ≈ 2 per block and band).
    """

    fy: np.ndarray
    fx: np.ndarray
    s_ss: np.ndarray
    s_rr: np.ndarray
    s_rs: np.ndarray
    n_blocks: int
    block_px: int

    @property
    def transfer(self) -> np.ndarray:
        """Complex transfer function estimate H = S_rs / S_ss."""
        return self.s_rs / np.maximum(self.s_ss, 1e-30)

    @property
    def coherence(self) -> np.ndarray:
        """Magnitude-squared coherence γ² in [0, 1]."""
        den = np.maximum(self.s_ss * self.s_rr, 1e-300)
        return np.clip(np.abs(self.s_rs) ** 2 / den, 0.0, 1.0)

    @property
    def f_radial(self) -> np.ndarray:
        """Radial frequency |f| in cycles per pixel."""
        return np.hypot(self.fy, self.fx)


def _detrend(block: np.ndarray) -> np.ndarray:
    return block - block.mean()


def block_ffts(img: np.ndarray, origins: list[tuple[int, int]], block_px: int,
               window: np.ndarray) -> np.ndarray:
    """FFTs (n_blocks, block_px, block_px) of the blocks of a 2-D image (real or complex)
    at ``origins``, each less its mean and multiplied by ``window``."""
    out = np.empty((len(origins), block_px, block_px), dtype=complex)
    for k, (r0, c0) in enumerate(origins):
        out[k] = np.fft.fft2(_detrend(img[r0:r0 + block_px, c0:c0 + block_px]) * window)
    return out


def unexplained_power(regressors: list[np.ndarray], target: np.ndarray, *,
                      held_rel: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Per frequency bin, the power of ``target`` that no linear combination of the
    ``regressors`` explains (the complement of the multiple coherence; Bendat & Piersol,
    *Random Data*, ch. 7).

    Parameters
    ----------
    regressors
        Block spectra (n_blocks, rows, cols), complex, of each input; the first one's
        power at a bin is the scale against which the others count as holding anything
        there (``held_rel``).
    target
        Block spectra (n_blocks, rows, cols) of the output.
    held_rel
        A regressor whose power at a bin is below this fraction of the first one's is not
        counted there (the sharp cell masks leave ~1e-16 of it).

    Returns
    -------
    (rss, n_held)
        rss (rows, cols): Σ over blocks of |target − Σ_j a_j regressor_j|², the complex
        coefficients a_j fitted per bin by least squares (units of power × blocks);
        n_held (rows, cols): how many regressors hold power at each bin (the fit's
        parameters there, for the degrees of freedom).
    """
    p = len(regressors)
    gram = np.empty(target.shape[1:] + (p, p), dtype=complex)
    proj = np.empty(target.shape[1:] + (p,), dtype=complex)
    for i, xi in enumerate(regressors):
        proj[..., i] = np.sum(np.conj(xi) * target, axis=0)
        for j in range(i, p):
            gram[..., i, j] = np.sum(np.conj(xi) * regressors[j], axis=0)
            gram[..., j, i] = np.conj(gram[..., i, j])
    power = np.real(np.einsum("...ii->...i", gram))
    n_held = np.sum(power > held_rel * power[..., :1], axis=-1)
    # a relative ridge keeps the empty regressors (no power at the bin) from making the
    # system singular without changing the fit of the others
    ridge = 1e-9 * power.sum(axis=-1)[..., None, None] * np.eye(p)
    coef = np.linalg.solve(gram + ridge, proj[..., None])[..., 0]
    total = np.sum(np.abs(target) ** 2, axis=0)
    explained = np.real(np.sum(np.conj(proj) * coef, axis=-1))
    return np.maximum(total - explained, 0.0), n_held


def cross_spectrum(sim: np.ndarray, real: np.ndarray, *, block_px: int = 32,
                   valid: np.ndarray | None = None, overlap: float = 0.5,
                   origins: list[tuple[int, int]] | None = None) -> CrossSpectrum:
    """Welch cross-spectral estimate between two co-registered images.

    Parameters
    ----------
    sim, real
        2-D images (rows, cols) on the same grid, or bands-first stacks (bands are then
        treated as further realisations, which suits a transfer function shared by the
        bands).
    block_px
        Welch block side in pixels; the frequency resolution is 1 / block_px cyc/px.
    valid
        Bool mask of usable pixels; only fully valid blocks are used.
    origins
        Explicit block origins (overrides ``valid``/``overlap``), e.g. for a split.

    Returns
    -------
    CrossSpectrum
    """
    s = np.asarray(sim, dtype=float)
    r = np.asarray(real, dtype=float)
    if s.shape != r.shape:
        raise ValueError(f"sim and real must have the same shape, got {s.shape} and {r.shape}")
    if s.ndim == 2:
        s, r = s[np.newaxis], r[np.newaxis]
    if origins is None:
        origins = block_origins(s.shape[-2:], block_px=block_px, valid=valid, overlap=overlap)
    if not origins:
        raise ValueError(f"no fully valid {block_px}x{block_px} block in a {s.shape[-2:]} image")
    w = hann2d(block_px)
    s_ss = np.zeros((block_px, block_px))
    s_rr = np.zeros((block_px, block_px))
    s_rs = np.zeros((block_px, block_px), dtype=complex)
    for sb, rb in zip(s, r, strict=True):
        fs = block_ffts(sb, origins, block_px, w)
        fr = block_ffts(rb, origins, block_px, w)
        s_ss += np.sum(np.abs(fs) ** 2, axis=0)
        s_rr += np.sum(np.abs(fr) ** 2, axis=0)
        s_rs += np.sum(fr * np.conj(fs), axis=0)
    n = len(origins) * s.shape[0]
    norm = 1.0 / (n * block_px * block_px)
    fy = np.fft.fftfreq(block_px)[:, np.newaxis] * np.ones((1, block_px))
    fx = np.fft.fftfreq(block_px)[np.newaxis, :] * np.ones((block_px, 1))
    return CrossSpectrum(fy=fy, fx=fx, s_ss=s_ss * norm, s_rr=s_rr * norm, s_rs=s_rs * norm,
                         n_blocks=n, block_px=block_px)


def apply_taper(img: np.ndarray, taper: np.ndarray | None) -> np.ndarray:
    """``img`` (rows, cols) pulled towards its ``taper``-weighted mean where the weight
    (rows, cols, in [0, 1]) is below 1: ``c + taper · (img − c)``. Blocks cut from it keep
    their content where the weight is 1 and lose it smoothly where it falls to 0. ``img``
    itself where ``taper`` is None."""
    if taper is None:
        return img
    c = float(np.sum(img * taper) / max(float(np.sum(taper)), 1e-12))
    return c + taper * (img - c)


def screen_blocks(sim: np.ndarray, real: np.ndarray, origins: list[tuple[int, int]],
                  block_px: int, *, min_rho: float = 0.3, n_mad: float = 4.0
                  ) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Drop Welch blocks where simulation and reality do not show the same scene.

    A block whose windowed correlation coefficient ρ is below ``min_rho`` or more than
    ``n_mad`` robust deviations below the median holds content one image lacks (moved
    cattle, other shadows, water): such content is not linear in the simulation and would
    bias the transfer function low (it adds to S_ss but not to S_rs).

    Returns
    -------
    kept origins, ρ of every input block
    """
    w = hann2d(block_px)
    rho = np.empty(len(origins))
    for k, (r0, c0) in enumerate(origins):
        a = sim[r0:r0 + block_px, c0:c0 + block_px]
        b = real[r0:r0 + block_px, c0:c0 + block_px]
        a = (a - a.mean()) * w
        b = (b - b.mean()) * w
        rho[k] = float(np.sum(a * b) / max(np.sqrt(np.sum(a * a) * np.sum(b * b)), 1e-12))
    if rho.size == 0:
        return origins, rho
    med = float(np.median(rho))
    mad = 1.4826 * float(np.median(np.abs(rho - med)))
    keep = (rho >= min_rho) & (rho >= med - n_mad * max(mad, 0.01))
    return [o for o, k in zip(origins, keep, strict=True) if k], rho


def power_spectrum(image: np.ndarray, *, block_px: int = 32, valid: np.ndarray | None = None,
                   origins: list[tuple[int, int]] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Welch power spectrum of a 2-D image: (fy, fx, P) on the block FFT grid."""
    cs = cross_spectrum(image, image, block_px=block_px, valid=valid, origins=origins)
    return cs.fy, cs.fx, cs.s_ss


def frequency_angle_deg(fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
    """Orientation of frequency vectors, degrees clockwise from grid north, in [0, 180).

    (fx, −fy) are the (east, north) components of the wave vector.
    """
    return np.mod(np.degrees(np.arctan2(fx, -fy)), 180.0)


def polar_bin_mean(values: np.ndarray, fy: np.ndarray, fx: np.ndarray, *, n_radial: int,
                   n_angular: int = 1, f_min: float | None = None, f_max: float = 0.5,
                   weights: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Average ``values`` in radial × angular frequency bins.

    Returns
    -------
    f_centres : (n_radial,) cycles per pixel
    angle_centres_deg : (n_angular,) degrees clockwise from north
    means : (n_angular, n_radial) bin means (NaN where a bin is empty)
    counts : (n_angular, n_radial) number of frequency samples per bin
    """
    fr = np.hypot(fy, fx)
    if f_min is None:
        f_min = 1.0 / fy.shape[0]
    edges = np.linspace(f_min, f_max, n_radial + 1)
    ang = frequency_angle_deg(fy, fx)
    a_edges = np.linspace(0.0, 180.0, n_angular + 1)
    # centre angular sectors on 0, 180/n, ... so that the north–south sector is whole
    ang_shift = np.mod(ang + 90.0 / n_angular, 180.0)
    ri = np.digitize(fr, edges) - 1
    ai = np.clip(np.digitize(ang_shift, a_edges) - 1, 0, n_angular - 1)
    ok = (ri >= 0) & (ri < n_radial)
    w = np.ones_like(fr) if weights is None else weights
    sums = np.zeros((n_angular, n_radial))
    wsum = np.zeros((n_angular, n_radial))
    counts = np.zeros((n_angular, n_radial), dtype=int)
    np.add.at(sums, (ai[ok], ri[ok]), (values * w)[ok])
    np.add.at(wsum, (ai[ok], ri[ok]), w[ok])
    np.add.at(counts, (ai[ok], ri[ok]), 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(wsum > 0, sums / np.where(wsum > 0, wsum, 1), np.nan)
    return 0.5 * (edges[1:] + edges[:-1]), np.arange(n_angular) * 180.0 / n_angular, means, \
        counts


def radial_profile(values: np.ndarray, fy: np.ndarray, fx: np.ndarray, *, n_bins: int = 16,
                   weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Azimuthally averaged profile: (f_centres cyc/px, mean per bin)."""
    f, _, m, _ = polar_bin_mean(values, fy, fx, n_radial=n_bins, n_angular=1, weights=weights)
    return f, m[0]


def directional_profiles(values: np.ndarray, fy: np.ndarray, fx: np.ndarray, *,
                         n_sectors: int = 4, n_bins: int = 12,
                         weights: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radial profiles within angular sectors: (f_centres, sector_centres_deg, means)."""
    f, a, m, _ = polar_bin_mean(values, fy, fx, n_radial=n_bins, n_angular=n_sectors,
                                weights=weights)
    return f, a, m


def spectral_error(sim: np.ndarray | list[np.ndarray], real: np.ndarray, *,
                   valid: np.ndarray | None = None, block_px: int = 32, n_radial: int = 12,
                   n_angular: int = 8, origins: list[tuple[int, int]] | None = None) -> float:
    """RMS over radial × angular frequency bins of log10(P_sim / P_real).

    Power spectra are Welch estimates on the grey level (or on each given 2-D image);
    bins run from 1/block_px to 0.5 cycles per pixel radially and over [0, 180) in
    orientation. 0 means identical spectra; 0.3 means a typical factor of 2 in power.
    ``sim`` may be a list of 2-D images (noise realisations of one model): their Welch
    powers are averaged, an estimate of the model's *expected* spectrum.
    """
    ratio = log_power_ratio(sim, real, valid=valid, block_px=block_px, n_radial=n_radial,
                            n_angular=n_angular, origins=origins)
    ratio = ratio[np.isfinite(ratio)]
    return float(np.sqrt(np.mean(ratio**2)))


def log_power_ratio(sim: np.ndarray | list[np.ndarray], real: np.ndarray, *,
                    valid: np.ndarray | None = None, block_px: int = 32, n_radial: int = 12,
                    n_angular: int = 8, origins: list[tuple[int, int]] | None = None
                    ) -> np.ndarray:
    """log10(P_sim / P_real) per radial × angular bin, (n_angular, n_radial), NaN where a
    bin is empty: the terms of :func:`spectral_error` (same arguments)."""
    sims = sim if isinstance(sim, list) else [sim]
    r = np.asarray(real, dtype=float)
    s_ss = None
    for one in sims:
        cs = cross_spectrum(np.asarray(one, dtype=float), r, block_px=block_px, valid=valid,
                            origins=origins)
        s_ss = cs.s_ss if s_ss is None else s_ss + cs.s_ss
    _, _, ps, _ = polar_bin_mean(s_ss / len(sims), cs.fy, cs.fx, n_radial=n_radial,
                                 n_angular=n_angular)
    _, _, pr, _ = polar_bin_mean(cs.s_rr, cs.fy, cs.fx, n_radial=n_radial, n_angular=n_angular)
    ok = np.isfinite(ps) & np.isfinite(pr)
    ratio = np.full(ps.shape, np.nan)
    ratio[ok] = np.log10(np.maximum(ps[ok], 1e-20) / np.maximum(pr[ok], 1e-20))
    return ratio
