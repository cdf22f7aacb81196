"""Sub-pixel co-registration of the simulation to the real scene.

A shift between simulation and reality is a phase ramp in their cross-spectrum,
S_rs(f) ∝ exp(−2πi f·d); a blur only changes the magnitude (and, for sinc-type
blurs, flips the sign). We find the whole-pixel part by phase correlation and the
sub-pixel part by a weighted least-squares fit of a plane to the *doubled* phase
of the Welch cross-spectrum, arg(S_rs²) = −4π f·d, which is immune to the π
flips of negative sinc lobes (motion smear, detector integration). The fitted
shift is then reported as ``misregistration`` and removed before any blur is
estimated, so a shift is never mistaken for blur.

Sign convention: ``shift_px = (d_col, d_row)`` means real(x) ≈ sim(x − d), i.e.
the real scene is the simulation moved by +d_col columns (east) and +d_row rows
(south). In metres on a north-up grid: (east, north) = (d_col·gsd, −d_row·gsd).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geosim.align.phasecorr import phase_correlate
from geosim.diagnose.spectra import cross_spectrum
from geosim.errors import AlignmentError
from geosim.physics.geometry import fourier_shift

__all__ = ["ShiftEstimate", "estimate_shift", "fourier_shift", "integer_shift"]


@dataclass(frozen=True)
class ShiftEstimate:
    """Result of :func:`estimate_shift`.

    Attributes
    ----------
    shift_px
        (d_col, d_row) in pixels, real ≈ sim moved by this vector.
    sigma_px
        1-σ uncertainty of each component, pixels.
    delta_bic
        Evidence for a non-zero shift: BIC(no shift) − BIC(shift) of the doubled-phase fit.
    n_freq
        Number of frequency samples used in the fit.
    """

    shift_px: tuple[float, float]
    sigma_px: tuple[float, float]
    delta_bic: float
    n_freq: int

    def shift_m(self, gsd_m: float) -> tuple[float, float]:
        """(east, north) shift in metres on a north-up grid of pixel size ``gsd_m``."""
        return (self.shift_px[0] * gsd_m, -self.shift_px[1] * gsd_m)


def integer_shift(sim: np.ndarray, real: np.ndarray, *, valid: np.ndarray | None = None,
                  max_shift_px: int = 8) -> tuple[int, int]:
    """Whole-pixel (d_col, d_row) at the peak of the phase-correlation surface.

    The registration kernel :func:`geosim.align.phase_correlate` with the reference
    ``sim`` and the moving ``real`` (its shift is this module's ``d``), Hann window,
    classical phase correlation (``whitening=1``), integer peak within ``max_shift_px``.
    Full whitening matters here: the simulation and the real scene differ at low
    frequencies (haze, exposure seams, changed fields), and the kernel's default partial
    whitening lets that difference raise a smooth ramp on the surface that outweighs
    the true peak (see the ``whitening`` parameter of the kernel).

    Returns (0, 0) when the images cannot be correlated (smaller than 32 px, flat or
    almost wholly invalid); :func:`estimate_shift`'s phase fit then measures the shift.
    """
    try:
        pc = phase_correlate(sim, real, valid_reference=valid, valid_moving=valid,
                             window="hann", whitening=1.0, upsample_factor=1,
                             max_shift_px=max_shift_px)
    except AlignmentError:
        return 0, 0
    return int(round(pc.shift_px[0])), int(round(pc.shift_px[1]))


def _phase_fit(sim: np.ndarray, real: np.ndarray, valid: np.ndarray | None, block_px: int,
               f_max: float) -> tuple[np.ndarray, np.ndarray, float, int]:
    cs = cross_spectrum(sim, real, block_px=block_px, valid=valid)
    fy, fx = cs.fy, cs.fx
    fr = np.hypot(fy, fx)
    # half plane (fx > 0, or fx == 0 and fy > 0) to avoid counting conjugates twice
    half = (fx > 0) | ((fx == 0) & (fy > 0))
    use = half & (fr > 0) & (fr <= f_max)
    g2 = np.clip(cs.coherence[use], 1e-4, 0.999)
    doubled = np.angle(cs.s_rs[use] ** 2)
    # variance of the phase of H: (1 − γ²) / (2 n γ²); doubled phase has 4× that
    var = 4.0 * (1.0 - g2) / (2.0 * cs.n_blocks * g2) + (0.02) ** 2
    w = 1.0 / var
    a = np.column_stack([-4 * np.pi * fx[use], -4 * np.pi * fy[use]])
    aw = a * np.sqrt(w)[:, None]
    bw = doubled * np.sqrt(w)
    sol, *_ = np.linalg.lstsq(aw, bw, rcond=None)
    resid = bw - aw @ sol
    n = int(use.sum())
    chi2 = float(resid @ resid)
    chi2_0 = float(bw @ bw)
    s2 = chi2 / max(n - 2, 1)
    cov = np.linalg.pinv(aw.T @ aw) * max(s2, 1.0) * 2.25  # Hann bins are correlated
    dbic = n * np.log(chi2_0 / max(chi2, 1e-300)) - 2 * np.log(n)
    return sol, np.sqrt(np.diag(cov)), float(dbic), n


def estimate_shift(sim: np.ndarray, real: np.ndarray, *, valid: np.ndarray | None = None,
                   block_px: int = 32, f_max: float = 0.2, max_shift_px: int = 8
                   ) -> ShiftEstimate:
    """Sub-pixel shift of ``real`` relative to ``sim`` (grey-level 2-D images).

    Parameters
    ----------
    sim, real
        2-D images on the same 0.5 m grid.
    valid
        Bool mask of usable pixels (Welch blocks must be fully valid).
    block_px
        Welch block side, pixels.
    f_max
        Highest radial frequency used in the phase fit, cycles per pixel. With
        the doubled phase, shifts up to 1 / (4 f_max) px are unambiguous after the
        whole-pixel part is removed.
    max_shift_px
        Search radius of the whole-pixel phase correlation, pixels.

    Returns
    -------
    ShiftEstimate
    """
    s = np.asarray(sim, dtype=float)
    r = np.asarray(real, dtype=float)
    fill = valid if valid is not None else np.ones(s.shape, bool)
    s0 = np.where(fill, s, s[fill].mean())
    r0 = np.where(fill, r, r[fill].mean())
    dc, dr = integer_shift(s0, r0, valid=valid, max_shift_px=max_shift_px)
    moved = fourier_shift(s0, (dc, dr)) if (dc or dr) else s0
    sol, sig, dbic, n = _phase_fit(moved, r0, valid, block_px, f_max)
    # one refinement pass: remove the estimate and fit the remainder
    total = np.array([dc + sol[0], dr + sol[1]])
    moved = fourier_shift(s0, tuple(total))
    sol2, sig, _, n = _phase_fit(moved, r0, valid, block_px, f_max)
    total = total + sol2
    if dc == 0 and dr == 0:
        _, _, dbic, _ = _phase_fit(s0, r0, valid, block_px, f_max)
    else:
        dbic = float("inf")
    return ShiftEstimate(shift_px=(float(total[0]), float(total[1])),
                         sigma_px=(float(sig[0]), float(sig[1])), delta_bic=dbic, n_freq=n)


@dataclass(frozen=True)
class AffineEstimate:
    """Similarity-type misregistration field d(x) = t + M·(x − c) fitted to local shifts.

    Attributes
    ----------
    shift_px
        (d_col, d_row) at the centre ``centre_px`` (col, row), pixels.
    matrix
        2×2 matrix M acting on (col, row) offsets from the centre (dimensionless).
    rotation_deg
        Rotation of the real scene relative to the simulation, counter-clockwise on the
        map positive (degrees).
    scale
        Scale factor of the real scene relative to the simulation (1 = same).
    residual_px
        RMS of local shifts about the fitted field, pixels (local distortion).
    n_blocks
        Number of blocks whose local shift was used.
    local
        (n, 4) array of (col, row, d_col, d_row) local shifts.
    """

    shift_px: tuple[float, float]
    matrix: np.ndarray
    centre_px: tuple[float, float]
    rotation_deg: float
    scale: float
    residual_px: float
    n_blocks: int
    local: np.ndarray

    def field(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(d_col, d_row) maps of the fitted shift field on a grid of ``shape``."""
        rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
        dx = cols + 0.5 - self.centre_px[0]
        dy = rows + 0.5 - self.centre_px[1]
        m = self.matrix
        return (self.shift_px[0] + m[0, 0] * dx + m[0, 1] * dy,
                self.shift_px[1] + m[1, 0] * dx + m[1, 1] * dy)


def _block_shift(s: np.ndarray, r: np.ndarray, f_max: float) -> tuple[float, float, float]:
    n = s.shape[0]
    w = np.outer(np.hanning(n), np.hanning(n))
    fs = np.fft.fft2((s - s.mean()) * w)
    fr = np.fft.fft2((r - r.mean()) * w)
    x = fr * np.conj(fs)
    fy = np.fft.fftfreq(n)[:, None] * np.ones((1, n))
    fx = np.fft.fftfreq(n)[None, :] * np.ones((n, 1))
    fr_ = np.hypot(fy, fx)
    use = ((fx > 0) | ((fx == 0) & (fy > 0))) & (fr_ > 0) & (fr_ <= f_max)
    wgt = np.abs(x[use])
    ph = np.angle(x[use] ** 2)
    a = np.column_stack([-4 * np.pi * fx[use], -4 * np.pi * fy[use]]) * np.sqrt(wgt)[:, None]
    sol, *_ = np.linalg.lstsq(a, ph * np.sqrt(wgt), rcond=None)
    # quality: normalised correlation of the blocks (0 for a featureless block, e.g. a
    # saturated or uniform object: no shift is measured there, as below any threshold)
    norm = float(np.sqrt(np.sum(np.abs(fs) ** 2) * np.sum(np.abs(fr) ** 2)))
    rho = float(np.sum(np.real(x))) / norm if norm > 0 else 0.0
    return float(sol[0]), float(sol[1]), rho


def estimate_affine(sim: np.ndarray, real: np.ndarray, *, valid: np.ndarray | None = None,
                    block_px: int = 32, f_max: float = 0.2, min_rho: float = 0.5,
                    iterations: int = 3) -> AffineEstimate:
    """Iterated :func:`_estimate_affine_once`: the simulation is warped by the field found so
    far and the remainder re-estimated (removes the bias of a fixed analysis window toward
    zero shift)."""
    s = np.asarray(sim, float)
    total = None
    for _ in range(max(1, iterations)):
        moved = s if total is None else warp_by_field(s, *total.field(s.shape))
        est = _estimate_affine_once(moved, real, valid=valid, block_px=block_px, f_max=f_max,
                                    min_rho=min_rho)
        if total is None:
            total = est
            continue
        t = (total.shift_px[0] + est.shift_px[0], total.shift_px[1] + est.shift_px[1])
        m = total.matrix + est.matrix
        jac = np.eye(2) + m
        scale = float(np.sqrt(abs(np.linalg.det(jac))))
        rot = -float(np.degrees(np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1])))
        total = AffineEstimate(t, m, total.centre_px, rot, scale, est.residual_px,
                               est.n_blocks, est.local)
    assert total is not None
    return total


