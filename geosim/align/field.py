"""Local (non-rigid) co-registration: a smooth displacement field from window shifts.

After the global similarity has been applied, what is left between a flight and the
reference is a slowly varying displacement (orthomosaic stitching warps, relief).
This module estimates it in three pure steps:

1. :func:`measure_window_shifts` — sub-pixel phase correlation
   (:mod:`geosim.align.phasecorr`) in a regular grid of overlapping windows over the
   whole common extent;
2. :func:`reject_outliers` — windows are dropped for low confidence (featureless or
   changed ground, e.g. seasonal change), an implausibly large shift, or disagreement
   with their neighbours (the normalised median test of PIV, Westerweel & Scarano
   2005, applied twice);
3. :func:`fit_field` — a smoothing thin-plate spline (scipy ``RBFInterpolator``, each
   window's smoothing inversely proportional to its confidence) through the accepted
   shifts, sampled on a coarse node grid and interpolated between nodes by a cubic
   B-spline. Away from the measurements the field is faded to zero — the global model —
   so it never extrapolates beyond the data (``support`` says where it was estimated).

The result, :class:`DisplacementField`, lives in map metres and is a pure mapping that
a windowed resampler calls for each output window (:meth:`DisplacementField.apply`).

Convention
----------
``D(p) = (dx_m, dy_m)`` at a point ``p`` of the aligned frame (map metres, x east,
y north): the ground shown at ``p`` in the reference is shown at ``p + D(p)`` in the
flight *after the global correction*. Resampling the globally corrected flight at
``apply(p) = p + D(p)`` puts it on the reference; a point of the globally corrected
flight (a label) moves to ``invert(p)``. In pixels of a north-up grid of size ``g``:
``dx_m = dx_px · g``, ``dy_m = −dy_px · g`` with the window shift convention of
:mod:`geosim.align.phasecorr`.

References
----------
Westerweel, J. & Scarano, F. (2005). Universal outlier detection for PIV data.
Experiments in Fluids 39, 1096–1100.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from affine import Affine
from scipy import ndimage
from scipy.interpolate import RBFInterpolator
from scipy.spatial import cKDTree

from geosim.align.local import pair_valid, shifts_in_windows, window_starts
from geosim.align.phasecorr import as_grey
from geosim.errors import AlignmentError

__all__ = [
    "DisplacementField",
    "WindowShifts",
    "fit_field",
    "measure_window_shifts",
    "reject_outliers",
    "STATUS_NAMES",
]

#: Status codes of :attr:`WindowShifts.status`.
ACCEPTED, UNMEASURED, LOW_CONFIDENCE, TOO_LARGE, NEIGHBOUR_OUTLIER = 0, 1, 2, 3, 4
STATUS_NAMES = ("accepted", "unmeasured", "low_confidence", "too_large", "neighbour_outlier")


@dataclass(frozen=True, eq=False)
class WindowShifts:
    """Shifts measured in a grid of windows of one image pair.

    Attributes
    ----------
    x_px, y_px : numpy.ndarray
        ``(n_rows, n_cols)`` window centres, pixel-centre coordinates (column, row).
    dx_px, dy_px : numpy.ndarray
        Shift of the moving content relative to the reference (x right, y down), pixels;
        NaN where not measured.
    confidence : numpy.ndarray
        Phase-correlation confidence in ``[0, 1]`` (0 where not measured).
    status : numpy.ndarray
        ``int8`` code per window, see :data:`STATUS_NAMES` (0 = accepted).
    window_px, step_px : int
        Window side and distance between window starts, pixels.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    dx_px: np.ndarray
    dy_px: np.ndarray
    confidence: np.ndarray
    status: np.ndarray
    window_px: int
    step_px: int

    @property
    def accepted(self) -> np.ndarray:
        """Boolean mask of the windows that passed every test."""
        return self.status == ACCEPTED

    def with_status(self, status: np.ndarray) -> WindowShifts:
        """A copy with another status array."""
        return WindowShifts(self.x_px, self.y_px, self.dx_px, self.dy_px, self.confidence,
                            np.asarray(status, dtype=np.int8), self.window_px, self.step_px)

    def counts(self) -> dict[str, int]:
        """Number of windows per status name."""
        return {name: int(np.count_nonzero(self.status == k))
                for k, name in enumerate(STATUS_NAMES)}


