"""Fitting the extended forward model.

Blur (Fourier domain)
---------------------
Let S_q be the paper's model at optical quality q (exact, aliasing included) and
R the real scene, both on the 0.5 m grid. With S_0 = S_{q_0} the sharpest
simulation of a Q grid q_0 < q_1 < … and Welch spectra taken against S_0,

    T_R(f) = S_{R,0} / S_{0,0}      (measured transfer, real vs sharpest simulation)
    G_j(f) = S_{j,0} / S_{0,0}      (measured transfer between simulations, exact)

the extended model R = g · H_e ⊛ S_q + noise predicts T_R = g · H_e(f; θ) · G(q)(f),
with G(q) interpolated linearly in log q between grid simulations. Because G is
measured on the same blocks as T_R, aliasing and windowing enter both alike and
the Q part of the model is exact at grid points: a control made with the paper's
model is fitted to within interpolation error, so no effect is needed to explain
it. Residuals are weighted by the coherence-based variance of the estimate,
var(T̂) ≈ (1 − γ²) / (2 n γ²) · |T|² (Bendat & Piersol), plus a floor.

Radiometry and noise (image domain)
-----------------------------------
Per-band gains/offsets by least squares of R on the blurred model; noise variance
a·s + b from block variances of the residual against block brightness.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from geosim.diagnose.alias_cells import ALIAS_CELLS, AliasPieces
from geosim.diagnose.effects import NON_LSI, BlurEffect, get_effect
from geosim.diagnose.spectra import block_ffts, hann2d, unexplained_power

__all__ = [
    "SpectralData", "TransferFit", "build_spectral_data", "fit_transfer", "model_transfer",
    "blur_transfer", "evaluate_chi2", "fit_radiometry", "fit_noise", "NoiseFit", "RadiometryFit",
    "HANN_CORRELATION", "BinFilter", "used_bins", "measured_transfer", "transfer_variance",
    "alias_unexplained_share",
]

#: number of frequency bins one independent Welch estimate spreads over with a 2-D Hann window
HANN_CORRELATION = 2.25
#: floor of the standard error of the measured transfer (model approximations), dimensionless
TRANSFER_FLOOR = 0.004
#: fewest Welch blocks on which the alias-cell regression (9 complex coefficients per
#: bin) is trusted to say how much of the scene's incoherent power the cells explain
SHARE_MIN_BLOCKS = 18
#: most blocks the regression uses (evenly spaced among them; the share is a property of
#: the scene and its frequencies, and 10 stacks of block FFTs of a large scene are large)
SHARE_MAX_BLOCKS = 256


@dataclass
class SpectralData:
    """Measured transfers on a half-plane of frequencies (DC excluded).

    Attributes
    ----------
    fy, fx
        Frequencies, cycles per pixel (1-D arrays of the used samples).
    t_real
        Measured complex transfer real / sharpest simulation.
    g_q
        (n_q, n_f) measured transfers sharpest → simulation at ``q_grid[j]``.
    q_grid
        Q values of the grid simulations (increasing).
    var
        Variance of each ``t_real`` sample (real and imaginary parts each).
    n_blocks
        Number of Welch blocks averaged.
    """

    fy: np.ndarray
    fx: np.ndarray
    t_real: np.ndarray
    g_q: np.ndarray
    q_grid: np.ndarray
    var: np.ndarray
    n_blocks: int
    coherence: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: (n_cells, n_q, n_f) measured transfers sharpest → the part of the simulation at
    #: ``q_grid[j]`` folded from each alias cell (:mod:`geosim.diagnose.alias_cells`);
    #: None: the simulations hold no content beyond the Nyquist (or none was split)
    alias_g: np.ndarray | None = None

    @property
    def n_eff(self) -> float:
        """Independent real residual values (2 per frequency, divided by the Hann spread)."""
        return 2.0 * self.t_real.size / HANN_CORRELATION

    @cached_property
    def log_q_grid(self) -> np.ndarray:
        """ln of ``q_grid`` (computed once: :meth:`g_at` runs in every residual of a fit)."""
        return np.log(self.q_grid)

    def _weights(self, q: float) -> tuple[int, float]:
        """(j, t): q lies at t between grid members j and j + 1 in log q (clamped)."""
        lq = self.log_q_grid
        # scalar clamps (the same values as np.clip, a third of its per-call cost)
        x = min(max(np.log(q), lq[0]), lq[-1])
        j = min(max(int(np.searchsorted(lq, x)) - 1, 0), len(lq) - 2)
        return j, (x - lq[j]) / (lq[j + 1] - lq[j])

    def g_at(self, q: float) -> np.ndarray:
        """G(q)(f) by linear interpolation in log q (clamped to the grid)."""
        j, t = self._weights(q)
        return (1 - t) * self.g_q[j] + t * self.g_q[j + 1]

    @cached_property
    def _alias_held(self) -> np.ndarray:
        """Per member of ``q_grid``: whether its alias parts hold anything (computed once:
        :meth:`alias_at` runs in every residual of a fit)."""
        if self.alias_g is None:
            return np.zeros(len(self.q_grid), bool)
        return self.alias_g.any(axis=(0, 2))

    def alias_at(self, q: float) -> np.ndarray | None:
        """G_k(q)(f) of every alias cell, (n_cells, n_f), interpolated as :meth:`g_at`;
        None where no simulation near ``q`` holds content beyond the Nyquist."""
        if self.alias_g is None:
            return None
        j, t = self._weights(q)
        if not (self._alias_held[j] or self._alias_held[j + 1]):
            return None
        return (1 - t) * self.alias_g[:, j] + t * self.alias_g[:, j + 1]


#: ``keep(fy, fx)`` → bool: the frequency bins (cycles/px) a transfer fit may use
BinFilter = Callable[[np.ndarray, np.ndarray], np.ndarray]


def used_bins(fy: np.ndarray, fx: np.ndarray, f_max: float = 0.5,
              keep: BinFilter | None = None) -> np.ndarray:
    """The bins of a block's FFT grid (``fy``, ``fx``: cycles/px) a transfer fit uses: one
    of each conjugate pair, DC excluded, radius ≤ ``f_max``, and where ``keep`` allows."""
    fr = np.hypot(fy, fx)
    half = ((fx > 0) | ((fx == 0) & (fy > 0))) & (fr <= f_max) & (fr > 0)
    return half if keep is None else half & keep(fy, fx)


def measured_transfer(s00: np.ndarray, srr: np.ndarray, sr0: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(transfer sr0 / s00, magnitude-squared coherence clipped to (0, 1)) from Welch sums:
    s00 the sharpest simulation's power, srr the real scene's, sr0 their cross-spectrum."""
    t = sr0 / np.maximum(s00, 1e-30)
    coh = np.clip(np.abs(sr0) ** 2 / np.maximum(s00 * srr, 1e-300), 1e-6, 1.0 - 1e-9)
    return t, coh


