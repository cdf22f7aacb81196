"""Radiometric and sampling effects on images in digital numbers (DN).

Images are float arrays with bands first, (bands, rows, cols), on a 0–255
scale for 8-bit data. Randomness only through an explicit Generator.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from geosim.physics.cubic import OPENCV_A, cubic_resize


def per_band_values(values: Sequence[float] | np.ndarray, bands: int, name: str) -> np.ndarray:
    """``values`` as one float per band, (bands,): a single value repeated; any other count
    than 1 or ``bands`` is an error naming ``name``."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size == 1:
        v = np.repeat(v, bands)
    if v.size != bands:
        raise ValueError(f"{name}: need 1 or {bands} values, got {v.size}")
    return v


def _per_band(values: Sequence[float] | np.ndarray, bands: int, name: str) -> np.ndarray:
    return per_band_values(values, bands, name)[:, np.newaxis, np.newaxis]


def apply_gain_offset(image: np.ndarray, *, gain: Sequence[float] | np.ndarray,
                      offset_dn: Sequence[float] | np.ndarray = 0.0) -> np.ndarray:
    """Per-band linear response: gain · x + offset (haze: gain < 1, offset > 0)."""
    img = np.asarray(image, dtype=float)
    return _per_band(gain, img.shape[0], "gain") * img + _per_band(offset_dn, img.shape[0],
                                                                    "offset_dn")


def haze(image: np.ndarray, *, transmission: Sequence[float], path_radiance_dn: Sequence[float]
         ) -> np.ndarray:
    """Path radiance model: x · t + L_path per band (t < 1, L_path > 0, bluest strongest)."""
    return apply_gain_offset(image, gain=transmission, offset_dn=path_radiance_dn)


def add_sensor_noise(image: np.ndarray, *, gain_dn: float, read_var_dn2: float,
                     rng: np.random.Generator) -> np.ndarray:
    """Add shot + read noise with variance a·signal + b (DN²).

    Parameters
    ----------
    gain_dn
        a: shot-noise variance per DN of signal (DN).
    read_var_dn2
        b: signal-independent read-noise variance (DN²).
    """
    img = np.asarray(image, dtype=float)
    var = gain_dn * np.clip(img, 0, None) + read_var_dn2
    return img + rng.standard_normal(img.shape) * np.sqrt(var)


def jpeg_roundtrip(image: np.ndarray, *, quality: int) -> np.ndarray:
    """Encode and decode as JPEG (8×8 DCT blocks) at ``quality`` 1–100.

    ``image`` is (bands, rows, cols) with 1 or 3 bands, 0–255; returns float.
    """
    img = np.clip(np.rint(np.asarray(image, dtype=float)), 0, 255).astype(np.uint8)
    hwc = np.moveaxis(img, 0, -1)
    if hwc.shape[-1] == 3:
        hwc = hwc[..., ::-1]  # OpenCV expects BGR
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(hwc),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    dec = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if dec.ndim == 2:
        dec = dec[..., np.newaxis]
    elif dec.shape[-1] == 3:
        dec = dec[..., ::-1]
    return np.moveaxis(dec, -1, 0).astype(float)


def resample_through_native(image: np.ndarray, *, native_pitch_px: float,
                            cubic_a: float = OPENCV_A) -> np.ndarray:
    """Simulate a product resampled from a coarser native GSD onto this grid.

    Each band is area-averaged onto a native grid ``native_pitch_px`` times
    coarser (the native detector integration), then resampled back to the original
    shape by cubic convolution with kernel parameter ``cubic_a`` (the product's
    resampling; −0.75 OpenCV's bicubic, −0.5 GDAL's). Content above the native
    Nyquist, 1 / (2 · native_pitch_px) cycles per pixel, is removed.
    """
    img = np.asarray(image, dtype=np.float32)
    rows, cols = img.shape[-2:]
    n_rows = max(2, int(round(rows / native_pitch_px)))
    n_cols = max(2, int(round(cols / native_pitch_px)))
    out = np.empty_like(img)
    for i, band in enumerate(img.reshape(-1, rows, cols)):
        low = cv2.resize(band, (n_cols, n_rows), interpolation=cv2.INTER_AREA)
        out.reshape(-1, rows, cols)[i] = cubic_resize(low, (rows, cols), cubic_a)
    return out.astype(float)


#: ITU-R BT.601 luma weights of R, G, B (as OpenCV's RGB2GRAY).
LUMA_WEIGHTS: tuple[float, float, float] = (0.299, 0.587, 0.114)


def luma(image: np.ndarray) -> np.ndarray:
    """Grey level (ITU-R BT.601 luma, as OpenCV's RGB2GRAY) of a (3, rows, cols) image.

    A single-band image is returned as is (as float).
    """
    img = np.asarray(image, dtype=float)
    if img.ndim == 2:
        return img
    if img.shape[0] == 1:
        return img[0]
    _require_luma_bands(img.shape[0])
    wr, wg, wb = LUMA_WEIGHTS
    return wr * img[0] + wg * img[1] + wb * img[2]


def luma_weights(n_bands: int) -> np.ndarray:
    """Per-band weights of :func:`luma`, (n_bands,): R, G, B first, extra bands 0; a single
    band 1."""
    if n_bands == 1:
        return np.ones(1)
    _require_luma_bands(n_bands)
    return np.concatenate([LUMA_WEIGHTS, np.zeros(n_bands - 3)])


def _require_luma_bands(n_bands: int) -> None:
    if n_bands < 3:
        raise ValueError(f"luma needs 1 or ≥3 bands (R, G, B first), got {n_bands}")
