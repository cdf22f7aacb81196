"""Resampling kernels: affine warps and displacement-field remaps of an image and its mask.

The public functions take bands-first images ``(bands, rows, cols)``; masks are
``(rows, cols)`` bool (True = valid). Image bands are interpolated bicubically
(OpenCV, border replicated so that no black fringe bleeds into valid pixels); the
mask is resampled with nearest neighbour and everything sampled from outside the
input is marked invalid. Invalid pixels are set to 0 in the output image. Pure
functions: nothing is modified in place.

The work is done on pixel-interleaved ``(rows, cols, bands)`` arrays (OpenCV's
layout: each pixel's source position is computed once for all bands), and the
pipeline keeps its images in that layout from its first stage to its last
(:func:`affine_resample_hwc`, :func:`remap_resample_hwc`, :func:`interleave`,
:func:`planar`), so that a chain of stages converts the layout once each way.
"""

from __future__ import annotations

import cv2
import numpy as np

from geosim.augment.geometry import integer_permutation, is_identity, to_cv2_inverse

__all__ = ["INTERPOLATION", "affine_resample", "affine_resample_hwc", "bands_last_view",
           "interleave",
           "permute_exact", "planar", "remap_resample", "remap_resample_hwc", "zero_invalid"]

#: OpenCV interpolation flags by name.
INTERPOLATION = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR,
                 "cubic": cv2.INTER_CUBIC}

#: Output rows per block when remapping (bounds the memory of the coordinate maps).
REMAP_BLOCK_ROWS = 512

#: Most bands OpenCV's warps interpolate in one multi-channel call.
_CV_MAX_CHANNELS = 4

_CV2_DTYPES = {np.dtype(t) for t in (np.uint8, np.uint16, np.int16, np.float32, np.float64)}


def _check(image: np.ndarray, mask: np.ndarray) -> None:
    if image.ndim != 3:
        raise ValueError(f"image must be (bands, rows, cols), got shape {image.shape}")
    if mask.shape != image.shape[1:] or mask.dtype != bool:
        raise ValueError(f"mask must be bool {image.shape[1:]}, got {mask.dtype} {mask.shape}")
    if image.dtype not in _CV2_DTYPES:
        raise ValueError(f"unsupported image dtype {image.dtype}; use uint8, uint16, int16 "
                         "or float32")


def bands_last_view(image: np.ndarray) -> np.ndarray | None:
    """The contiguous ``(rows, cols, bands)`` array a ``(bands, rows, cols)`` image views, or None.

    An image read pixel-interleaved (as :func:`geosim.augment.io.read_tile` reads tiles)
    is handed around as ``np.moveaxis(hwc, -1, 0)``; this gives ``hwc`` back, no copy.
    """
    hwc = np.moveaxis(image, 0, -1)
    return hwc if hwc.flags.c_contiguous else None


def interleave(image: np.ndarray) -> np.ndarray:
    """``(bands, rows, cols)`` → a new contiguous ``(rows, cols, bands)`` array."""
    bands, rows, cols = image.shape
    if bands == 1:
        return image[0].reshape(rows, cols, 1).copy()
    return cv2.merge(list(image)).reshape(rows, cols, bands)


def planar(hwc: np.ndarray) -> np.ndarray:
    """``(rows, cols, bands)`` → a new contiguous ``(bands, rows, cols)`` array."""
    rows, cols, bands = hwc.shape
    out = np.empty((bands, rows, cols), hwc.dtype)
    if bands == 1:
        out[0] = hwc[..., 0]
    else:
        cv2.split(hwc, list(out))  # writes into the planes
    return out


