"""A resampling's native pitch, Q and native-grid phase refined together on the power
spectrum.

Below Q ≈ 2 the optics pass content above the native Nyquist 1/(2p), and the native
sampling folds it into peaks whose place is set by the pitch p and whose height by Q. The
delivered power spectrum then pins both sharply (development c629, Q 0.98 from 1.33 px:
the spectral error 0.005 at the truth, 0.03 at Q 7 % off or 0.1 at a pitch 0.1 px off),
far more sharply than the coherent transfer, which the aliased power makes incoherent
(the transfer's Q for the true pitch was 1.04; the 0.05 px pitch scan at that Q missed the
minimum). On one scene the aliases also interfere with the pass band according to where
the native grid lies (its phase): development c09 (Q 1.01, 1.63 px), spectral error 0.146
at phase 0 and 0.046 near the true phase.

:func:`refine_resampling` searches (p, ln Q) by a bounded Nelder–Mead, then the phase on a
grid of a quarter native cell, then all four together. Pure: the caller renders and scores.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

__all__ = ["RefinedResampling", "refine_resampling", "minimise_bounded",
           "REFINE_PITCH_TOL_PX", "REFINE_MAX_EVALS", "PHASE_STEPS"]

#: stop when the simplex spans less than this (pitch and phase in px, ln Q)
REFINE_PITCH_TOL_PX = 0.004
#: at most this many renders per Nelder–Mead search (≈ 25 ms each on a 128 px scene)
REFINE_MAX_EVALS = 60
#: the phase grid: this many steps of a native cell per axis
PHASE_STEPS = 4
#: the first simplex's steps: pitch (px), ln Q, phase (px)
_STEP_PITCH, _STEP_LNQ, _STEP_PHASE = 0.04, 0.06, 0.15

#: ``se_at(pitch_px, q, (phase_row_px, phase_col_px))`` → spectral error
SpectralScore = Callable[[float, float, tuple[float, float]], float]


@dataclass(frozen=True)
class RefinedResampling:
    """The outcome of :func:`refine_resampling`.

    Attributes
    ----------
    native_pitch_px
        Native pitch, product pixels.
    q
        Optical Q (dimensionless).
    phase_px
        (row, col) position of a native pixel edge, product pixels (modulo the pitch).
    spectral_error
        The score there (as ``se_at`` returns it).
    n_evals
        Renders the search made.
    """

    native_pitch_px: float
    q: float
    phase_px: tuple[float, float]
    spectral_error: float
    n_evals: int


def minimise_bounded(f: Callable[[np.ndarray], float], x0: np.ndarray, lo: np.ndarray,
                     hi: np.ndarray, step: np.ndarray, *, xatol: float = REFINE_PITCH_TOL_PX,
                     max_evals: int = REFINE_MAX_EVALS) -> tuple[np.ndarray, float]:
    """Nelder–Mead of ``f`` in the box [lo, hi] from ``x0`` (clipped into it), the first
    simplex ``step`` along each axis (inwards where the start sits near a bound). The
    spectral error is not smooth enough for gradients (block spectra of rendered images),
    and a few parameters need few renders. Never returns a point scoring worse than the
    start.

    Returns
    -------
    x, f(x)
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    x0 = np.clip(np.asarray(x0, float), lo, hi)
    step = np.asarray(step, float)
    steps = np.where(x0 + step <= hi, step, -step)
    simplex = np.vstack([x0, x0 + np.diag(steps)])
    f0 = f(x0)
    res = minimize(lambda x: f(np.clip(x, lo, hi)), x0, method="Nelder-Mead",
                   bounds=list(zip(lo, hi, strict=True)),
                   options={"initial_simplex": simplex, "xatol": xatol, "fatol": 1e-4,
                            "maxfev": max_evals})
    x = np.clip(res.x, lo, hi)
    fx = f(x)
    return (x, fx) if fx <= f0 else (x0, f0)


def refine_resampling(se_at: SpectralScore, pitch_px: float, q: float,
                      phase_px: tuple[float, float], *, pitch_bounds: tuple[float, float],
                      q_bounds: tuple[float, float], fit_phase: bool = True
                      ) -> RefinedResampling:
    """Minimise ``se_at`` over pitch (within ``pitch_bounds``), Q (within ``q_bounds``) and,
    with ``fit_phase``, the native grid's phase, from the start given.

    1. (pitch, ln Q) at the start's phase (:func:`minimise_bounded`);
    2. the phase on a grid of :data:`PHASE_STEPS` × :data:`PHASE_STEPS` positions of a
       native cell at that pitch and Q (the phase is periodic and the error has one
       minimum per cell; a local search from an arbitrary phase can stall);
    3. pitch, ln Q and phase together from the best.
    """
    seen: dict[tuple[float, ...], float] = {}

    def score(p: float, lq: float, ph: tuple[float, float]) -> float:
        key = (round(p, 6), round(lq, 6), round(ph[0] % p, 5), round(ph[1] % p, 5))
        if key not in seen:
            seen[key] = float(se_at(p, float(np.exp(lq)), (ph[0] % p, ph[1] % p)))
        return seen[key]

    lo = np.array([pitch_bounds[0], np.log(q_bounds[0])])
    hi = np.array([pitch_bounds[1], np.log(q_bounds[1])])
    ph = (float(phase_px[0]), float(phase_px[1]))
    x, fx = minimise_bounded(lambda v: score(v[0], v[1], ph), np.array([pitch_px, np.log(q)]),
                             lo, hi, np.array([_STEP_PITCH, _STEP_LNQ]))
    if fit_phase:
        p = float(x[0])
        grid = [(ph[0] + i * p / PHASE_STEPS, ph[1] + j * p / PHASE_STEPS)
                for i in range(PHASE_STEPS) for j in range(PHASE_STEPS)]
        ph = min(grid, key=lambda g: score(p, float(x[1]), g))
        wide = 4.0 * float(pitch_bounds[1])     # the phase is periodic: no real bound
        x4, fx = minimise_bounded(lambda v: score(v[0], v[1], (v[2], v[3])),
                                  np.array([x[0], x[1], ph[0], ph[1]]),
                                  np.array([*lo, -wide, -wide]), np.array([*hi, wide, wide]),
                                  np.array([_STEP_PITCH, _STEP_LNQ, _STEP_PHASE, _STEP_PHASE]),
                                  max_evals=2 * REFINE_MAX_EVALS)
        x, ph = x4[:2], (float(x4[2]), float(x4[3]))
    p = float(x[0])
    return RefinedResampling(native_pitch_px=p, q=float(np.exp(x[1])),
                             phase_px=(ph[0] % p, ph[1] % p), spectral_error=float(fx),
                             n_evals=len(seen))