def measure_window_shifts(reference: np.ndarray, moving: np.ndarray, *,
                          valid: np.ndarray | None = None, window_px: int = 256,
                          step_px: int = 128, upsample_factor: int = 20,
                          min_valid_fraction: float = 0.5, progress: bool = False
                          ) -> WindowShifts:
    """Phase-correlate two co-gridded images in a grid of (overlapping) windows.

    Parameters
    ----------
    reference, moving : numpy.ndarray
        Same-shaped ``(rows, cols)`` or bands-first images on one pixel grid (the moving
        one after the global correction).
    valid : numpy.ndarray of bool, optional
        ``True`` where both images are valid (default: finite in both).
    window_px, step_px : int
        Window side and step, pixels. Windows lie fully inside the image.
    upsample_factor : int
        Sub-pixel resolution ``1 / upsample_factor`` px before the final quadratic fit.
    min_valid_fraction : float
        A window is measured only if at least this fraction of its pixels is valid.
    progress : bool
        Show a progress bar.

    Returns
    -------
    WindowShifts
        Every window ``UNMEASURED`` or ``ACCEPTED`` (rejection is :func:`reject_outliers`).
    """
    ref = as_grey(reference, "reference")
    mov = as_grey(moving, "moving")
    both = pair_valid(ref, mov, valid)
    sr = window_starts(ref.shape[0], window_px, step_px)
    sc = window_starts(ref.shape[1], window_px, step_px)
    dx, dy, conf = shifts_in_windows(ref, mov, both, both, sr, sc, int(window_px),
                                     upsample_factor=int(upsample_factor),
                                     min_valid_fraction=min_valid_fraction, progress=progress)
    half = (window_px - 1) / 2.0
    yy, xx = np.meshgrid(sr + half, sc + half, indexing="ij")
    status = np.where(np.isfinite(dx) & np.isfinite(dy), ACCEPTED, UNMEASURED).astype(np.int8)
    return WindowShifts(xx.astype(float), yy.astype(float), dx, dy, conf, status,
                        int(window_px), int(step_px))


def _median_test(dx: np.ndarray, dy: np.ndarray, ok: np.ndarray, *, eps_px: float,
                 threshold: float) -> np.ndarray:
    """Normalised median test over the 8 neighbours; True where a window is an outlier.

    The neighbours' shifts are first fitted by a plane in window coordinates (so a smooth
    gradient of the field, e.g. along the image edge where all neighbours are on one side,
    is not mistaken for an outlier); the window's deviation from the plane is compared with
    the neighbours' median absolute deviation from it plus ``eps_px``.
    """
    n_r, n_c = dx.shape
    out = np.zeros(dx.shape, dtype=bool)
    for i, j in zip(*np.nonzero(ok), strict=True):
        i0, i1, j0, j1 = max(0, i - 1), min(n_r, i + 2), max(0, j - 1), min(n_c, j + 2)
        nb = ok[i0:i1, j0:j1].copy()
        nb[i - i0, j - j0] = False
        if np.count_nonzero(nb) < 4:
            continue  # too few neighbours to judge: keep
        ri, rj = np.nonzero(nb)
        a = np.stack([np.ones(ri.size), ri + i0 - i, rj + j0 - j], axis=1)
        r = 0.0
        for comp in (dx, dy):
            vals = comp[i0:i1, j0:j1][nb]
            coef, *_ = np.linalg.lstsq(a, vals, rcond=None)
            rm = np.median(np.abs(vals - a @ coef))
            r = max(r, abs(comp[i, j] - coef[0]) / (rm + eps_px))
        out[i, j] = r > threshold
    return out


def reject_outliers(shifts: WindowShifts, *, min_confidence: float = 0.1,
                    max_shift_px: float | None = None, median_threshold: float = 3.0,
                    median_eps_px: float = 0.3) -> WindowShifts:
    """Flag windows that cannot be trusted.

    Parameters
    ----------
    shifts : WindowShifts
        Measured windows.
    min_confidence : float
        Below it a window is ``low_confidence`` (featureless or changed ground).
    max_shift_px : float, optional
        Larger shifts are ``too_large`` (default a quarter of the window: beyond what
        phase correlation of the window resolves reliably).
    median_threshold, median_eps_px : float
        Normalised median test (Westerweel & Scarano 2005): a window whose shift differs
        from the median of its accepted neighbours by more than ``median_threshold``
        times their median absolute deviation (+ ``median_eps_px``, the measurement
        noise) is a ``neighbour_outlier``. Applied twice, so that a cluster of two does
        not shield itself.

    Returns
    -------
    WindowShifts
        The same measurements with updated status.
    """
    if max_shift_px is None:
        max_shift_px = shifts.window_px / 4.0
    st = shifts.status.copy()
    measured = st != UNMEASURED
    st[measured & (shifts.confidence < min_confidence)] = LOW_CONFIDENCE
    mag = np.hypot(shifts.dx_px, shifts.dy_px)
    st[(st == ACCEPTED) & ~(mag <= max_shift_px)] = TOO_LARGE
    for _ in range(2):
        bad = _median_test(shifts.dx_px, shifts.dy_px, st == ACCEPTED, eps_px=median_eps_px,
                           threshold=median_threshold)
        if not bad.any():
            break
        st[bad] = NEIGHBOUR_OUTLIER
    return shifts.with_status(st)


