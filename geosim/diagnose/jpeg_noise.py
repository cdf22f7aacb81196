"""Sensor noise under JPEG, from the quantised DCT coefficients of the real scene.

JPEG quantises each 8×8 block's DCT coefficient k to a multiple of its step q_k and drops
most high-frequency power: the white floor that :mod:`geosim.diagnose.noise` reads at
0.3–0.5 cycles/px is gone (the steps there are far coarser than the noise), so noise
under JPEG cannot be read from the spectrum. What survives is exact, though: the real
scene's coefficient c_k of a block is the quantisation of (model coefficient μ_k + noise),
so the index j = round(c_k / q_k) tells that μ_k + noise fell in [(j − ½) q_k, (j + ½) q_k).
Each DCT frequency k gets its own gain g_k (real ≈ g_k μ_k + noise, profiled out): a blur
or contrast the model lacks scales the coefficients coherently and is not noise.
The noise variance σ² is the maximum of this interval-censored Gaussian likelihood, summed
over blocks and coefficients; noise before JPEG raises the chance that a coefficient leaves
the bin of its noise-free value, which is what the likelihood measures (no assumption on
the spectrum the JPEG leaves). The steps q_k are read from the real scene itself (the
lattice its coefficients lie on), so no quantisation table or quality is assumed.

The JPEG DCT is orthonormal, so white pixel noise of variance σ² gives every AC
coefficient the variance σ², and luma noise is Σ w_b² σ_b² for independent bands.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import fft as sfft
from scipy.special import ndtr

__all__ = ["JpegNoiseFit", "block_dct", "whole_blocks", "block_grid", "jitter_density",
           "lattice_steps",
           "lattice_evidence", "jpeg_noise_variance", "MIN_LATTICE_GAIN", "BRIGHTNESS_CLASSES",
           "NoiseLine"]

#: RMS jitter (DN, coefficient units) of the decoded coefficients around their lattice
#: (integer Y conversion, integer DCT, rounding of the decoded pixels to 8 bit)
LATTICE_JITTER = 0.5
#: variance the encoder's and decoder's integer arithmetic add to every coefficient (DN²);
#: measured: Pillow round trips of a noise-free smooth image give 0 with this floor
ARITHMETIC_VAR_DN2 = 0.25
#: fraction of coefficients allowed to be outliers (edges of moved objects, misfit)
OUTLIER_FRACTION = 0.02
#: a coefficient whose step is this coarse (or coarser) holds only zeros: no information
MAX_STEP = 255
#: smallest lattice evidence (log-likelihood gain, :func:`lattice_evidence`) for which
#: a scene counts as JPEG-compressed on its grid (development half: compressed scenes
#: 350–550 at quality 35–67, and 35–160 when re-encoded at quality 90; uncompressed
#: scenes −52 to −0.4, at the block grid found and at others)
MIN_LATTICE_GAIN = 10.0
#: grid of luma noise variances searched (DN²)
VAR_GRID_DN2 = np.concatenate([[0.0], np.geomspace(0.02, 400.0, 161)])
#: per-coefficient gains g searched (real ≈ g·model + noise in each DCT frequency): a blur
#: the model lacks scales a frequency's coefficients, coherently, and is not noise (as the
#: per-frequency transfer absorbs it in the spectral estimate)
GAIN_GRID = np.linspace(0.6, 1.4, 17)
#: classes of block brightness for the noise's brightness dependence (var = a·s + b),
#: each of at least :data:`MIN_CLASS_BLOCKS` blocks
BRIGHTNESS_CLASSES = 3
MIN_CLASS_BLOCKS = 8
#: the low-frequency DCT coefficients (u + v ≤ 2) of the 64, row-major: their noise
#: estimate against the others' is the whiteness test
LOW_FREQUENCY = np.add(*np.divmod(np.arange(64), 8)) <= 2


@dataclass(frozen=True)
class NoiseLine:
    """Noise variance ``gain_dn`` · s + ``read_var_dn2`` (DN² per DN of brightness s, DN²;
    both ≥ 0) and their standard errors (half-widths of the profile log-likelihood
    within ½ of its maximum)."""

    gain_dn: float
    read_var_dn2: float
    gain_sigma: float
    read_sigma: float


@dataclass
class JpegNoiseFit:
    """Luma noise variance from the censored DCT coefficients.

    ``var_dn2``: maximum-likelihood luma noise variance over all informative coefficients
    (arithmetic floor removed); ``var_low_dn2`` / ``var_high_dn2``: the same from the
    low-frequency (u + v ≤ 2) and the other coefficients (white noise: equal; a misfit of
    the model: unequal); ``steps``: the 8×8 quantisation steps found (0 = not used);
    ``n_blocks``: blocks used; ``offset_px``: the block grid's phase used (row, col);
    ``delta_bic``: 2 Δ log-likelihood of ``var_dn2`` against no noise, minus ln(values).
    """

    var_dn2: float
    var_low_dn2: float
    var_high_dn2: float
    steps: np.ndarray
    n_blocks: int
    offset_px: tuple[int, int] = (0, 0)
    delta_bic: float = 0.0
    #: the blocks in :data:`BRIGHTNESS_CLASSES` classes of the model's brightness: their
    #: mean luma (DN) and the maximum-likelihood luma noise variance of each class (DN²);
    #: empty where too few blocks
    class_brightness_dn: np.ndarray = field(default_factory=lambda: np.zeros(0))
    class_var_dn2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: the luma noise line of maximum joint likelihood over the classes; None without them
    line: NoiseLine | None = None


def block_dct(grey: np.ndarray, offset_px: tuple[int, int], mask: np.ndarray | None = None
              ) -> np.ndarray:
    """Orthonormal 8×8 DCT of the blocks starting at ``offset_px`` (row, col), (n, 64);
    only blocks wholly inside ``mask`` when given."""
    r0, c0 = int(offset_px[0]) % 8, int(offset_px[1]) % 8
    g = np.asarray(grey, float)[r0:, c0:]
    nr, nc = g.shape[0] // 8, g.shape[1] // 8
    blk = g[:nr * 8, :nc * 8].reshape(nr, 8, nc, 8).transpose(0, 2, 1, 3)
    blk = blk[whole_blocks(mask, offset_px)] if mask is not None else blk.reshape(-1, 8, 8)
    return sfft.dctn(blk, type=2, norm="ortho", axes=(-2, -1)).reshape(-1, 64)


def whole_blocks(mask: np.ndarray, offset_px: tuple[int, int]) -> np.ndarray:
    """Bool (block rows, block cols): the 8×8 blocks starting at ``offset_px`` (row, col)
    that lie wholly inside ``mask`` (the blocks :func:`block_dct` keeps, in its order)."""
    r0, c0 = int(offset_px[0]) % 8, int(offset_px[1]) % 8
    m = np.asarray(mask, bool)[r0:, c0:]
    nr, nc = m.shape[0] // 8, m.shape[1] // 8
    return m[:nr * 8, :nc * 8].reshape(nr, 8, nc, 8).all(axis=(1, 3))


def jitter_density(d: np.ndarray, step: np.ndarray | float,
                   jitter: float = LATTICE_JITTER) -> np.ndarray:
    """Unnormalised density of decoded values offset ``d`` from their nearest lattice point
    (lattice ``step``), with Gaussian ``jitter``: the nearest point and its two neighbours,
    Σ_m exp(−½ ((d + m·step) / jitter)²)."""
    return sum(np.exp(-0.5 * ((d + m * step) / jitter) ** 2) for m in (-1, 0, 1))


def lattice_steps(coef: np.ndarray, *, jitter: float = LATTICE_JITTER,
                  max_step: int = MAX_STEP) -> np.ndarray:
    """Quantisation step of each coefficient (columns of ``coef``): the integer step q whose
    lattice, with Gaussian jitter, is most likely to have produced the values.

    The likelihood of a value c is q · Σ_m φ((c − m q) / jitter) / jitter: a finer lattice
    fits any value but spreads its probability over more points, a coarser one must
    pass through every value."""
    qs = np.arange(1, max_step + 1, dtype=float)[:, None]
    steps = np.zeros(coef.shape[1])
    for k in range(coef.shape[1]):
        x = coef[:, k][None, :]
        d = x - qs * np.rint(x / qs)
        dens = jitter_density(d, qs, jitter)
        ll = np.sum(np.log(np.maximum(qs * dens / (jitter * np.sqrt(2 * np.pi)), 1e-300)),
                    axis=1)
        steps[k] = qs[int(np.argmax(ll)), 0]
    return steps


def _lattice_gain(x: np.ndarray, *, jitter: float = LATTICE_JITTER, max_step: int = 64
                  ) -> float:
    """Log-likelihood gain of the best lattice (step ≥ 2) over none (step 1) for values x."""
    qs = np.arange(1, max_step + 1, dtype=float)[:, None]
    d = x[None, :] - qs * np.rint(x[None, :] / qs)
    dens = jitter_density(d, qs, jitter)
    ll = np.sum(np.log(np.maximum(qs * dens, 1e-300)), axis=1)
    return float(np.max(ll[1:]) - ll[0])


def lattice_evidence(grey: np.ndarray, offset_px: tuple[int, int], mask: np.ndarray) -> float:
    """Log-likelihood gain of a quantisation lattice (step ≥ 2) over none for the lowest AC
    coefficients (k = 1, 8, 9) of the 8×8 blocks at ``offset_px``: the trace a JPEG leaves
    in its own block grid (≫ 0, hundreds on a 128 px scene at quality ≤ 75), which block-edge
    steps of another origin (a structured residual) do not (≤ 0)."""
    coef = block_dct(grey, offset_px, mask)
    if coef.shape[0] < 8:
        return 0.0
    return float(sum(_lattice_gain(coef[:, k]) for k in (1, 8, 9)))


def block_grid(grey: np.ndarray, mask: np.ndarray, first_guess: tuple[int, int] = (0, 0)
               ) -> tuple[int, int]:
    """Phase (row, col) of the JPEG block grid: the one whose lowest AC coefficients lie
    best on a lattice (``first_guess`` wins ties)."""
    best, best_gain = (int(first_guess[0]) % 8, int(first_guess[1]) % 8), -np.inf
    cands = [best] + [(r, c) for r in range(8) for c in range(8) if (r, c) != best]
    for off in cands:
        coef = block_dct(grey, off, mask)
        if coef.shape[0] < 8:
            continue
        gain = sum(_lattice_gain(coef[:, k]) for k in (1, 8, 9))
        if gain > best_gain + 1e-9:
            best, best_gain = off, gain
    return best


def _censored_loglik(j: np.ndarray, mu: np.ndarray, q: float, spread: float,
                     var_grid: np.ndarray) -> np.ndarray:
    """Log-likelihood over ``var_grid`` of bin indices ``j`` given means ``mu``, with a
    small uniform outlier part over ``spread`` (DN), per value: (len(var_grid), len(j))."""
    lo = (j - 0.5) * q - mu
    hi = (j + 0.5) * q - mu
    s = np.sqrt(var_grid + ARITHMETIC_VAR_DN2)[:, None]
    p = ndtr(hi[None] / s) - ndtr(lo[None] / s)
    out = OUTLIER_FRACTION * min(1.0, q / max(spread, q))
    return np.log((1 - OUTLIER_FRACTION) * p + out)


def jpeg_noise_variance(real_grey: np.ndarray, model_grey: np.ndarray,
                        offset_px: tuple[int, int], mask: np.ndarray) -> JpegNoiseFit:
    """Luma noise variance (DN²) of a JPEG'd ``real_grey`` beyond ``model_grey`` (the
    deterministic model *before* compression, same grid), from blocks wholly in ``mask``
    on the JPEG block grid (``offset_px``: the row, col phase of the block edges found by
    the compression test; checked against the lattice, :func:`block_grid`)."""
    offset_px = block_grid(real_grey, mask, offset_px)
    cr = block_dct(real_grey, offset_px, mask)
    cm = block_dct(model_grey, offset_px, mask)
    empty = JpegNoiseFit(0.0, 0.0, 0.0, np.zeros((8, 8)), int(cr.shape[0]), offset_px)
    if cr.shape[0] < 8:
        return empty
    steps = lattice_steps(cr)
    steps[0] = 0.0                      # DC: the level shift and the radiometry misfit
    steps[steps >= MAX_STEP] = 0.0
    if not np.any(steps > 1):
        return empty
    ll_low, ll_high = _profiles(cr, cm, steps)
    ll = ll_low + ll_high
    best = VAR_GRID_DN2[int(np.argmax(ll))]
    n_values = int(np.sum(steps > 1)) * int(cr.shape[0])
    dbic = float(2.0 * (np.max(ll) - ll[0]) - np.log(max(n_values, 2)))
    v_low = (VAR_GRID_DN2[int(np.argmax(ll_low))] if np.any(steps[LOW_FREQUENCY] > 1)
             else best)
    v_high = (VAR_GRID_DN2[int(np.argmax(ll_high))] if np.any(steps[~LOW_FREQUENCY] > 1)
              else best)
    # the brightness dependence: the same likelihood on classes of block brightness (the
    # model's block mean: the orthonormal DC is 8 × the mean)
    brightness = cm[:, 0] / 8.0
    order = np.argsort(brightness, kind="stable")
    classes = [c for c in np.array_split(order, BRIGHTNESS_CLASSES)
               if c.size >= MIN_CLASS_BLOCKS]
    c_s, c_ll = [], []
    if len(classes) >= 2:
        for c in classes:
            c_s.append(float(np.mean(brightness[c])))
            c_ll.append(sum(_profiles(cr[c], cm[c], steps)))
    c_v = [float(VAR_GRID_DN2[int(np.argmax(lc))]) for lc in c_ll]
    line = _noise_line(np.array(c_s), c_ll) if len(c_s) >= 2 else None
    return JpegNoiseFit(float(best), float(v_low), float(v_high),
                        np.where(steps > 1, steps, 0.0).reshape(8, 8), int(cr.shape[0]),
                        offset_px, dbic, np.array(c_s), np.array(c_v), line)


#: slopes (luma DN² per DN) searched for the noise line; its intercepts (luma DN²) are
#: searched over :data:`VAR_GRID_DN2`
SLOPE_GRID = np.linspace(0.0, 2.0, 201)


def _noise_line(brightness: np.ndarray, class_ll: list[np.ndarray]) -> NoiseLine | None:
    """The line var = slope · s + intercept (luma, both ≥ 0) that maximises the summed
    class log-likelihoods (each a profile over :data:`VAR_GRID_DN2`, interpolated at the
    line's variance for the class's brightness ``s``), with the half-widths of the
    profile log-likelihood within ½ of the maximum as standard errors."""
    if float(np.ptp(brightness)) <= 0:
        return None
    var = SLOPE_GRID[:, None, None] * brightness[None, None, :] + VAR_GRID_DN2[None, :, None]
    total = sum(np.interp(var[..., k], VAR_GRID_DN2, ll, right=-np.inf)
                for k, ll in enumerate(class_ll))
    i, j = np.unravel_index(int(np.argmax(total)), total.shape)
    near = total >= total[i, j] - 0.5
    slopes, intercepts = SLOPE_GRID[near.any(axis=1)], VAR_GRID_DN2[near.any(axis=0)]
    return NoiseLine(float(SLOPE_GRID[i]), float(VAR_GRID_DN2[j]),
                     max(float(np.ptp(slopes)) / 2.0, float(SLOPE_GRID[1])),
                     max(float(np.ptp(intercepts)) / 2.0, float(VAR_GRID_DN2[1])))


def _profiles(cr: np.ndarray, cm: np.ndarray, steps: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Log-likelihood over :data:`VAR_GRID_DN2` of the blocks' real coefficients ``cr``
    (n, 64) given the model's ``cm``, summed over the quantised coefficients (``steps`` > 1;
    each with its own gain, profiled out), split into the low-frequency (u + v ≤ 2) and
    the other coefficients."""
    ll_low = np.zeros(VAR_GRID_DN2.size)
    ll_high = np.zeros(VAR_GRID_DN2.size)
    for k in np.flatnonzero(steps > 1):  # a step of 1 is no quantisation: not censored
        q = float(steps[k])
        j = np.rint(cr[:, k] / q)
        spread = 6.0 * float(np.std(cr[:, k]))
        ll = np.max([_censored_loglik(j, g * cm[:, k], q, spread, VAR_GRID_DN2).sum(axis=1)
                     for g in GAIN_GRID], axis=0)
        if LOW_FREQUENCY[k]:
            ll_low += ll
        else:
            ll_high += ll
    return ll_low, ll_high

