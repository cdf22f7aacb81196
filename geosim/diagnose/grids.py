"""One flight's co-gridded pixels and their diagnosis.

:class:`FlightPixels` holds a satellite window and the UAV pixels under it (the UAV grid
nested ``phi`` times finer); :func:`diagnose_pixels` brings both to the same bands,
calibrates the baseline Q by Laplacian variance (:func:`calibrate_q_lv`) when none is
given and runs :func:`~geosim.diagnose.engine.diagnose_arrays`; :func:`diagnose_grids`
also writes the outputs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import Diagnosis, diagnose_arrays
from geosim.diagnose.locate import laplacian_variance
from geosim.diagnose.report import write_diagnosis
from geosim.diagnose.report_figures import DEFAULT_DPI
from geosim.diagnose.simulate import QSimulator
from geosim.errors import DiagnosisError, ExtentError
from geosim.io.raster import RasterData
from geosim.physics.radiometry import luma

__all__ = ["FlightPixels", "diagnose_pixels", "diagnose_grids", "calibrate_q_lv",
           "common_bands", "sim_valid", "central_window", "MAX_SAT_PX"]


MAX_SAT_PX = 384


def calibrate_q_lv(sim: QSimulator, real_grey: np.ndarray, valid: np.ndarray, *,
                   q_min: float = 0.5, q_max: float = 8.0, quantized: bool = True) -> float:
    """Q at which the paper model's Laplacian variance equals the real scene's.

    The project's calibration (:func:`geosim.degrade.calibrate.calibrate_q`: a bracketed
    root finder that also accounts for the LV that rounding to whole DN adds, and raises
    :class:`~geosim.errors.CalibrationError` when the target is outside the bracket).
    """
    from geosim.degrade.calibrate import calibrate_q
    from geosim.errors import CalibrationError

    target = laplacian_variance(real_grey, valid)
    lo = max(q_min, sim.q_min)
    try:
        return float(calibrate_q(sim.uav, sim.valid, target, phi=sim.phi, q_min=lo,
                                 q_max=q_max, quantized=quantized, name="UAV image"))
    except CalibrationError:
        # noise (or compression) can make the scene look sharper than the sharpest
        # simulation: that is a finding for the diagnosis, whose baseline is then the
        # sharpest Q; anything else (flat scene, no overlap) is still an error
        if np.isfinite(target) and target > laplacian_variance(luma(sim(lo)), valid):
            import warnings

            warnings.warn(f"the satellite scene looks sharper (LV {target:.4g}) than the "
                          f"sharpest simulation (Q = {lo:g}); the diagnosis baseline is "
                          f"Q = {lo:g} (noise or compression raise the LV)", stacklevel=2)
            return float(lo)
        raise


def central_window(valid: np.ndarray, max_px: int) -> tuple[slice, slice]:
    """At most ``max_px`` × ``max_px`` pixels at the centre of the valid area's bounding box."""
    rows = np.flatnonzero(valid.any(axis=1))
    cols = np.flatnonzero(valid.any(axis=0))
    if rows.size == 0:
        raise ExtentError("satellite scene on the grid: no valid pixel in the common extent; "
                          "check that UAV and satellite images overlap")
    rc, cc = (rows[0] + rows[-1]) // 2, (cols[0] + cols[-1]) // 2
    h = min(max_px, rows[-1] - rows[0] + 1)
    w = min(max_px, cols[-1] - cols[0] + 1)
    r0 = max(0, rc - h // 2)
    c0 = max(0, cc - w // 2)
    return slice(r0, r0 + h), slice(c0, c0 + w)


@dataclass(frozen=True)
class FlightPixels:
    """What one flight's diagnosis reads: a satellite window and the UAV pixels under it.

    Attributes
    ----------
    uav
        The flight on the UAV grid nested in the satellite window (pixel size
        ``sat.transform.a / phi``, same origin).
    sat
        The satellite scene's window (its ``transform`` and ``crs`` place every output).
    q_base
        Calibrated Q to start from (None: calibrate here by Laplacian variance).
    sources
        Input files, recorded in the provenance tags.
    """

    uav: RasterData
    sat: RasterData
    q_base: float | None = None
    sources: tuple[str, ...] = ()

    @classmethod
    def of_arrays(cls, uav: np.ndarray, sat: np.ndarray, *, sat_transform: Affine, crs: CRS,
                  phi: int, uav_valid: np.ndarray | None = None,
                  sat_valid: np.ndarray | None = None, q_base: float | None = None
                  ) -> FlightPixels:
        """From in-memory ``(bands, rows, cols)`` arrays: the UAV grid is the satellite
        window's grid refined ``phi`` times (same origin); masks default to all valid."""
        def data(a: np.ndarray, valid: np.ndarray | None, t: Affine) -> RasterData:
            v = np.ones(a.shape[-2:], bool) if valid is None else np.asarray(valid, bool)
            return RasterData(array=a, valid=v, transform=t, crs=crs,
                              band_names=(None,) * a.shape[0])

        return cls(uav=data(uav, uav_valid, sat_transform * Affine.scale(1.0 / phi)),
                   sat=data(sat, sat_valid, sat_transform), q_base=q_base)


def diagnose_pixels(pixels: FlightPixels, *, phi: int, seed: int = 0, q_min: float = 0.5,
                    q_max: float = 8.0) -> Diagnosis:
    """Diagnose one flight's co-gridded pixels, in memory (what :func:`diagnose_grids`
    writes).

    Both images are brought to the same bands; the paper's model is simulated from the UAV
    pixels (their invalid ones filled, :class:`~geosim.diagnose.simulate.QSimulator`); the
    pixels compared are the satellite's valid ones whose ``phi`` × ``phi`` UAV pixels are
    all valid; the baseline Q is ``pixels.q_base`` or, where None, calibrated here by
    Laplacian variance within [``q_min``, ``q_max``].

    Parameters
    ----------
    pixels
        The satellite window and the UAV pixels under it.
    phi
        UAV pixels per satellite pixel along each axis.
    seed
        Seed of the refined simulation's noise realisation.
    q_min, q_max
        Range of the Laplacian-variance calibration of Q.
    """
    uav, sat = common_bands(pixels.uav.array, pixels.sat.array)
    sim = QSimulator(uav.astype(np.float32), phi=phi, valid=pixels.uav.valid, q_min=0.6)
    s0 = sim(2.0)
    valid = pixels.sat.valid & sim_valid(pixels.uav.valid, phi, s0.shape[-2:])
    q_base = pixels.q_base
    if q_base is None:
        q_base = calibrate_q_lv(sim, luma(sat), valid, q_min=q_min, q_max=q_max)
    return diagnose_arrays(sat, sim, q_base=q_base, rng=np.random.default_rng(seed),
                           valid=valid, gsd_m=abs(pixels.sat.transform.a), q_lo=0.7)


def diagnose_grids(pixels: FlightPixels, out_dir: Path, *, phi: int, seed: int = 0,
                   q_min: float = 0.5, q_max: float = 8.0, extra: dict[str, Any] | None = None,
                   dpi: int = DEFAULT_DPI) -> dict[str, Any]:
    """Diagnose one flight's co-gridded pixels (UAV at sat/phi, satellite at the sat grid;
    :func:`diagnose_pixels`) and write diagnosis.json, GeoTIFFs and figures (at ``dpi``)
    into ``out_dir``."""
    diag = diagnose_pixels(pixels, phi=phi, seed=seed, q_min=q_min, q_max=q_max)
    return write_diagnosis(diag, out_dir, transform=pixels.sat.transform, crs=pixels.sat.crs,
                           sources=list(pixels.sources), extra=extra, dpi=dpi)


def common_bands(uav: np.ndarray, sat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two images with the same bands: both as they are, or both grey (luma).

    A grey (1-band) flight or satellite scene says nothing about colour, so when one
    image is grey and the other RGB the RGB one is compared by its luma (BT.601).

    Parameters
    ----------
    uav, sat
        (bands, rows, cols) arrays, DN; 1 or >= 3 bands each.
    """
    nu, ns = uav.shape[0], sat.shape[0]
    if nu == ns:
        return uav, sat
    if 1 not in (nu, ns):
        raise DiagnosisError(f"UAV imagery has {nu} band(s) and the satellite scene {ns}; "
                             "give both the same bands (RGB) or one of them grey")
    if nu > 1:
        uav = luma(uav)[np.newaxis].astype(uav.dtype, copy=False)
    if ns > 1:
        sat = luma(sat)[np.newaxis].astype(np.float32, copy=False)
    return uav, sat


def sim_valid(uav_valid: np.ndarray, phi: int, shape: tuple[int, int]) -> np.ndarray:
    """Satellite pixels (``shape``) whose ``phi`` × ``phi`` UAV pixels are all valid."""
    r, c = shape
    v = uav_valid[: r * phi, : c * phi].reshape(r, phi, c, phi)
    return v.all(axis=(1, 3))