@dataclass(frozen=True, eq=False)
class DisplacementField:
    """A smooth displacement field on a coarse node grid, in map metres.

    Attributes
    ----------
    node_transform : affine.Affine
        North-up affine of the node grid: node ``(i, j)`` is the *centre* of "pixel"
        ``(row i, col j)`` (so this is the GeoTIFF transform of the field raster).
    dx_m, dy_m : numpy.ndarray
        ``(n_rows, n_cols)`` float64 displacement at the nodes, metres (east, north);
        0 where the global model is kept.
    support : numpy.ndarray
        ``(n_rows, n_cols)`` float in ``[0, 1]``: 1 where the field was estimated from
        measurements nearby, 0 where it falls back to the global model (no measurement
        within reach), in between over the taper.
    stats : dict
        JSON-able numbers about the fit (see :func:`fit_field`).
    """

    node_transform: Affine
    dx_m: np.ndarray
    dy_m: np.ndarray
    support: np.ndarray
    stats: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        t = self.node_transform
        if t.b != 0 or t.d != 0 or t.a <= 0 or t.e >= 0:
            raise AlignmentError(f"displacement field: node grid transform {tuple(t)[:6]} is "
                                 "not north-up; build it on a north-up grid")
        coef = [ndimage.spline_filter(np.asarray(a, dtype=np.float64), order=3, mode="nearest")
                for a in (self.dx_m, self.dy_m)]
        object.__setattr__(self, "_coef", coef)

    @property
    def spacing_m(self) -> float:
        """Distance between nodes, metres."""
        return float(self.node_transform.a)

    @property
    def shape(self) -> tuple[int, int]:
        """``(n_rows, n_cols)`` of the node grid."""
        return tuple(self.dx_m.shape)  # type: ignore[return-value]

    def displacement_m(self, x_m: np.ndarray, y_m: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
        """``D(x, y)`` in metres (cubic B-spline between nodes, constant beyond the grid).

        Parameters
        ----------
        x_m, y_m : array_like
            Map coordinates (same shape), metres.

        Returns
        -------
        tuple of numpy.ndarray
            ``(dx_m, dy_m)``, same shape as the inputs, float64.
        """
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        inv = ~self.node_transform
        # node centres sit at pixel centres: fractional index = corner coordinate - 0.5
        col = inv.a * x + inv.b * y + inv.c - 0.5
        row = inv.d * x + inv.e * y + inv.f - 0.5
        coords = np.stack([row.ravel(), col.ravel()])
        out = [ndimage.map_coordinates(c, coords, order=3, mode="nearest", prefilter=False)
               .reshape(x.shape) for c in self._coef]  # type: ignore[attr-defined]
        return out[0], out[1]

    def apply(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``p + D(p)``: where to sample the globally corrected flight for aligned point ``p``."""
        dx, dy = self.displacement_m(x_m, y_m)
        return np.asarray(x_m, dtype=np.float64) + dx, np.asarray(y_m, dtype=np.float64) + dy

    def invert(self, x_m: np.ndarray, y_m: np.ndarray, *, iterations: int = 6
               ) -> tuple[np.ndarray, np.ndarray]:
        """Aligned point ``p`` with ``apply(p) = q`` (fixed-point iteration).

        Moves a point of the globally corrected flight (e.g. a label centre) into the
        aligned frame. Converges because the field's gradient is far below 1.
        """
        qx = np.asarray(x_m, dtype=np.float64)
        qy = np.asarray(y_m, dtype=np.float64)
        px, py = qx.copy(), qy.copy()
        for _ in range(iterations):
            dx, dy = self.displacement_m(px, py)
            px, py = qx - dx, qy - dy
        return px, py

    def magnitude_m(self) -> np.ndarray:
        """``hypot(dx_m, dy_m)`` at the nodes."""
        return np.hypot(self.dx_m, self.dy_m)


def _taper(dist: np.ndarray, reach: float, fade: float) -> np.ndarray:
    """1 up to ``reach``, raised cosine down to 0 at ``reach + fade``."""
    t = np.clip((dist - reach) / max(fade, 1e-9), 0.0, 1.0)
    return 0.5 + 0.5 * np.cos(np.pi * t)


def fit_field(shifts: WindowShifts, pixel_transform: Affine, shape: tuple[int, int], *,
              node_spacing_px: int | None = None, smoothing: float = 0.1,
              reach_px: float | None = None, fade_px: float | None = None,
              min_windows: int = 4) -> DisplacementField:
    """Smooth displacement field through the accepted window shifts.

    Parameters
    ----------
    shifts : WindowShifts
        After :func:`reject_outliers`; only ``accepted`` windows are used.
    pixel_transform : affine.Affine
        North-up affine of the image grid the shifts were measured on (pixel corners).
    shape : tuple of int
        ``(rows, cols)`` of that grid; the node grid covers it.
    node_spacing_px : int, optional
        Node spacing in pixels (default the window step).
    smoothing : float
        Thin-plate-spline smoothing in units of (node spacing)², divided by each
        window's confidence: 0 interpolates exactly; larger values follow noisy windows
        less.
    reach_px, fade_px : float, optional
        The field is kept where a node is within ``reach_px`` of an accepted window
        centre (default 1.5 window steps: single missing windows are bridged) and faded
        to zero (the global model) over the next ``fade_px`` (default 2 window steps).
    min_windows : int
        With fewer accepted windows the field is zero everywhere (global model).

    Returns
    -------
    DisplacementField
        ``stats``: ``n_windows`` per status, ``fit_rms_px`` (accepted shifts vs the field),
        ``max_px``, ``median_px`` (field magnitude over supported nodes), ``supported_fraction``.
    """
    t = pixel_transform
    if t.b != 0 or t.d != 0:
        raise AlignmentError("displacement field: the image grid must be north-up")
    g = float(t.a)
    step = int(node_spacing_px or shifts.step_px)
    reach = float(reach_px if reach_px is not None else 1.5 * shifts.step_px)
    fade = float(fade_px if fade_px is not None else 2.0 * shifts.step_px)
    rows, cols = int(shape[0]), int(shape[1])
    n_r, n_c = max(1, math.ceil(rows / step)) + 1, max(1, math.ceil(cols / step)) + 1
    # node (i, j) at pixel-corner coordinates ((j - 0.5 + 0.5)·step, ...) = j·step: the grid
    # spans the image with a node on every edge
    node_t = t * Affine.translation(-0.5 * step, -0.5 * step) * Affine.scale(step)
    jj, ii = np.meshgrid(np.arange(n_c) * step, np.arange(n_r) * step)
    acc = shifts.accepted
    n_acc = int(np.count_nonzero(acc))
    stats: dict = {"n_windows": shifts.counts(), "window_px": shifts.window_px,
                   "step_px": shifts.step_px, "node_spacing_px": step,
                   "node_spacing_m": step * g, "smoothing": smoothing, "reach_px": reach,
                   "fade_px": fade}
    zeros = np.zeros((n_r, n_c))
    if n_acc < min_windows:
        stats.update(fit_rms_px=None, max_px=0.0, median_px=0.0, supported_fraction=0.0,
                     note=f"only {n_acc} accepted window(s) (< {min_windows}): global model "
                          "everywhere")
        return DisplacementField(node_t, zeros, zeros.copy(), zeros.copy(), stats)
    # window centres: pixel-centre coords → corner coords
    cx = shifts.x_px[acc] + 0.5
    cy = shifts.y_px[acc] + 0.5
    d = np.stack([shifts.dx_px[acc], shifts.dy_px[acc]], axis=1)
    conf = np.clip(shifts.confidence[acc], 0.05, 1.0)
    pts = np.stack([cy, cx], axis=1) / step
    rbf = RBFInterpolator(pts, d, kernel="thin_plate_spline", smoothing=smoothing / conf,
                          degree=1)
    nodes = np.stack([ii.ravel(), jj.ravel()], axis=1) / step
    val = rbf(nodes).reshape(n_r, n_c, 2)
    fit_rms = float(np.sqrt(np.mean(np.sum((rbf(pts) - d) ** 2, axis=1))))
    dist, _ = cKDTree(np.stack([cy, cx], axis=1)).query(
        np.stack([ii.ravel(), jj.ravel()], axis=1).astype(float))
    sup = _taper(dist.reshape(n_r, n_c), reach, fade)
    # never more than the largest accepted shift: no extrapolation blow-up
    cap = float(np.max(np.hypot(d[:, 0], d[:, 1])))
    mag = np.hypot(val[..., 0], val[..., 1])
    val *= np.minimum(1.0, cap / np.maximum(mag, 1e-12))[..., None]
    dx_px = val[..., 0] * sup
    dy_px = val[..., 1] * sup
    mag_px = np.hypot(dx_px, dy_px)[sup >= 1.0]
    stats.update(fit_rms_px=fit_rms,
                 max_px=float(mag_px.max()) if mag_px.size else 0.0,
                 median_px=float(np.median(mag_px)) if mag_px.size else 0.0,
                 supported_fraction=float(np.mean(sup >= 1.0)))
    return DisplacementField(node_t, dx_px * g, -dy_px * g, sup, stats)
