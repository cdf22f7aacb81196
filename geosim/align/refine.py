"""One iterative refinement of a transform from shifts measured in a grid of windows.

Used by :func:`geosim.align.register_similarity` (flight → reference flight) and by
:func:`geosim.prepare.anchor.register_to_satellite` (reference flight → satellite): the
moving image is warped with the current estimate, sub-pixel shifts are measured by phase
correlation in windows (:func:`geosim.align.local.shifts_in_windows`), a robust
(Huber-weighted) translation or similarity is fitted to them and composed into the
estimate, until the update moves no image corner by more than
:data:`REFINE_TOLERANCE_PX`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from geosim.align.local import shifts_in_windows

__all__ = ["REFINE_TOLERANCE_PX", "Refinement", "fit_similarity", "fit_translation",
           "refine_with_windows",
           "similarity_significance"]

#: The refinement stops when its update moves no image corner by more than this (px).
REFINE_TOLERANCE_PX = 0.01

#: Support assigned when fewer than three windows are confident.
UNCONFIRMED_SUPPORT = 0.5

Warp = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Refinement:
    """Result of :func:`refine_with_windows`.

    Attributes
    ----------
    matrix : numpy.ndarray
        ``(3, 3)`` refined reference-pixel → moving-pixel matrix.
    model : str
        ``"similarity"`` or ``"translation"`` (what the last update fitted).
    rms_px : float
        Robust RMS of the window shifts about the last fit, px (NaN: no windows).
    n_windows : int
        Confident windows of the last fit (0: none were usable).
    support : float
        Confidence-weighted fraction of them agreeing with the fit within the tolerance
        (:data:`UNCONFIRMED_SUPPORT` without windows).
    significance, effect_px : float
        For ``model="auto"``: the first similarity fit's rotation/scale part in standard
        errors and its displacement at the farthest window (NaN otherwise).
    """

    matrix: np.ndarray
    model: str
    rms_px: float
    n_windows: int
    support: float
    significance: float = float("nan")
    effect_px: float = float("nan")


def fit_translation(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, *,
                    huber_px: float = 0.5, iterations: int = 5
                    ) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust (Huber) weighted mean translation ``dst - src``; same returns as
    :func:`geosim.align.fit_similarity` (3×3 matrix, RMS px, residuals px)."""
    d = np.asarray(dst, dtype=float) - np.asarray(src, dtype=float)
    w0 = np.asarray(weights, dtype=float)
    w = w0.copy()
    t = np.zeros(2)
    for _ in range(max(1, iterations)):
        t = np.average(d, axis=0, weights=w)
        res = np.hypot(*(d - t).T)
        k = max(huber_px, 2.0 * float(np.median(res)))
        w = w0 * np.where(res <= k, 1.0, k / np.maximum(res, 1e-12))
    rms = float(np.sqrt(np.sum(w * res ** 2) / max(np.sum(w), 1e-12)))
    return np.array([[1.0, 0.0, t[0]], [0.0, 1.0, t[1]], [0.0, 0.0, 1.0]]), rms, res


def similarity_significance(m: np.ndarray, src: np.ndarray, rms_px: float,
                            ) -> tuple[float, float]:
    """How much a fitted similarity's rotation/scale part matters and how sure it is.

    Returns
    -------
    (effect_px, sigmas)
        ``effect_px``: displacement (px) the rotation/scale part causes at the
        farthest point ``src`` from its centroid; ``sigmas``: its size
        ``hypot(a - 1, b)`` in standard errors, from the residual RMS and the
        points' lever arm (``var = rms² / (2 Σ |p − p̄|²)``, per component).
    """
    a = 0.5 * (m[0, 0] + m[1, 1])
    b = 0.5 * (m[0, 1] - m[1, 0])
    dev = math.hypot(a - 1.0, b)
    p = np.asarray(src, dtype=float)
    p = p - p.mean(axis=0)
    r2 = np.sum(p * p, axis=1)
    lever = float(np.sqrt(r2.max())) if len(r2) else 0.0
    sigma = rms_px / math.sqrt(max(2.0 * float(r2.sum()), 1e-12))
    return dev * lever, dev / max(sigma, 1e-12)


