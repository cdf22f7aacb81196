"""Photometric kernels: per-channel colour shift, HSV shifts and additive noise.

All kernels work on float32 images in digital numbers (DN), *pixel-interleaved*
``(rows, cols, bands)`` (OpenCV's layout: colour conversions and per-channel
arithmetic run in one pass without splitting the bands), and return arrays
clipped to ``[0, dn_max]``; the input is never modified. Shift amounts are given
in 8-bit DN (the paper's ``[-255, 255]`` units) and scaled by ``dn_max / 255``,
so the same parameters mean the same relative change for 8-bit, 16-bit and
float (0–255) imagery. Bands 0, 1, 2 are red, green, blue; further bands (NIR,
…) are left untouched by the colour and HSV kernels.

HSV
---
OpenCV stores hue of *8-bit* images as 0–179 (degrees / 2) and so quantises
hue to 2° steps: an 8-bit RGB → HSV → RGB round trip is lossy even without a
shift. These kernels convert in float32 instead, where OpenCV's hue is in
degrees ``[0, 360)``, saturation in ``[0, 1]`` and value in the image's DN (the float
conversion is scale-free, so the image is not rescaled to ``[0, 1]``); hue is shifted
cyclically (``mod 360``), saturation and value are shifted in units of 1/255 of full
scale and clipped to it.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["NoiseBlockCache", "add_noise", "colour_lut", "colour_shift", "dn_max_for",
           "hsv_shift", "from_work", "saturates_to_range", "to_work"]

#: Largest 31-bit seed handed to OpenCV's generator.
_CV_SEED_MAX = 2**31 - 1

_CV_DEPTH = {np.dtype(np.uint8): cv2.CV_8U, np.dtype(np.uint16): cv2.CV_16U,
             np.dtype(np.int16): cv2.CV_16S}


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


def to_work(hwc: np.ndarray) -> np.ndarray:
    """Float32 working copy of an interleaved ``(rows, cols, bands)`` block (DN, unchanged)."""
    return hwc.astype(np.float32)


def from_work(work: np.ndarray, dtype: np.dtype | type, *, out: np.ndarray | None = None
              ) -> np.ndarray:
    """Back to ``dtype`` (same shape): integers are rounded to nearest and clipped to their range.

    Rounding is to nearest, ties to even (as :func:`numpy.rint`); OpenCV's saturating
    conversion does round, clip and cast in one pass. ``out`` (contiguous, of
    ``dtype`` and ``work``'s shape) receives the result if given.
    """
    dt = np.dtype(dtype)
    if out is None:
        out = np.empty(work.shape, dt)
    if dt.kind == "f":
        out[...] = work
    elif dt in _CV_DEPTH:
        flat = np.ascontiguousarray(work, dtype=np.float32).reshape(work.shape[0], -1)
        cv2.add(flat, 0.0, dst=out.reshape(flat.shape), dtype=_CV_DEPTH[dt])
    else:
        info = np.iinfo(dt)
        out[...] = np.clip(np.rint(work), info.min, info.max)
    return out


def saturates_to_range(dtype: np.dtype | type) -> bool:
    """Whether OpenCV's saturating conversion to ``dtype`` clips to ``[0, dn_max_for(dtype)]``.

    True for uint8 and uint16: a final clip to the full scale before :func:`from_work`
    changes nothing there (clip-then-round equals round-then-saturate), so it is skipped.
    """
    return np.dtype(dtype) in (np.dtype(np.uint8), np.dtype(np.uint16))


def colour_lut(shifts_dn: np.ndarray, bands: int, *, dn_max: float = 255.0) -> np.ndarray:
    """:func:`colour_shift` of every uint8 value as a float32 look-up table for ``cv2.LUT``.

    Returns a ``(1, 256, bands)`` float32 table: ``cv2.LUT(block, table)`` equals
    ``colour_shift(to_work(block), shifts_dn)`` exactly (the table *is* that kernel run
    on the 256 values), in one pass instead of three (convert, add, clip).
    """
    ramp = np.repeat(np.arange(256, dtype=np.float32)[:, np.newaxis], bands, axis=1)
    return colour_shift(ramp.reshape(1, 256, bands), shifts_dn, dn_max=dn_max)


def _rgb_count(work: np.ndarray) -> int:
    return min(3, work.shape[-1])


def colour_shift(work: np.ndarray, shifts_dn: np.ndarray, *, dn_max: float = 255.0
                 ) -> np.ndarray:
    """Add a constant to each of the R, G, B bands.

    Parameters
    ----------
    work
        Float32 ``(rows, cols, bands)`` image, DN.
    shifts_dn
        Three shifts (R, G, B), 8-bit DN (scaled by ``dn_max / 255``); only as many
        as the image has colour bands are used.
    dn_max
        Full-scale value of the image, DN.
    """
    n = _rgb_count(work)
    s = np.zeros(work.shape[-1], np.float32)
    s[:n] = np.asarray(shifts_dn, dtype=np.float32).reshape(-1)[:n] * np.float32(dn_max / 255.0)
    if work.shape[-1] <= 4:  # OpenCV adds a per-channel scalar in one pass
        out = cv2.add(work, (*s.tolist(), 0.0, 0.0, 0.0)[:4]).reshape(work.shape)
    else:
        out = work + s
    return np.clip(out, 0.0, dn_max, out=out)


def hsv_shift(work: np.ndarray, *, hue_deg: float = 0.0, saturation_dn: float = 0.0,
              value_dn: float = 0.0, dn_max: float = 255.0, clip_input: bool = True,
              clip_output: bool = True) -> np.ndarray:
    """Shift hue (cyclically), saturation and value of the R, G, B bands.

    One float32 RGB → HSV → RGB round trip (OpenCV) for any combination of the
    three shifts.

    Parameters
    ----------
    work
        Float32 ``(rows, cols, bands)`` image, DN. Fewer than 3 bands: hue and
        saturation have no meaning and are ignored; value is added to the band.
    hue_deg
        Hue shift, degrees (wrapped to ``[0, 360)``).
    saturation_dn, value_dn
        Saturation and value shifts in 8-bit units (1/255 of full scale).
    dn_max
        Full-scale value of the image, DN.
    clip_input, clip_output
        Clip the input / the result to ``[0, dn_max]``. The pipeline skips the input
        clip when the block is already in range (every kernel's result and every
        uint8/uint16 block is) and the output clip when the next step is a saturating
        conversion (:func:`saturates_to_range`): the values are the same, two passes fewer.
    """
    if work.shape[-1] < 3:
        out = work + np.float32(value_dn * dn_max / 255.0)
        return np.clip(out, 0.0, dn_max, out=out)
    # OpenCV's float RGB -> HSV is scale-free: V comes out in the input's DN, S in [0, 1],
    # H in degrees, so the image is not rescaled to [0, 1] and back (two passes fewer)
    rgb = work[..., :3]
    if clip_input:
        rgb = np.clip(rgb, 0.0, dn_max)              # a new (rows, cols, 3) array
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)       # H in [0, 360), S in [0, 1], V in DN
    # H + (hue mod 360) lies in [0, 720): OpenCV's float HSV → RGB takes the hue
    # modulo 360 (tested), so the shift is cyclic without a wrap pass.
    cv2.add(hsv, (float(hue_deg % 360.0), saturation_dn / 255.0, value_dn * dn_max / 255.0,
                  0.0), dst=hsv)
    # clip S and V: only on the side a shift moves them to (H, S and V of an in-range
    # block are in [0, 360), [0, 1] and [0, dn_max]; a clip on the other side is a no-op)
    if saturation_dn > 0 or value_dn > 0:
        cv2.min(hsv, (720.0, 1.0, dn_max, 0.0), dst=hsv)
    if saturation_dn < 0 or value_dn < 0:
        cv2.max(hsv, (0.0, 0.0, 0.0, 0.0), dst=hsv)
    back = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    if clip_output:
        np.clip(back, 0.0, dn_max, out=back)
    if work.shape[-1] == 3:
        return back
    out = work.copy()
    out[..., :3] = back
    return out


class NoiseBlockCache:
    """The last noise block :func:`add_noise` drew, for an identical draw that follows.

    A noise block is a function of its OpenCV seed, shape, ``sigma_dn`` and ``dn_max``
    only, so a second image whose noise generator gives the same seed (the pair's
    "together" noise: one seed for both images) can take the block instead of drawing
    it again: the same values, bit for bit. One block is kept (the pipeline runs the two
    images of a pair block by block in turn).
    """

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._noise: np.ndarray | None = None
        self.hits = 0

    def take(self, key: tuple) -> np.ndarray | None:
        """The cached block if it was drawn with ``key`` (then forgotten), else None."""
        if self._key != key:
            return None
        noise, self._key, self._noise = self._noise, None, None
        self.hits += 1
        return noise

    def put(self, key: tuple, noise: np.ndarray) -> None:
        """Keep ``noise`` (not to be modified afterwards) as the block drawn with ``key``."""
        self._key, self._noise = key, noise


def add_noise(work: np.ndarray, *, sigma_dn: float, rng: np.random.Generator,
              dn_max: float = 255.0, out: np.ndarray | None = None,
              cache: NoiseBlockCache | None = None) -> np.ndarray:
    """Add zero-mean Gaussian noise, independent for every pixel and band.

    The normals come from OpenCV's generator (:func:`cv2.randn`, 4–5× faster than
    numpy's for float32), seeded from ``rng``: one 31-bit seed drawn per call, so
    a generator consumed call after call (block after block) gives a reproducible
    noise image.

    Parameters
    ----------
    work
        Float32 ``(rows, cols, bands)`` image, DN.
    sigma_dn
        Noise standard deviation, 8-bit DN (scaled by ``dn_max / 255``); single
        values are limited to ``[-255, 255]`` (8-bit DN), as in the paper.
    rng
        Source of the noise (its next draw seeds OpenCV's generator).
    dn_max
        Full-scale value of the image, DN.
    out
        Optional uint8/uint16 array of ``work``'s shape (:func:`saturates_to_range`):
        the noisy image is added, rounded and saturated straight into it, one OpenCV pass
        instead of add, clip and :func:`from_work` (the same values), and returned.
    cache
        Optional :class:`NoiseBlockCache`: the block is taken from it when it holds one
        drawn with the same seed, shape and amounts, and left in it otherwise.
    """
    # cv2.randn draws from the calling thread's generator; seeding it right before
    # the draw makes the result independent of anything else run before.
    seed = int(rng.integers(1, _CV_SEED_MAX))
    key = (seed, work.shape, float(sigma_dn), float(dn_max))
    noise = cache.take(key) if cache is not None else None
    if noise is None:
        noise = _draw_noise(work.shape, seed, sigma_dn, dn_max)
        if cache is not None:
            cache.put(key, noise)
    flat = noise.reshape(noise.shape[0], -1)
    if out is not None:
        if not saturates_to_range(out.dtype) or out.shape != work.shape:
            raise ValueError(f"out must be uint8 or uint16 of shape {work.shape}")
        src = np.ascontiguousarray(work, dtype=np.float32).reshape(flat.shape)
        cv2.add(src, flat, dst=out.reshape(flat.shape), dtype=_CV_DEPTH[out.dtype])
        return out
    res = noise + work  # a new array: a cached block stays as drawn
    return np.clip(res, 0.0, dn_max, out=res)


def _draw_noise(shape: tuple[int, ...], seed: int, sigma_dn: float, dn_max: float
                ) -> np.ndarray:
    """Float32 noise block of ``shape``, DN: OpenCV's normals from ``seed``, scaled."""
    noise = np.empty(shape, np.float32)
    flat = noise.reshape(noise.shape[0], -1)  # one channel: any number of bands
    cv2.setRNGSeed(seed)
    if sigma_dn * 8.0 > 255.0:  # otherwise |noise| > 255 has probability < 1e-15
        cv2.randn(flat, 0.0, float(sigma_dn))
        np.clip(noise, -255.0, 255.0, out=noise)
        noise *= np.float32(dn_max / 255.0)
    else:
        cv2.randn(flat, 0.0, float(sigma_dn * dn_max / 255.0))
    return noise