def transfer_variance(t: np.ndarray, coh: np.ndarray, n_blocks: int,
                      share: np.ndarray | None = None) -> np.ndarray:
    """Variance of the real and of the imaginary part of a measured transfer ``t`` with
    coherence ``coh`` over ``n_blocks`` Welch blocks (:func:`measured_transfer`): the real
    scene's power that the simulation does not explain linearly (1 − coherence), times
    ``share`` where given (the part of that power the alias cells do not explain either,
    :func:`alias_unexplained_share`), plus the floor of the model's approximations
    (:data:`TRANSFER_FLOOR`)."""
    incoherent = (1.0 - coh) / (2.0 * n_blocks * coh) * np.abs(t) ** 2
    if share is not None:
        incoherent = incoherent * share
    return incoherent + TRANSFER_FLOOR**2


def alias_unexplained_share(sharpest: np.ndarray, cells: dict[tuple[int, int], np.ndarray],
                            real_grey: np.ndarray, origins: list[tuple[int, int]],
                            block_px: int) -> np.ndarray | None:
    """Per bin of the block FFT grid (block_px, block_px): the share of the real scene's
    power that the sharpest simulation does not explain which its alias-cell parts do
    not explain either (≤ 1).

    Below Q 2 the optics pass content beyond the Nyquist, and how sampling folds it
    depends on the blur acting before sampling: a scene with a detector box at Q 1.15
    keeps a different mix of each alias cell than the sharpest simulation. That part of
    the scene is not a linear function of the sharpest simulation, so the coherence
    against it counts it as noise — yet the fits model it exactly (:func:`model_transfer`
    with the cells). Counted as noise it inflated the transfer's variance ~5× and hid the
    box (development c1214: ΔBIC 7 against the tool's own pixel residual 0.29 → 0.083 DN²).
    Here the real scene's blocks are regressed per bin on the sharpest simulation and its
    eight cell parts (:func:`~geosim.diagnose.spectra.unexplained_power`); the ratio of the
    residual variances (each over its degrees of freedom, pooled over 3 × 3 neighbouring
    bins) is what remains noise.

    Parameters
    ----------
    sharpest, cells
        The sharpest grid simulation (grey, rows × cols) and its part in each alias cell
        (complex; :func:`geosim.diagnose.alias_cells.alias_pieces`), as the fits see them.
    real_grey
        The real scene as the fits see it.
    origins, block_px
        The Welch blocks (all of the fit's; at most :data:`SHARE_MAX_BLOCKS` are used).

    Returns
    -------
    np.ndarray or None
        None with fewer than :data:`SHARE_MIN_BLOCKS` blocks (too few for 9 coefficients).
    """
    n = len(origins)
    if n < SHARE_MIN_BLOCKS:
        return None
    step = -(-n // SHARE_MAX_BLOCKS)  # ceil: at most SHARE_MAX_BLOCKS, evenly spaced
    used = list(origins)[::step]
    n = len(used)
    w = hann2d(block_px)
    f0 = block_ffts(sharpest, used, block_px, w)
    fr = block_ffts(real_grey, used, block_px, w)
    rss_1, _ = unexplained_power([f0], fr)
    rss_m, n_held = unexplained_power(
        [f0, *(block_ffts(cells[c], used, block_px, w) for c in ALIAS_CELLS)], fr)
    noise_m = ndimage.uniform_filter(rss_m / np.maximum(n - n_held, 1), 3, mode="wrap")
    noise_1 = ndimage.uniform_filter(rss_1 / (n - 1), 3, mode="wrap")
    return np.clip(noise_m / np.maximum(noise_1, 1e-300), 0.0, 1.0)


def build_spectral_data(sims_grey: Sequence[np.ndarray], q_grid: Sequence[float],
                        real_grey: np.ndarray, *, origins: list[tuple[int, int]],
                        block_px: int, f_max: float = 0.5,
                        keep: BinFilter | None = None,
                        pieces: AliasPieces | None = None,
                        share: np.ndarray | None = None) -> SpectralData:
    """Welch spectra of the real scene and the Q-grid simulations against the sharpest.

    Parameters
    ----------
    sims_grey
        Grey-level paper-model simulations at ``q_grid`` (same order), co-registered
        with ``real_grey``.
    origins
        Welch block origins (e.g. one half of the scene for held-out validation).
    f_max
        Largest radial frequency used, cycles per pixel.
    keep
        ``keep(fy, fx)``: which bins the fit may use (under JPEG, those where the JPEG's
        linearised transfer was measured); None: all.
    pieces
        Per member of ``q_grid``, the simulation's parts folded from each alias cell
        (:func:`geosim.diagnose.alias_cells.alias_pieces`; None entries: none); their
        transfers let a blur act before sampling (:func:`model_transfer`).
    share
        Per bin of the block grid, the share of the incoherent power that is noise
        (:func:`alias_unexplained_share`, made on all the scene's blocks; the transfer's
        variance is scaled by it); None: all of it.
    """
    w = hann2d(block_px)
    n = len(origins)

    def ffts(img: np.ndarray) -> np.ndarray:
        return block_ffts(img, origins, block_px, w)

    f0 = ffts(sims_grey[0])
    fr_ = ffts(real_grey)
    s00 = np.sum(np.abs(f0) ** 2, axis=0)
    srr = np.sum(np.abs(fr_) ** 2, axis=0)
    sr0 = np.sum(fr_ * np.conj(f0), axis=0)
    g = [np.sum(ffts(s) * np.conj(f0), axis=0) / np.maximum(s00, 1e-30) for s in sims_grey]
    fy = np.fft.fftfreq(block_px)[:, None] * np.ones((1, block_px))
    fx = np.fft.fftfreq(block_px)[None, :] * np.ones((block_px, 1))
    half = used_bins(fy, fx, f_max, keep)
    t, coh = measured_transfer(s00, srr, sr0)
    var = transfer_variance(t, coh, n, share)
    alias_g = None
    if pieces is not None and any(p is not None for p in pieces):
        s00_safe = np.maximum(s00, 1e-30)
        alias_g = np.zeros((len(ALIAS_CELLS), len(pieces), int(half.sum())), dtype=complex)
        for j, piece in enumerate(pieces):
            if piece is None:
                continue
            for i, c in enumerate(ALIAS_CELLS):
                alias_g[i, j] = (np.sum(ffts(piece[c]) * np.conj(f0), axis=0) / s00_safe)[half]
    return SpectralData(fy=fy[half], fx=fx[half], t_real=t[half],
                        g_q=np.array([gi[half] for gi in g]), q_grid=np.asarray(q_grid, float),
                        var=var[half], n_blocks=n, coherence=coh[half], alias_g=alias_g)


def _blur(name: str) -> BlurEffect:
    e = get_effect(name)
    if not isinstance(e, BlurEffect):
        raise ValueError(f"{name} is not a blur effect")
    return e


def model_transfer(data: SpectralData, *, q: float, gain: float,
                   effects: dict[str, dict[str, float]]) -> np.ndarray:
    """g · ∏ H_e(f) · G(q)(f) on the samples of ``data``; where the simulations hold
    content beyond the Nyquist (``data.alias_g``), the blur acts before sampling:
    g · [G(q)(f) H(f) + Σ_k G_k(q)(f) (H(f + k) − H(f))] (:mod:`geosim.diagnose.alias_cells`)."""
    # the blurs that act on the ground, and what acts on the sampled image (resampling)
    ground = {n: p for n, p in effects.items() if n not in NON_LSI}
    later = {n: p for n, p in effects.items() if n in NON_LSI}
    h_ground = _effects_transfer(data, ground)
    t = data.g_at(q) * h_ground
    # under a resampling the scene was sampled on the native grid, whose alias cells are
    # not the product's: no cell correction (the delivered render samples it natively)
    gk = data.alias_at(q) if ground and not later else None
    if gk is not None:
        for i, (ky, kx) in enumerate(ALIAS_CELLS):
            t = t + gk[i] * (_effects_transfer(data, ground, (ky, kx)) - h_ground)
    return gain * t * _effects_transfer(data, later)


def blur_transfer(effects: dict[str, dict[str, float]], fy: np.ndarray, fx: np.ndarray
                  ) -> np.ndarray | float:
    """∏ H_e(fy, fx) of the blur ``effects`` (cycles/px; 1.0 for none); ValueError for an
    effect that is not a blur."""
    h: np.ndarray | float = 1.0
    for name, p in effects.items():
        h = h * _blur(name).transfer(fy, fx, **p)
    return h


def _effects_transfer(data: SpectralData, effects: dict[str, dict[str, float]],
                      cell: tuple[int, int] = (0, 0)) -> np.ndarray | float:
    """∏ H_e(f + k) of ``effects`` on the samples of ``data`` (1.0 for none); ``cell``:
    k, whole cycles per pixel (an alias cell)."""
    return blur_transfer(effects, data.fy + cell[0], data.fx + cell[1])


@dataclass
class TransferFit:
    """A fitted blur model.

    Attributes
    ----------
    effects
        {effect name: {param: value}} (directions wrapped to [0, 180)).
    sigmas
        1-σ uncertainties with the same structure, plus ``"q"`` and ``"gain"`` at top level.
    q, gain
        Fitted Q and overall (grey-level) gain.
    chi2
        Weighted residual sum of squares (in units of the estimated variances).
    n_params
        Number of fitted parameters.
    """

    effects: dict[str, dict[str, float]]
    sigmas: dict[str, dict[str, float] | float]
    q: float
    gain: float
    chi2: float
    n_params: int
    n_eff: float

    def bic(self, scale: float = 1.0) -> float:
        """BIC = χ²/(scale · Hann spread) + k ln n_eff."""
        return self.chi2 / (scale * HANN_CORRELATION) + self.n_params * np.log(self.n_eff)


def _pack_specs(names: Sequence[str]) -> list[tuple[str, str, float, float, tuple, float | None]]:
    specs = []
    for name in names:
        for p in _blur(name).params:
            specs.append((name, p.name, p.lower, p.upper, p.initial, p.periodic))
    return specs


def _unpack(x: np.ndarray, specs) -> tuple[float, float, dict[str, dict[str, float]]]:
    q, gain = float(np.exp(x[0])), float(x[1])
    eff: dict[str, dict[str, float]] = {}
    for (name, pname, *_), v in zip(specs, x[2:], strict=True):
        eff.setdefault(name, {})[pname] = float(v)
    return q, gain, eff


def _residual(x, data: SpectralData, specs, wt: np.ndarray,
              fixed: np.ndarray | float | None = None,
              fixed_effects: dict[str, dict[str, float]] | None = None) -> np.ndarray:
    q, gain, eff = _unpack(x, specs)
    h = model_transfer(data, q=q, gain=gain, effects={**eff, **(fixed_effects or {})})
    if fixed is not None:
        h = h * fixed
    d = (data.t_real - h) * wt
    return np.concatenate([d.real, d.imag])


def evaluate_chi2(data: SpectralData, *, q: float, gain: float,
                  effects: dict[str, dict[str, float]]) -> float:
    """χ² of a given model on (held-out) data."""
    d = (data.t_real - model_transfer(data, q=q, gain=gain, effects=effects)) / np.sqrt(data.var)
    return float(np.sum(np.abs(d) ** 2))


def fit_transfer(data: SpectralData, effect_names: Sequence[str], *,
                 q_starts: Sequence[float] = (1.5,), fix_q: float | None = None,
                 max_starts: int = 24, start: TransferFit | None = None,
                 fixed: dict[str, dict[str, float]] | None = None) -> TransferFit:
    """Least-squares fit of g, Q and the parameters of ``effect_names`` to ``data``.

    Multi-start over the catalogue's initial values (all directions) and ``q_starts``;
    the best χ² wins. Uncertainties from the Jacobian, scaled by max(1, χ²/dof) and the
    Hann-window correlation of neighbouring frequency bins.

    Parameters
    ----------
    fix_q
        Keep Q fixed at this value (e.g. the LV-calibrated baseline).
    start
        A fit of the same effects (e.g. on all blocks) to start from, alone: a single
        start, for the many refits of block cross-validation.
    fixed
        Effects in the model with their parameters held (e.g. measured on the power
        spectrum, which the transfer cannot see): they multiply the transfer, are not
        fitted, and appear in the result's ``effects`` (not in ``sigmas`` nor
        ``n_params``).
    """
    fixed = {n: dict(p) for n, p in (fixed or {}).items() if n not in effect_names}
    # held effects multiply the transfer once (fast), unless they act on aliased content
    aliased = fixed and data.alias_g is not None
    h_fixed = _effects_transfer(data, fixed) if fixed and not aliased else None
    fixed_effects = fixed if aliased else None
    specs = _pack_specs(effect_names)
    qlo, qhi = float(data.q_grid[0]), float(data.q_grid[-1])
    lb = [np.log(qlo), 0.05] + [s[2] for s in specs]
    ub = [np.log(qhi), 5.0] + [s[3] for s in specs]
    if fix_q is not None:
        lq = np.log(np.clip(fix_q, qlo, qhi))
        lb[0], ub[0] = lq - 1e-9, lq + 1e-9
        q_starts = (float(np.exp(lq)),)
    wt = 1.0 / np.sqrt(data.var)
    gain0 = float(np.real(np.mean(data.t_real[:4]))) or 1.0
    grids = [s[4] for s in specs]
    starts = list(itertools.product(q_starts, *grids))[:max_starts]
    if start is not None and all(n in start.effects for n in effect_names):
        starts = [(start.q, *[start.effects[s[0]][s[1]] for s in specs])]
        gain0 = start.gain
    best = None
    for st in starts:
        x0 = np.array([np.log(np.clip(st[0], qlo * 1.0001, qhi * 0.9999)),
                       np.clip(gain0, 0.06, 4.9)] + list(st[1:]), dtype=float)
        x0 = np.clip(x0, np.array(lb) + 1e-9, np.array(ub) - 1e-9)
        try:
            res = least_squares(_residual, x0, bounds=(lb, ub),
                                args=(data, specs, wt, h_fixed, fixed_effects),
                                method="trf", x_scale="jac", max_nfev=200)
        except ValueError:
            continue
        if best is None or res.cost < best.cost:
            best = res
    if best is None:
        raise RuntimeError("transfer fit failed from every start")
    chi2 = float(2 * best.cost)
    k = len(best.x) - (1 if fix_q is not None else 0)
    dof = max(2 * data.t_real.size - k, 1)
    scale = max(1.0, chi2 / dof) * HANN_CORRELATION
    jac = best.jac
    if fix_q is not None:
        jac = jac.copy()
        jac[:, 0] = 0.0
    try:
        cov = np.linalg.pinv(jac.T @ jac) * scale
        sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        sig = np.full(len(best.x), np.inf)
    q, gain, eff = _unpack(best.x, specs)
    sigmas: dict[str, dict[str, float] | float] = {"q": float(q * sig[0]), "gain": float(sig[1])}
    for (name, pname, _, _, _, periodic), s in zip(specs, sig[2:], strict=True):
        sigmas.setdefault(name, {})[pname] = float(s)  # type: ignore[union-attr]
        if periodic:
            eff[name][pname] = float(np.mod(eff[name][pname], periodic))
    return TransferFit(effects={**eff, **fixed}, sigmas=sigmas, q=q, gain=gain, chi2=chi2,
                       n_params=k, n_eff=data.n_eff)


# ----------------------------------------------------------------------------- radiometry
@dataclass
class RadiometryFit:
    """Per-band R ≈ gain · model + offset_dn (least squares) with 1-σ errors."""

    gain: np.ndarray
    offset_dn: np.ndarray
    gain_sigma: np.ndarray
    offset_sigma: np.ndarray
    rss_affine: np.ndarray
    rss_gain_only: np.ndarray
    gain_only: np.ndarray
    rss_identity: np.ndarray
    n: int
    model_mean: np.ndarray | None = None      # E[m] per band, DN
    model_meansq: np.ndarray | None = None    # E[m²] per band, DN²

    def correction_rms(self, gain: np.ndarray, offset_dn: np.ndarray) -> np.ndarray:
        """RMS over pixels of the change (gain − 1)·m + offset a correction makes, per band (DN)."""
        g1 = np.asarray(gain) - 1.0
        o = np.asarray(offset_dn)
        return np.sqrt(np.maximum(g1**2 * self.model_meansq + 2 * g1 * o * self.model_mean
                                  + o**2, 0.0))


def _tukey_weights(r: np.ndarray, scale: float, c: float = 4.685) -> np.ndarray:
    u = r / (c * scale)
    return np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)