def zero_invalid(hwc: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Set the pixels of an interleaved image where ``mask`` is False to 0, in place."""
    if not mask.all():
        invalid = np.logical_not(mask).view(np.uint8)
        if hwc.shape[-1] <= _CV_MAX_CHANNELS:
            cv2.bitwise_and(hwc, 0, dst=hwc, mask=invalid)  # one pass, only where invalid
        else:
            hwc[~mask] = 0
    return hwc


def _per_channel(hwc: np.ndarray, warp) -> np.ndarray:  # noqa: ANN001 - a cv2 call
    """Apply ``warp`` (array → array of the same layout) to all bands at once when OpenCV can."""
    bands = hwc.shape[-1]
    if bands == 1:
        return warp(hwc[..., 0])[..., np.newaxis]
    if bands <= _CV_MAX_CHANNELS:
        return warp(hwc)
    return np.stack([warp(np.ascontiguousarray(hwc[..., i])) for i in range(bands)], axis=-1)


def affine_resample(image: np.ndarray, mask: np.ndarray, matrix: np.ndarray, *,
                    interpolation: str = "cubic") -> tuple[np.ndarray, np.ndarray]:
    """Resample an image and its mask through a forward affine ``matrix``.

    Parameters
    ----------
    image
        ``(bands, rows, cols)`` pixel values.
    mask
        ``(rows, cols)`` bool valid-data mask.
    matrix
        3 × 3 forward matrix in pixel-edge coordinates (see
        :mod:`geosim.augment.geometry`); the output has the input's shape.
    interpolation
        ``"cubic"`` (default), ``"linear"`` or ``"nearest"`` for the image bands.

    Returns
    -------
    image, mask
        New arrays. The identity returns copies; whole-pixel permutations
        (flips, multiples of 90°, whole-pixel shifts) are done exactly by
        indexing, without interpolation.
    """
    _check(image, mask)
    if is_identity(matrix):
        return image.copy(), mask.copy()
    exact = permute_exact(image, mask, matrix, bands_last=False)
    if exact is not None:
        return exact
    out, out_mask = affine_resample_hwc(interleave(image), mask, matrix,
                                        interpolation=interpolation)
    return planar(out), out_mask


def affine_resample_hwc(hwc: np.ndarray, mask: np.ndarray, matrix: np.ndarray, *,
                        interpolation: str = "cubic", zero: bool = True
                        ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`affine_resample` of an interleaved ``(rows, cols, bands)`` image (new arrays).

    ``zero=False`` leaves the interpolated pixels where the mask is False as they are
    (not 0), for a caller whose next, pixel-wise stage zeroes them (one pass fewer).
    """
    if is_identity(matrix):
        return hwc.copy(), mask.copy()
    exact = permute_exact(hwc, mask, matrix, bands_last=True)
    if exact is not None:
        return exact
    rows, cols = mask.shape
    inv = to_cv2_inverse(matrix)
    flag = INTERPOLATION[interpolation] | cv2.WARP_INVERSE_MAP
    out = _per_channel(hwc, lambda a: cv2.warpAffine(a, inv, (cols, rows), flags=flag,
                                                     borderMode=cv2.BORDER_REPLICATE))
    out_mask = cv2.warpAffine(mask.view(np.uint8), inv, (cols, rows),
                              flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
    return (zero_invalid(out, out_mask) if zero else out), out_mask


def _axis_slices(sign: int, offset: int, n_out: int, n_src: int) -> tuple[slice, slice] | None:
    """Output and source slices along one axis for ``src = sign · out + offset`` (sign ±1)."""
    out = np.arange(n_out)
    src = sign * out + offset
    ok = np.flatnonzero((src >= 0) & (src < n_src))
    if ok.size == 0:
        return None
    o0, o1 = int(ok[0]), int(ok[-1]) + 1
    s0 = int(src[o0])
    if sign > 0:
        return slice(o0, o1), slice(s0, s0 + (o1 - o0))
    stop = s0 - (o1 - o0)
    return slice(o0, o1), slice(s0, stop if stop >= 0 else None, -1)


def permute_exact(image: np.ndarray, mask: np.ndarray, matrix: np.ndarray, *,
                  bands_last: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """Exact resampling (new arrays) when ``matrix`` only permutes whole pixels, else ``None``.

    Flips, multiples of 90° and whole-pixel shifts need no interpolation; they are
    done by indexing, in either layout (``bands_last``: ``(rows, cols, bands)``,
    else ``(bands, rows, cols)``), so a chain that only flips needs no layout change.
    """
    back = integer_permutation(matrix)
    if back is None:
        return None
    return _permute(image, mask, back, bands_last=bands_last)


def _permute(image: np.ndarray, mask: np.ndarray, back: np.ndarray, *, bands_last: bool = True
             ) -> tuple[np.ndarray, np.ndarray]:
    """Exact resampling when the backward index map ``back`` (2 × 3 int) permutes pixels.

    ``back`` maps output (col, row) to source (col, row). With an off-diagonal
    linear part (odd multiples of 90°) the source is read transposed.
    """
    rows, cols = mask.shape

    def at(r: slice, c: slice) -> tuple[slice, ...]:
        return (r, c) if bands_last else (slice(None), r, c)

    lin, t = back[:, :2], back[:, 2]
    if lin[0, 0] == 0:
        # source col = lin01·row + t0 and source row = lin10·col + t1: index the transposed
        # source (its axis 1 is the source col) with (output row, output col).
        src_img = image.transpose((1, 0, 2) if bands_last else (0, 2, 1))
        src_mask = mask.T
        sr, sc = int(lin[0, 1]), int(lin[1, 0])
        tr, tc = int(t[0]), int(t[1])
    else:
        src_img, src_mask = image, mask
        sr, sc = int(lin[1, 1]), int(lin[0, 0])
        tr, tc = int(t[1]), int(t[0])
    out = np.zeros(image.shape, image.dtype)  # C order
    out_mask = np.zeros_like(mask)
    along_r = _axis_slices(sr, tr, rows, src_mask.shape[0])
    along_c = _axis_slices(sc, tc, cols, src_mask.shape[1])
    if along_r is not None and along_c is not None:
        (o_r, s_r), (o_c, s_c) = along_r, along_c
        out[at(o_r, o_c)] = src_img[at(s_r, s_c)]
        out_mask[o_r, o_c] = src_mask[s_r, s_c]
    if bands_last:
        return zero_invalid(out, out_mask), out_mask
    if not out_mask.all():
        out *= out_mask  # broadcast over the leading band axis: one contiguous pass
    return out, out_mask


def remap_resample(image: np.ndarray, mask: np.ndarray, u_px: np.ndarray, v_px: np.ndarray,
                   *, interpolation: str = "cubic", matrix: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Resample through a backward displacement field: ``out(x) = in(x + d(x))``.

    Parameters
    ----------
    image, mask
        As :func:`affine_resample`.
    u_px, v_px
        ``(rows, cols)`` displacement, pixels, along x (columns) and y (rows),
        sampled at output pixel centres: output pixel ``(r, c)`` takes the input
        value at column ``c + u_px[r, c]`` and row ``r + v_px[r, c]``.
    interpolation
        ``"cubic"`` (default, the paper's), ``"linear"`` or ``"nearest"``.
    matrix
        Optional forward affine (3 × 3, pixel edges, as :func:`affine_resample`)
        applied *before* the field: the result is that of
        ``affine_resample(matrix)`` followed by this remap, in one interpolation
        instead of two (``out(x) = in(A⁻¹(x + d(x)))``). Pixels whose position in the
        intermediate (affine-only) image falls outside it are invalid, as they
        would be after the separate affine step.
    """
    _check(image, mask)
    out, out_mask = remap_resample_hwc(interleave(image), mask, u_px, v_px,
                                       interpolation=interpolation, matrix=matrix)
    return planar(out), out_mask


def remap_resample_hwc(hwc: np.ndarray, mask: np.ndarray, u_px: np.ndarray, v_px: np.ndarray,
                       *, interpolation: str = "cubic", matrix: np.ndarray | None = None,
                       zero: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`remap_resample` of an interleaved ``(rows, cols, bands)`` image (new arrays).

    ``zero``: as :func:`affine_resample_hwc`.
    """
    rows, cols = mask.shape
    if u_px.shape != (rows, cols) or v_px.shape != (rows, cols):
        raise ValueError(f"field shape {u_px.shape}/{v_px.shape} != image {(rows, cols)}")
    inv = None if matrix is None or is_identity(matrix) else to_cv2_inverse(matrix)
    out = np.empty_like(hwc)
    out_mask = np.empty_like(mask)
    # An all-valid mask remapped with nearest neighbour is 1 exactly where the rounded
    # source position is inside the image: one range test instead of a remap.
    inside_src = _nearest_inside_bounds(rows, cols) if mask.all() else None
    # (col, row) of every output pixel of a block of rows, one 2-channel float32 array
    # (OpenCV's point-map layout); the row channel is moved down block by block
    grid = np.empty((min(rows, REMAP_BLOCK_ROWS), cols, 2), np.float32)
    grid[..., 0] = np.arange(cols, dtype=np.float32)
    grid[..., 1] = np.arange(grid.shape[0], dtype=np.float32)[:, np.newaxis]
    for r0 in range(0, rows, REMAP_BLOCK_ROWS):
        r1 = min(rows, r0 + REMAP_BLOCK_ROWS)
        if r0:
            grid[..., 1] += np.float32(REMAP_BLOCK_ROWS)
        # Map for this block of output rows (bounded memory); the source is the whole
        # image. Positions x + d(x), then through the pending affine if any: a 2-channel
        # float map that OpenCV's remap takes as it is (it converts it to its fixed-point
        # form internally, as cv2.convertMaps would, for each band at once).
        xy = cv2.merge([u_px[r0:r1], v_px[r0:r1]])
        cv2.add(xy, grid[:r1 - r0], dst=xy)
        inside = None
        if inv is not None:
            # positions in the intermediate image -> source positions (OpenCV index frame)
            inside = cv2.inRange(xy, (-0.5, -0.5), (cols - 0.5, rows - 0.5))  # 0 / 255
            xy = cv2.transform(xy, inv)
        # remapped straight into the output rows (no block copy)
        block_mask = out_mask[r0:r1].view(np.uint8)
        if inside_src is not None:
            cv2.bitwise_and(cv2.inRange(xy, *inside_src), 1, dst=block_mask)  # 0 / 1
        else:
            cv2.remap(mask.view(np.uint8), xy, None, cv2.INTER_NEAREST, dst=block_mask,
                      borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if inside is not None:
            cv2.bitwise_and(block_mask, inside, dst=block_mask)  # (0 / 1) & (0 / 255)
        _remap_into(hwc, xy, out[r0:r1], INTERPOLATION[interpolation])
    return (zero_invalid(out, out_mask) if zero else out), out_mask


def _nearest_inside_bounds(rows: int, cols: int
                           ) -> tuple[tuple[float, float], tuple[float, float]]:
    """``cv2.inRange`` bounds of the float (x, y) positions that nearest-neighbour remap
    reads from inside a ``rows`` × ``cols`` image.

    OpenCV rounds a float map position to the nearest index, ties to even (tested):
    ``-0.5`` reads index 0, and ``n - 0.5`` reads index ``n - 1`` when ``n`` is odd but
    ``n`` (outside) when ``n`` is even, so the upper bound is then the float32 just below.
    """
    def upper(n: int) -> float:
        hi = np.float32(n - 0.5)
        return float(hi if n % 2 else np.nextafter(hi, np.float32(-np.inf)))

    return (-0.5, -0.5), (upper(cols), upper(rows))


def _remap_into(hwc: np.ndarray, xy: np.ndarray, dst: np.ndarray, flag: int) -> None:
    """``cv2.remap`` of every band of ``hwc`` through the 2-channel map ``xy`` into ``dst``."""
    bands = hwc.shape[-1]
    if bands <= _CV_MAX_CHANNELS:
        src = hwc[..., 0] if bands == 1 else hwc
        cv2.remap(src, xy, None, flag, dst=dst[..., 0] if bands == 1 else dst,
                  borderMode=cv2.BORDER_REPLICATE)
        return
    for i in range(bands):
        dst[..., i] = cv2.remap(np.ascontiguousarray(hwc[..., i]), xy, None, flag,
                                borderMode=cv2.BORDER_REPLICATE)