def refine_with_windows(reference: np.ndarray, valid_reference: np.ndarray, warp: Warp,
                        m: np.ndarray, *, starts_r: np.ndarray, starts_c: np.ndarray,
                        window_px: int, min_confidence: float, upsample_factor: int,
                        min_valid_fraction: float, support_tolerance_px: float,
                        model: str = "similarity", joint_mask: bool = False,
                        min_windows_similarity: int = 3, significance: float = 5.0,
                        min_effect_px: float = 0.1, max_iterations: int = 5,
                        tolerance_px: float = REFINE_TOLERANCE_PX,
                        fallback: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
                        ) -> Refinement:
    """Iteratively refine ``m`` from window shifts between the reference and the warped moving.

    Parameters
    ----------
    reference, valid_reference : numpy.ndarray
        Grey reference (float32) and its mask.
    warp : callable
        ``warp(m_2x3_or_3x3) -> (warped, valid)``: the moving image resampled onto the
        reference grid with the reference → moving matrix.
    m : numpy.ndarray
        ``(3, 3)`` initial estimate.
    starts_r, starts_c, window_px
        Window layout (first rows / columns, side), pixels.
    min_confidence, upsample_factor, min_valid_fraction
        Window acceptance and sub-pixel settings (:func:`shifts_in_windows`).
    support_tolerance_px : float
        A window supports the fit when its residual is within this distance.
    model : {"similarity", "auto"}
        ``"similarity"``: always a similarity. ``"auto"``: a translation unless the first
        similarity fit's rotation/scale is significant (``> significance`` σ and moves the
        farthest window by more than ``min_effect_px``) and at least
        ``min_windows_similarity`` windows are confident.
    joint_mask : bool
        Measure windows with the joint mask (reference ∧ warped) on both images instead
        of each image's own mask.
    max_iterations, tolerance_px
        Stop after this many updates, or when an update moves no corner by more than
        ``tolerance_px``.
    fallback : callable, optional
        With fewer than three confident windows, ``fallback(warped, valid) -> (3, 3)``
        update (e.g. a whole-window translation) and iterate on; ``None``: stop.

    Returns
    -------
    Refinement
    """
    h, w = reference.shape
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float).T
    half = (window_px - 1) / 2.0
    yy, xx = np.meshgrid(starts_r + half, starts_c + half, indexing="ij")
    chosen = "similarity" if model == "similarity" else None
    rms, n_used, support = float("nan"), 0, UNCONFIRMED_SUPPORT
    signif = effect = float("nan")
    for _ in range(max(1, max_iterations)):
        warped, wv = warp(m)
        vr, vm = (valid_reference & wv, valid_reference & wv) if joint_mask else \
            (valid_reference, wv)
        dx, dy, conf = shifts_in_windows(reference, warped, vr, vm, starts_r, starts_c,
                                         window_px, upsample_factor=upsample_factor,
                                         min_valid_fraction=min_valid_fraction)
        ok = np.isfinite(dx) & (conf >= min_confidence)
        if ok.sum() < 3:
            rms, n_used, support = float("nan"), 0, UNCONFIRMED_SUPPORT
            if fallback is None:
                break
            update = fallback(warped, wv)
        else:
            src = np.column_stack([xx[ok], yy[ok]])
            dst = src + np.column_stack([dx[ok], dy[ok]])
            c = conf[ok]
            if chosen == "translation" or ok.sum() < min_windows_similarity:
                update, rms, res = fit_translation(src, dst, c)
                chosen = chosen or "translation"
            else:
                upd_s, rms_s, res_s = fit_similarity(src, dst, c)
                if chosen is None:
                    effect, signif = similarity_significance(upd_s, src, rms_s)
                    chosen = ("similarity" if signif > significance and effect > min_effect_px
                              else "translation")
                update, rms, res = ((upd_s, rms_s, res_s) if chosen == "similarity"
                                    else fit_translation(src, dst, c))
            n_used = int(ok.sum())
            support = float(np.sum(c * (res <= support_tolerance_px)) / np.sum(c))
        new = m @ update
        change = float(np.abs((new - m) @ corners)[:2].max())
        m = new
        if change < tolerance_px:
            break
    return Refinement(matrix=m, model=chosen or "translation", rms_px=rms, n_windows=n_used,
                      support=support, significance=signif, effect_px=effect)


def fit_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray, *,
                   huber_px: float = 0.5, iterations: int = 5
                   ) -> tuple[np.ndarray, float, np.ndarray]:
    """Robust weighted least-squares similarity mapping ``src`` points to ``dst``.

    Parameters
    ----------
    src, dst : numpy.ndarray
        ``(n, 2)`` point coordinates ``(x, y)`` in pixels, ``n >= 2``.
    weights : numpy.ndarray
        ``(n,)`` non-negative prior weights (e.g. confidences).
    huber_px : float
        Minimum Huber threshold in pixels (the threshold used is the larger of
        this and 2 × the median residual).
    iterations : int
        Reweighting iterations.

    Returns
    -------
    tuple
        ``(matrix, rms_px, residuals_px)``: ``(3, 3)`` homogeneous similarity
        ``[[a, b, tx], [-b, a, ty], [0, 0, 1]]`` (``a = s cos θ``, ``b = s sin θ``),
        the robustly weighted RMS residual in pixels and the ``(n,)`` residual
        distances in pixels.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    w0 = np.asarray(weights, dtype=float)
    centre = np.average(src, axis=0, weights=w0)
    p = src - centre
    n = len(p)
    a_mat = np.zeros((2 * n, 4))
    a_mat[0::2] = np.column_stack([p[:, 0], p[:, 1], np.ones(n), np.zeros(n)])
    a_mat[1::2] = np.column_stack([p[:, 1], -p[:, 0], np.zeros(n), np.ones(n)])
    rhs = dst.reshape(-1)
    w = w0.copy()
    for _ in range(max(1, iterations)):
        sw = np.sqrt(np.repeat(w, 2))
        params, *_ = np.linalg.lstsq(a_mat * sw[:, None], rhs * sw, rcond=None)
        res = np.hypot(*(a_mat @ params - rhs).reshape(-1, 2).T)
        k = max(huber_px, 2.0 * float(np.median(res)))
        w = w0 * np.where(res <= k, 1.0, k / np.maximum(res, 1e-12))
    a, b, tx, ty = params
    lin = np.array([[a, b], [-b, a]])
    t = np.array([tx, ty]) - lin @ centre
    rms = float(np.sqrt(np.sum(w * res ** 2) / max(np.sum(w), 1e-12)))
    return np.array([[a, b, t[0]], [-b, a, t[1]], [0.0, 0.0, 1.0]]), rms, res