def _robust_affine(x: np.ndarray, y: np.ndarray, iterations: int = 10, n_pairs: int = 400
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Robust fit of y ≈ g x + o: RANSAC over random point pairs, then Tukey IRLS.

    The consensus line (most points within a tolerance) is found first, so that large
    clusters of changed pixels (shadows present in one image only) cannot pull the slope;
    the biweight refinement then uses the inliers' robust scale, held fixed. Deterministic
    (fixed seed).
    """
    rng = np.random.default_rng(12345)
    a = np.column_stack([x, np.ones_like(x)])
    base_r = y - x - np.median(y - x)
    tol = max(2.0, 0.5 * 1.4826 * float(np.median(np.abs(base_r))))
    best = (np.array([1.0, float(np.median(y - x))]), -1)
    if x.size >= 2:
        i = rng.integers(0, x.size, n_pairs)
        j = rng.integers(0, x.size, n_pairs)
        dx = x[j] - x[i]
        ok = np.abs(dx) > max(1.0, 0.25 * float(np.std(x)))
        sample = rng.choice(x.size, min(x.size, 4000), replace=False)
        for ii, jj in zip(i[ok], j[ok], strict=True):
            g = (y[jj] - y[ii]) / (x[jj] - x[ii])
            if not 0.05 < g < 5.0:
                continue
            o = y[ii] - g * x[ii]
            score = int(np.sum(np.abs(y[sample] - g * x[sample] - o) < tol))
            if score > best[1]:
                best = (np.array([g, o]), score)
    sol = best[0]
    r = y - a @ sol
    inl = np.abs(r) < tol
    scale = 1.4826 * float(np.median(np.abs(r[inl] - np.median(r[inl])))) + 1e-6 \
        if inl.sum() > 10 else tol
    w = _tukey_weights(r, scale)
    for _ in range(iterations):
        sw = np.sqrt(w)
        sol, *_ = np.linalg.lstsq(a * sw[:, None], y * sw, rcond=None)
        w = _tukey_weights(y - a @ sol, scale)
    return sol, w


def _robust_location(r: np.ndarray, iterations: int = 10) -> tuple[float, np.ndarray]:
    loc = float(np.median(r))
    scale = 1.4826 * float(np.median(np.abs(r - loc))) + 1e-6
    w = _tukey_weights(r - loc, scale)
    for _ in range(iterations):
        loc = float(np.sum(w * r) / max(np.sum(w), 1e-30))
        w = _tukey_weights(r - loc, scale)
    return loc, w


def fit_radiometry(model: np.ndarray, real: np.ndarray, mask: np.ndarray, *,
                   corr_px2: float = 4.0, gains: np.ndarray | None = None,
                   gain_sigmas: np.ndarray | None = None) -> RadiometryFit:
    """Per-band robust regressions of the real scene on the (blurred) model.

    RANSAC over point pairs then Tukey-biweight IRLS (:func:`_robust_affine`), so that pixels
    whose content changed (other shadows, moved cattle) — outliers of the radiometric
    relation — do not drag the gain toward zero. With ``gains`` given (fixed per-band
    gains), only the offsets are fitted (robust location of y − g·x). The residual sums of
    squares of the identity, gain-only and affine models are all weighted by the affine
    fit's final weights (same inliers). ``corr_px2`` is the area (px²) over which residuals
    are correlated; uncertainties use (Σw)/corr_px2 independent samples.
    """
    bands = model.shape[0]
    g = np.zeros(bands)
    o = np.zeros(bands)
    gs = np.zeros(bands)
    os_ = np.zeros(bands)
    rss_a = np.zeros(bands)
    rss_g = np.zeros(bands)
    g_only = np.zeros(bands)
    rss_i = np.zeros(bands)
    n = int(mask.sum())
    for b in range(bands):
        x = model[b][mask]
        y = real[b][mask]
        a = np.column_stack([x, np.ones_like(x)])
        if gains is not None:
            # gain from contrast (cross-spectrum), offset = robust mean of y − g x
            off, w = _robust_location(y - gains[b] * x)
            sol = np.array([gains[b], off])
        else:
            sol, w = _robust_affine(x, y)
        r = y - a @ sol
        rss_a[b] = float(np.sum(w * r * r))
        n_w = max(float(w.sum()), 3.0)
        s2 = rss_a[b] / max(n_w - 2, 1)
        aw = a * np.sqrt(w)[:, None]
        cov = np.linalg.inv(aw.T @ aw) * s2 * corr_px2
        g[b], o[b] = sol
        gs[b], os_[b] = np.sqrt(np.diag(cov))
        if gains is not None and gain_sigmas is not None:
            gs[b] = float(np.hypot(gs[b], gain_sigmas[b]))
            os_[b] = float(np.hypot(os_[b], gain_sigmas[b] * np.sum(w * x) / n_w))
        g_only[b] = float(np.sum(w * x * y) / max(np.sum(w * x * x), 1e-30))
        rg = y - g_only[b] * x
        rss_g[b] = float(np.sum(w * rg * rg))
        ri = y - x
        rss_i[b] = float(np.sum(w * ri * ri))
        n = min(n, int(round(n_w)))
    mm = np.array([model[b][mask].mean() for b in range(bands)])
    msq = np.array([np.mean(model[b][mask] ** 2) for b in range(bands)])
    return RadiometryFit(gain=g, offset_dn=o, gain_sigma=gs, offset_sigma=os_, rss_affine=rss_a,
                         rss_gain_only=rss_g, gain_only=g_only, rss_identity=rss_i, n=n,
                         model_mean=mm, model_meansq=msq)


# ----------------------------------------------------------------------------- noise
@dataclass
class NoiseFit:
    """Noise variance model var = gain_dn · s + read_var_dn2 (DN², s in DN)."""

    gain_dn: float
    read_var_dn2: float
    gain_sigma: float
    read_sigma: float
    brightness_dn: np.ndarray       # bin centres
    variance_dn2: np.ndarray        # robust variance per bin
    mean_variance_dn2: float        # variance at the mean brightness
    quantization_dn2: float
    mean_variance_sigma: float = float("inf")   # 1-σ of mean_variance_dn2


def fit_noise(residual: np.ndarray, brightness: np.ndarray, mask: np.ndarray, *,
              block_px: int = 8, n_bins: int = 12, quantized: bool = False) -> NoiseFit:
    """Fit var = a·s + b to block variances of ``residual`` against block brightness.

    Parameters
    ----------
    residual, brightness
        Bands-first residual (real − deterministic model) and model brightness, DN.
    mask
        Pixels to use (valid, outside scene-change regions).
    quantized
        The real scene holds whole DN: its rounding adds 1/12 DN², which is subtracted
        from ``read_var_dn2``.

    Notes
    -----
    The median of block variances in each brightness bin (divided by the median of a
    χ² with block_px² − 1 dof over its mean) resists blocks where the deterministic model
    still misfits texture.
    """
    v_all, s_all = [], []
    rows, cols = residual.shape[-2:]
    for b in range(residual.shape[0]):
        for r0 in range(0, rows - block_px + 1, block_px):
            for c0 in range(0, cols - block_px + 1, block_px):
                m = mask[r0:r0 + block_px, c0:c0 + block_px]
                if not m.all():
                    continue
                e = residual[b, r0:r0 + block_px, c0:c0 + block_px]
                v_all.append(e.var(ddof=1))
                s_all.append(brightness[b, r0:r0 + block_px, c0:c0 + block_px].mean())
    v = np.asarray(v_all)
    s = np.asarray(s_all)
    qv = 1.0 / 12.0 if quantized else 0.0
    if v.size < 8:
        return NoiseFit(0.0, 0.0, np.inf, np.inf, np.zeros(0), np.zeros(0), 0.0, qv)
    dof = block_px * block_px - 1
    med_factor = (1 - 2 / (9 * dof)) ** 3  # Wilson–Hilferty median of χ²/dof
    edges = np.unique(np.quantile(s, np.linspace(0, 1, n_bins + 1)))
    centres, meds, errs = [], [], []
    for lo, hi in itertools.pairwise(edges):
        sel = (s >= lo) & (s <= hi)
        if sel.sum() < 4:
            continue
        centres.append(float(np.mean(s[sel])))
        med = float(np.median(v[sel])) / med_factor
        meds.append(med)
        errs.append(med * np.sqrt(2.0 / dof) * 1.25 / np.sqrt(sel.sum()) + 1e-6)
    c = np.asarray(centres)
    m = np.asarray(meds)
    e = np.asarray(errs)
    a = np.column_stack([c, np.ones_like(c)]) / e[:, None]
    sol, *_ = np.linalg.lstsq(a, m / e, rcond=None)
    cov = np.linalg.pinv(a.T @ a)
    chi2 = float(np.sum((m / e - a @ sol) ** 2))
    cov *= max(1.0, chi2 / max(len(c) - 2, 1))
    gain_dn, read = float(sol[0]), float(sol[1])
    if gain_dn < 0:  # no shot noise term supported: constant variance
        gain_dn = 0.0
        read = float(np.average(m, weights=1 / e**2))
    read_q = max(read - qv, 0.0)
    s_mean = float(np.mean(s))
    mean_var = max(gain_dn * s_mean + read - qv, 0.0)
    jvec = np.array([s_mean, 1.0])
    mean_sig = float(np.sqrt(max(jvec @ cov @ jvec, 0.0)))
    return NoiseFit(gain_dn=gain_dn, read_var_dn2=read_q, gain_sigma=float(np.sqrt(cov[0, 0])),
                    read_sigma=float(np.sqrt(cov[1, 1])), brightness_dn=c, variance_dn2=m,
                    mean_variance_dn2=mean_var, quantization_dn2=qv,
                    mean_variance_sigma=mean_sig)
