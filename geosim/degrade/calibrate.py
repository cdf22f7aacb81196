"""Calibrate Q: find the Q whose degraded UAV imagery has the satellite's Laplacian variance.

LV(Q) of the degraded UAV image falls as Q grows (the OTF at every frequency
falls with Q); the calibrated Q solves LV(Q) = LV_satellite with a bracketed
root finder (Brent's method on [q_min, q_max]), after checking that the bracket
really contains the solution.

Speed. Every step before rounding is linear (luma, PSF convolution, bicubic
resampling), so degrading the grey image equals the grey of the degraded
RGB image: calibration works on one band. The truncated DCT coefficients of
the grey image are computed once (:class:`~geosim.degrade.core.SpectralDegrader`)
and each LV(Q) then costs two small matrix products per block, so a curve
and a root search of ~10 evaluations are cheap even for a whole flight.

Large images are handled as blocks (:class:`LVBlock`): each block degrades a
window of the UAV image with a margin around its core, and the Laplacian
moment sums of the cores are pooled, which gives the LV of the whole area.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from geosim.degrade.blur import (
    PAPER_LAPLACIAN,
    MomentSums,
    interior_mask,
    laplacian_moments,
    to_grey,
)
from geosim.degrade.core import SpectralDegrader, _check_phi, _check_q
from geosim.errors import CalibrationError
from geosim.physics.radiometry import LUMA_WEIGHTS

if TYPE_CHECKING:
    from geosim.io.raster import RasterData

#: Q range of real satellite cameras (the paper); outside it the model lacks physics.
PLAUSIBLE_Q = (0.5, 2.0)


def quantization_lv(step_grey: float, *, bands: int = 3) -> float:
    """Expected LV added by rounding each delivered band to a step of ``step_grey``.

    Rounding adds independent, uniform errors of variance step²/12 to each band;
    luma weights them by Σ c_b² (R, G, B) and the Laplacian by Σ 𝓛² = 13, so for
    8-bit RGB the LV rises by 13 × 0.4459 / 12 = 0.483 grey levels², a large
    share of a satellite LV of ~5. Degraded tiles are delivered rounded to the
    UAV's dtype, and the satellite's LV is measured on its rounded values, so the
    simulated LV must include it.

    Parameters
    ----------
    step_grey
        Rounding step in grey levels (1 for 8-bit data; 0 for float output).
    bands
        Bands of the delivered image: ≥ 3 uses the luma weights, 1 a single grey band.
    """
    weights = np.asarray(LUMA_WEIGHTS) if bands >= 3 else np.ones(1)
    return float((PAPER_LAPLACIAN**2).sum() * (weights**2).sum() * step_grey**2 / 12.0)


def delivery_offset_lv(image: np.ndarray, *, quantized: bool = True) -> float:
    """Expected LV from rounding the degraded bands to ``image``'s dtype (0 for floats).

    The degraded image is delivered in the input's dtype (:func:`~geosim.degrade.core.to_dtype`);
    for integer dtypes the rounding adds :func:`quantization_lv` to its LV.
    """
    arr = np.asarray(image)
    if not quantized or not np.issubdtype(arr.dtype, np.integer):
        return 0.0
    dn_max = 255.0 if arr.dtype == np.uint8 else float(np.iinfo(arr.dtype).max)
    return quantization_lv(255.0 / dn_max, bands=1 if arr.ndim == 2 else arr.shape[0])


def _erode(valid: np.ndarray, radius_px: int) -> np.ndarray:
    """Erode by a (2r+1)² square; beyond the array counts as valid (edge replicated)."""
    if radius_px <= 0 or valid.all():
        return valid
    k = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return cv2.erode(valid.astype(np.uint8), k, borderType=cv2.BORDER_REPLICATE) > 0


#: Reads a window of the grey UAV image: (row_px, col_px, height_px, width_px) relative
#: to the calibrated region's north-west corner (may reach outside it) → a
#: :class:`~geosim.io.raster.RasterData` of one band (grey float ``(1, height, width)``,
#: valid bool ``(height, width)``, the window's transform); outside the data: invalid.
GreyWindowReader = Callable[[int, int, int, int], "RasterData"]


@dataclass
class LVBlock:
    """One block of a blocked LV computation.

    Attributes
    ----------
    degrader
        Prepared degrader of the grey UAV window (core plus margin).
    rows, cols
        Region of the degrader's output (satellite pixels) whose Laplacian is
        taken: the core plus a one-pixel ring of neighbours.
    mask
        Bool array the shape of that region: pixels that count (already eroded
        by the Laplacian's reach against the whole area, so ring pixels are False).
    """

    degrader: SpectralDegrader
    rows: slice
    cols: slice
    mask: np.ndarray

    def moments(self, q: float) -> MomentSums:
        """Laplacian moment sums of the degraded block at ``q``."""
        if not self.mask.any():
            return MomentSums(0, 0.0, 0.0)
        degraded = self.degrader.degrade(q)[self.rows, self.cols]
        return laplacian_moments(degraded, self.mask)


@dataclass
class DegradedLV:
    """LV of degraded imagery as a function of Q, pooled over blocks, memoised.

    Call it with a Q to get the LV (grey levels²) of the degraded imagery over
    all the blocks' counting pixels, plus ``offset_lv`` (see :func:`quantization_lv`).
    ``lv_mask`` is the area's mask (satellite grid) of the pixels that count.
    """

    blocks: list[LVBlock]
    lv_mask: np.ndarray
    offset_lv: float = 0.0
    cache: dict[float, float] = field(default_factory=dict)

    @classmethod
    def from_image(cls, image: np.ndarray, valid: np.ndarray | None = None, *, phi: int = 10,
                   q_min: float = 0.5, obscuration: float = 0.0,
                   out_mask: np.ndarray | None = None, offset_lv: float = 0.0,
                   guard_sat_px: int = 0) -> DegradedLV:
        """Whole in-memory image as one block.

        Parameters
        ----------
        image
            UAV image, bands-first RGB (luma is taken) or one grey band, DN 0–255.
        valid
            UAV valid mask (True = valid) or None.
        out_mask
            Extra mask on the degraded grid (e.g. the satellite's valid pixels).
        offset_lv
            Added to every LV (see :func:`quantization_lv`).
        guard_sat_px
            Leave out pixels this close to UAV no-data (see :func:`build_blocked_lv`).
        """
        grey = image if np.ndim(image) == 2 else to_grey(image)
        degrader = SpectralDegrader(grey, phi=phi, q_min=q_min, valid=valid,
                                    obscuration=obscuration)
        usable = _erode(degrader.valid_out, guard_sat_px)
        counted = usable if out_mask is None else usable & out_mask
        rows, cols = degrader.out_shape
        lv_mask = interior_mask(counted, (rows, cols))
        return cls([LVBlock(degrader, slice(0, rows), slice(0, cols), lv_mask)], lv_mask,
                   offset_lv=offset_lv)

    @property
    def n_pixels(self) -> int:
        """Number of satellite pixels whose Laplacian counts."""
        return int(self.lv_mask.sum())

    @property
    def q_min(self) -> float:
        """Smallest Q the blocks were prepared for."""
        return max(b.degrader.q_min for b in self.blocks)

    def __call__(self, q: float) -> float:
        key = float(q)
        if key not in self.cache:
            total = MomentSums(0, 0.0, 0.0)
            for block in self.blocks:
                total = total + block.moments(key)
            self.cache[key] = total.variance + self.offset_lv
        return self.cache[key]


def build_blocked_lv(read_window: GreyWindowReader, shape_sat: tuple[int, int], *,
                     phi: int = 10, q_min: float = 0.5, out_mask: np.ndarray | None = None,
                     block_sat_px: int = 400, margin_sat_px: int = 32,
                     obscuration: float = 0.0, offset_lv: float = 0.0, guard_sat_px: int = 0,
                     progress: Callable[[int], object] | None = None) -> DegradedLV:
    """LV(Q) of a large area, degraded block by block with overlapping margins.

    The area is ``shape_sat`` satellite pixels (rows, cols); block cores of
    ``block_sat_px`` satellite pixels are degraded from UAV windows that reach
    ``margin_sat_px`` further on every side (real neighbouring data, or invalid
    outside the data), so the cores see almost the same PSF support as in one
    big image; the Laplacian moment sums of the cores are pooled.

    Parameters
    ----------
    read_window
        Reader of grey UAV windows (see :data:`GreyWindowReader`).
    shape_sat
        (rows, cols) of the area in satellite pixels; the UAV area is φ times larger.
    phi
        UAV pixels per satellite pixel.
    q_min
        Smallest Q that will be evaluated.
    out_mask
        (rows, cols) bool mask on the satellite grid of pixels that may count
        (e.g. the satellite's valid pixels); None = all.
    block_sat_px, margin_sat_px
        Core side and margin width, satellite pixels (margin ≥ 1).
    offset_lv
        Added to every LV (see :func:`quantization_lv`).
    guard_sat_px
        Also leave out pixels within this many satellite pixels (Chebyshev
        distance) of a degraded pixel that is invalid for lack of UAV data
        (≤ ``margin_sat_px``). Near the edge of the UAV data the PSF reaches
        into the smooth fill (:func:`~geosim.degrade.core.fill_invalid`) where a
        satellite sees textured ground, so the simulation's LV is biased low
        there (−1 % in Q at Q = 6 without a guard on a 100 × 100 px area); a
        guard of about the first dark ring (1.22 Q satellite pixels) removes it.
    progress
        Called with 1 after each block (e.g. ``tqdm.update``).

    Returns
    -------
    DegradedLV
        Callable Q → LV; the pixels that count are the area's degraded-valid
        pixels (all φ × φ UAV pixels valid) within ``out_mask``, eroded by the
        Laplacian's reach against the whole area (not against block edges).
    """
    phi = _check_phi(phi)
    rows_s, cols_s = (int(v) for v in shape_sat)
    if rows_s < 1 or cols_s < 1:
        raise ValueError(f"shape_sat must be positive, got {shape_sat}")
    if block_sat_px < 1 or margin_sat_px < 1:
        raise ValueError("block_sat_px and margin_sat_px must be ≥ 1")
    if not 0 <= guard_sat_px <= margin_sat_px:
        raise ValueError(f"guard_sat_px = {guard_sat_px} must be in [0, margin_sat_px = "
                         f"{margin_sat_px}]")
    if out_mask is not None and np.shape(out_mask) != (rows_s, cols_s):
        raise ValueError(f"out_mask shape {np.shape(out_mask)} != shape_sat {shape_sat}")
    m = int(margin_sat_px)
    uav_valid_sat = np.zeros((rows_s, cols_s), bool)
    prepared: list[tuple[SpectralDegrader, int, int, int, int]] = []
    for r0 in range(0, rows_s, block_sat_px):
        for c0 in range(0, cols_s, block_sat_px):
            h, w = min(block_sat_px, rows_s - r0), min(block_sat_px, cols_s - c0)
            window = read_window((r0 - m) * phi, (c0 - m) * phi,
                                 (h + 2 * m) * phi, (w + 2 * m) * phi)
            grey, valid = window.array[0], window.valid
            if progress is not None:
                progress(1)
            if not np.any(valid[m * phi:(m + h) * phi, m * phi:(m + w) * phi]):
                continue
            degrader = SpectralDegrader(grey, phi=phi, q_min=q_min, valid=valid,
                                        obscuration=obscuration)
            usable = _erode(degrader.valid_out, guard_sat_px)
            uav_valid_sat[r0:r0 + h, c0:c0 + w] = usable[m:m + h, m:m + w]
            prepared.append((degrader, r0, c0, h, w))
    counted = uav_valid_sat if out_mask is None else uav_valid_sat & np.asarray(out_mask, bool)
    lv_mask = interior_mask(counted, (rows_s, cols_s))
    blocks = []
    for degrader, r0, c0, h, w in prepared:
        mask = np.zeros((h + 2, w + 2), bool)
        mask[1:-1, 1:-1] = lv_mask[r0:r0 + h, c0:c0 + w]
        if mask.any():
            blocks.append(LVBlock(degrader, slice(m - 1, m + h + 1), slice(m - 1, m + w + 1),
                                  mask))
    return DegradedLV(blocks, lv_mask, offset_lv=offset_lv)


@dataclass(frozen=True)
class QSolution:
    """Result of a calibration: Q and the numbers around it."""

    q: float
    lv_at_q: float
    target_lv: float
    lv_at_q_min: float
    lv_at_q_max: float
    evaluations: int


def solve_q(lv_at: Callable[[float], float], target_lv: float, *, q_min: float = 0.5,
            q_max: float = 8.0, xtol: float = 1e-4, name: str = "image") -> QSolution:
    """Solve LV(Q) = target with Brent's method on a checked bracket.

    Parameters
    ----------
    lv_at
        LV of the degraded imagery at a Q (grey levels²), decreasing in Q.
    target_lv
        LV of the satellite scene (grey levels²).
    q_min, q_max
        Bracket (dimensionless).
    xtol
        Absolute tolerance on Q.
    name
        What is calibrated (e.g. ``"flight PA1"``), for messages.

    Raises
    ------
    CalibrationError
        The target is not bracketed, or an LV is not finite.
    """
    q_min, q_max = _check_q(q_min), _check_q(q_max)
    if not q_min < q_max:
        raise CalibrationError(f"{name}: q_min = {q_min} must be below q_max = {q_max}")
    if not (np.isfinite(target_lv) and target_lv > 0):
        raise CalibrationError(f"{name}: the satellite Laplacian variance is {target_lv!r}; "
                               "the satellite scene is flat or empty over the common extent")
    lv_lo, lv_hi = float(lv_at(q_min)), float(lv_at(q_max))
    if not (np.isfinite(lv_lo) and np.isfinite(lv_hi)):
        raise CalibrationError(f"{name}: no valid pixels to measure the degraded imagery's "
                               "Laplacian variance; check the valid masks and the overlap")
    if target_lv > lv_lo:
        raise CalibrationError(
            f"{name}: the satellite LV {target_lv:.4g} is above the degraded UAV LV "
            f"{lv_lo:.4g} at q_min = {q_min:g}: the satellite looks sharper than the sharpest "
            "simulation (noise, sharpening or compression raise its LV, or its DN range "
            "differs from the UAV's); lower parameters.q_min or run `geosim diagnose`")
    if target_lv < lv_hi:
        raise CalibrationError(
            f"{name}: the satellite LV {target_lv:.4g} is below the degraded UAV LV "
            f"{lv_hi:.4g} at q_max = {q_max:g}: the satellite is blurrier than the blurriest "
            "simulation; raise parameters.q_max or check the satellite scene (haze, "
            "clouds, wrong area)")
    evaluations = [2]

    def residual(q: float) -> float:
        evaluations[0] += 1
        return float(lv_at(q)) - target_lv

    if target_lv == lv_lo:
        q = q_min
    elif target_lv == lv_hi:
        q = q_max
    else:
        import scipy.optimize  # here: `geosim degrade` imports this module but never solves

        q = float(scipy.optimize.brentq(residual, q_min, q_max, xtol=xtol))
    return QSolution(q=q, lv_at_q=float(lv_at(q)), target_lv=float(target_lv),
                     lv_at_q_min=lv_lo, lv_at_q_max=lv_hi, evaluations=evaluations[0])


def lv_of_degraded(image: np.ndarray, valid: np.ndarray | None, q: float, *, phi: int = 10,
                   obscuration: float = 0.0, quantized: bool = True) -> float:
    """LV of the image degraded at ``q`` (grey levels²), over valid 0.5 m pixels.

    Computed on the degraded grey image (luma first: every step is linear), so
    it equals the LV of RGB → degrade → grey exactly before rounding.

    Parameters
    ----------
    image
        UAV image, bands-first RGB or one grey band, DN (uint8 0–255, other
        integer types scaled by their maximum, float taken as 0–255).
    valid
        UAV valid mask (True = valid) or None.
    q
        Q (dimensionless).
    phi
        UAV pixels per satellite pixel (whole number).
    obscuration
        Central obscuration, diameter ratio in [0, 1).
    quantized
        Include the LV that rounding the degraded bands to the image's integer
        dtype adds (:func:`delivery_offset_lv`), i.e. the LV of the image as
        :func:`~geosim.degrade.core.degrade_array` + ``to_dtype`` deliver it.
    """
    q = _check_q(q)
    return DegradedLV.from_image(image, valid, phi=_check_phi(phi), q_min=q,
                                 obscuration=obscuration,
                                 offset_lv=delivery_offset_lv(image, quantized=quantized))(q)


def lv_curve(image: np.ndarray, valid: np.ndarray | None, q_values: Sequence[float], *,
             phi: int = 10, obscuration: float = 0.0, quantized: bool = True) -> np.ndarray:
    """LV of the degraded image at each Q of ``q_values`` (grey levels²).

    Same conventions as :func:`lv_of_degraded`; the image is transformed once.
    """
    qs = np.asarray(q_values, dtype=float).reshape(-1)
    if qs.size == 0:
        return np.zeros(0)
    for q in qs:
        _check_q(q)
    model = DegradedLV.from_image(image, valid, phi=_check_phi(phi), q_min=float(qs.min()),
                                  obscuration=obscuration,
                                  offset_lv=delivery_offset_lv(image, quantized=quantized))
    return np.array([model(q) for q in qs])


def calibrate_q(image: np.ndarray, valid: np.ndarray | None, target_lv: float, *,
                phi: int = 10, q_min: float = 0.5, q_max: float = 8.0, xtol: float = 1e-4,
                obscuration: float = 0.0, quantized: bool = True, name: str = "image") -> float:
    """The Q at which the degraded image's LV equals ``target_lv``.

    Parameters
    ----------
    image
        UAV image, bands-first RGB or grey, DN.
    valid
        UAV valid mask or None.
    target_lv
        Satellite LV over the same ground (grey levels²), measured with
        :func:`~geosim.degrade.blur.laplacian_variance` on :func:`~geosim.degrade.blur.to_grey`.
    phi
        UAV pixels per satellite pixel.
    q_min, q_max
        Search bracket (dimensionless).
    xtol
        Absolute tolerance on Q.
    quantized
        See :func:`lv_of_degraded`.
    name
        What is calibrated (e.g. ``"flight PA1"``), for error messages.

    Raises
    ------
    CalibrationError
        ``target_lv`` is outside [LV(q_max), LV(q_min)]: the message names
        ``name`` and the three values.
    """
    model = DegradedLV.from_image(image, valid, phi=_check_phi(phi), q_min=_check_q(q_min),
                                  obscuration=obscuration,
                                  offset_lv=delivery_offset_lv(image, quantized=quantized))
    return solve_q(model, target_lv, q_min=q_min, q_max=q_max, xtol=xtol, name=name).q
