"""Photometric kernels: per-channel colour shift, HSV shifts and additive noise.

All kernels work on float32 images ``(bands, rows, cols)`` in digital numbers
(DN) and return new arrays clipped to ``[0, dn_max]``. Shift amounts are given
in 8-bit DN (the paper's ``[-255, 255]`` units) and scaled by ``dn_max / 255``,
so the same parameters mean the same relative change for 8-bit, 16-bit and
float (0–255) imagery. Bands 0, 1, 2 are red, green, blue; further bands (NIR,
…) are left untouched by the colour and HSV kernels.

HSV
---
OpenCV stores hue of *8-bit* images as 0–179 (degrees / 2) and so quantises
hue to 2° steps: an 8-bit RGB → HSV → RGB round trip is lossy even without a
shift. These kernels convert in float32 instead, where OpenCV's hue is in
degrees ``[0, 360)`` and saturation and value in ``[0, 1]``; hue is shifted
cyclically (``mod 360``), saturation and value are shifted in units of 1/255 and
clipped to ``[0, 1]``.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["add_noise", "colour_shift", "dn_max_for", "hsv_shift", "from_work", "to_work"]


def dn_max_for(dtype: np.dtype | type) -> float:
    """Full-scale value of an image dtype, DN: 255 for uint8 and float, 65535 for uint16.

    Float imagery is taken to be on the 0–255 scale used throughout geosim.
    """
    dt = np.dtype(dtype)
    if dt == np.uint8 or dt.kind == "f":
        return 255.0
    if dt == np.uint16:
        return 65535.0
    if dt == np.int16:
        return 32767.0
    raise ValueError(f"unsupported image dtype {dt}; use uint8, uint16, int16 or float32")


def to_work(image: np.ndarray) -> np.ndarray:
    """Float32 working copy of an image (values unchanged, DN)."""
    return np.asarray(image, dtype=np.float32).copy()


def from_work(work: np.ndarray, dtype: np.dtype | type) -> np.ndarray:
    """Back to ``dtype``: integers are rounded to nearest and clipped to their range."""
    dt = np.dtype(dtype)
    if dt.kind == "f":
        return work.astype(dt)
    info = np.iinfo(dt)
    return np.clip(np.rint(work), info.min, info.max).astype(dt)


def _rgb_count(work: np.ndarray) -> int:
    return min(3, work.shape[0])


def colour_shift(work: np.ndarray, shifts_dn: np.ndarray, *, dn_max: float = 255.0
                 ) -> np.ndarray:
    """Add a constant to each of the R, G, B bands.

    Parameters
    ----------
    work
        Float32 ``(bands, rows, cols)`` image, DN.
    shifts_dn
        Three shifts (R, G, B), 8-bit DN (scaled by ``dn_max / 255``); only as many
        as the image has colour bands are used.
    dn_max
        Full-scale value of the image, DN.
    """
    out = work.copy()
    n = _rgb_count(work)
    s = np.asarray(shifts_dn, dtype=np.float32).reshape(-1)[:n] * np.float32(dn_max / 255.0)
    out[:n] += s[:, np.newaxis, np.newaxis]
    return np.clip(out, 0.0, dn_max, out=out)


def hsv_shift(work: np.ndarray, *, hue_deg: float = 0.0, saturation_dn: float = 0.0,
              value_dn: float = 0.0, dn_max: float = 255.0) -> np.ndarray:
    """Shift hue (cyclically), saturation and value of the R, G, B bands.

    Parameters
    ----------
    work
        Float32 ``(bands, rows, cols)`` image, DN. Fewer than 3 bands: hue and
        saturation have no meaning and are ignored; value is added to the band.
    hue_deg
        Hue shift, degrees (wrapped to ``[0, 360)``).
    saturation_dn, value_dn
        Saturation and value shifts in 8-bit units (1/255 of full scale).
    dn_max
        Full-scale value of the image, DN.
    """
    out = work.copy()
    if work.shape[0] < 3:
        out += np.float32(value_dn * dn_max / 255.0)
        return np.clip(out, 0.0, dn_max, out=out)
    if not hue_deg % 360.0:
        return _sv_shift(out, work, saturation_dn=saturation_dn, value_dn=value_dn,
                         dn_max=dn_max)
    inv = np.float32(1.0 / dn_max)
    rgb = cv2.merge([np.clip(work[i] * inv, 0.0, 1.0) for i in range(3)])
    h, sat, val = cv2.split(cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV))
    if hue_deg:
        h += np.float32(hue_deg % 360.0)  # now in [0, 720): one wrap brings it to [0, 360)
        np.subtract(h, np.float32(360.0), out=h, where=h >= 360.0)
    if saturation_dn:
        sat += np.float32(saturation_dn / 255.0)
        np.clip(sat, 0.0, 1.0, out=sat)
    if value_dn:
        val += np.float32(value_dn / 255.0)
        np.clip(val, 0.0, 1.0, out=val)
    back = cv2.split(cv2.cvtColor(cv2.merge([h, sat, val]), cv2.COLOR_HSV2RGB))
    scale = np.float32(dn_max)
    for i in range(3):
        np.multiply(back[i], scale, out=out[i])
    return np.clip(out, 0.0, dn_max, out=out)


def _sv_shift(out: np.ndarray, work: np.ndarray, *, saturation_dn: float, value_dn: float,
              dn_max: float) -> np.ndarray:
    """Saturation and value shifts that keep the hue, without a colour-space round trip.

    With the hue fixed, OpenCV's HSV → RGB gives each channel as ``c = V (1 − S g_c)``
    with ``g_c = (V − c) / (V − min)`` a function of the hue alone; a grey pixel
    (``V = min``) has hue 0 (red), i.e. ``g = (0, 1, 1)``. So shifting S and V is
    ``c' = V' − (V − c) · V' S' / (V − min)`` (grey: ``R' = V'``, ``G' = B' = V' (1 − S')``):
    the same numbers as the :func:`cv2.cvtColor` round trip (to float32 rounding, about
    1e-4 DN), several times faster.
    """
    c = [np.clip(work[i], 0.0, dn_max) for i in range(3)]            # DN
    v = np.maximum(c[0], c[1])
    np.maximum(v, c[2], out=v)
    span = np.minimum(c[0], c[1])
    np.minimum(span, c[2], out=span)
    np.subtract(v, span, out=span)                                   # V − min = V·S
    tiny = np.float32(1e-30)  # x / max(y, tiny) is x / y, or 0 where x = y = 0
    s_new = span / np.maximum(v, tiny)                               # S
    if saturation_dn:
        s_new += np.float32(saturation_dn / 255.0)
        np.clip(s_new, 0.0, 1.0, out=s_new)
    v_new = v + np.float32(value_dn * dn_max / 255.0) if value_dn else v.copy()
    np.clip(v_new, 0.0, dn_max, out=v_new)
    vs = v_new * s_new                                               # V' S'
    k = vs / np.maximum(span, tiny)        # finite: (V − c) = 0 wherever span = 0
    grey_vs = vs * (span <= 0)                                       # V' S' on grey pixels
    for i in range(3):
        np.subtract(v, c[i], out=c[i])
        c[i] *= k
        np.subtract(v_new, c[i], out=out[i])
        if i:
            out[i] -= grey_vs
    return np.clip(out, 0.0, dn_max, out=out)


def add_noise(work: np.ndarray, *, sigma_dn: float, rng: np.random.Generator,
              dn_max: float = 255.0) -> np.ndarray:
    """Add zero-mean Gaussian noise, independent for every pixel and band.

    Parameters
    ----------
    work
        Float32 ``(bands, rows, cols)`` image, DN.
    sigma_dn
        Noise standard deviation, 8-bit DN (scaled by ``dn_max / 255``); single
        values are limited to ``[-255, 255]`` (8-bit DN), as in the paper.
    rng
        Source of the noise.
    dn_max
        Full-scale value of the image, DN.
    """
    noise = rng.standard_normal(work.shape, dtype=np.float32)
    if sigma_dn * 8.0 > 255.0:  # otherwise |noise| > 255 has probability < 1e-15
        noise *= np.float32(sigma_dn)
        np.clip(noise, -255.0, 255.0, out=noise)
        noise *= np.float32(dn_max / 255.0)
    else:
        noise *= np.float32(sigma_dn * dn_max / 255.0)
    noise += work
    return np.clip(noise, 0.0, dn_max, out=noise)