def _estimate_affine_once(sim: np.ndarray, real: np.ndarray, *, valid: np.ndarray | None,
                          block_px: int, f_max: float, min_rho: float) -> AffineEstimate:
    """Fit a shift + linear (rotation/scale/shear) field to local block shifts.

    ``sim`` should already be moved by the global whole-pixel shift, so that local
    shifts are below 1/(4 f_max) px. Blocks whose correlation after the shift is below
    ``min_rho`` (scene change, shadows) are ignored; the fit is iteratively reweighted
    (blocks with residuals > 3 × the robust spread are dropped).
    """
    s = np.asarray(sim, float)
    r = np.asarray(real, float)
    rows, cols = s.shape
    step = block_px // 2
    pts = []
    for r0 in range(0, rows - block_px + 1, step):
        for c0 in range(0, cols - block_px + 1, step):
            if valid is not None and not valid[r0:r0 + block_px, c0:c0 + block_px].all():
                continue
            dc, dr, rho = _block_shift(s[r0:r0 + block_px, c0:c0 + block_px],
                                       r[r0:r0 + block_px, c0:c0 + block_px], f_max)
            if rho >= min_rho:
                pts.append((c0 + block_px / 2, r0 + block_px / 2, dc, dr))
    p = np.asarray(pts, float).reshape(-1, 4)
    centre = (cols / 2.0, rows / 2.0)
    if len(p) < 6:
        return AffineEstimate((0.0, 0.0), np.zeros((2, 2)), centre, 0.0, 1.0, float("nan"),
                              len(p), p)
    keep = np.ones(len(p), bool)
    for _ in range(3):
        a = np.column_stack([np.ones(keep.sum()), p[keep, 0] - centre[0], p[keep, 1] - centre[1]])
        cx, *_ = np.linalg.lstsq(a, p[keep, 2], rcond=None)
        cy, *_ = np.linalg.lstsq(a, p[keep, 3], rcond=None)
        af = np.column_stack([np.ones(len(p)), p[:, 0] - centre[0], p[:, 1] - centre[1]])
        res = np.hypot(p[:, 2] - af @ cx, p[:, 3] - af @ cy)
        spread = 1.4826 * np.median(res[keep]) + 1e-3
        keep = res <= 3 * spread
        if keep.sum() < 6:
            keep = res <= np.sort(res)[5]
    m = np.array([[cx[1], cx[2]], [cy[1], cy[2]]])
    # on a north-up grid, (col, row) → (east, −north): rotation sign flips
    jac = np.eye(2) + m
    scale = float(np.sqrt(abs(np.linalg.det(jac))))
    rot = float(np.degrees(np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1])))
    return AffineEstimate((float(cx[0]), float(cy[0])), m, centre, -rot, scale,
                          float(np.sqrt(np.mean(res[keep] ** 2))), int(keep.sum()), p)


def warp_by_field(image: np.ndarray, d_col: np.ndarray, d_row: np.ndarray) -> np.ndarray:
    """Resample so that out(x) = image(x − d(x)) (cubic spline), bands first or 2-D."""
    from scipy import ndimage

    arr = np.asarray(image, float)
    rows, cols = np.mgrid[0:arr.shape[-2], 0:arr.shape[-1]].astype(float)
    at = np.stack([rows - d_row, cols - d_col])     # once for every band
    out = [ndimage.map_coordinates(b, at, order=3, mode="reflect", prefilter=True)
           for b in (arr if arr.ndim == 3 else [arr])]
    return np.stack(out) if arr.ndim == 3 else out[0]
