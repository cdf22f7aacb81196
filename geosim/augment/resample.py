"""Resampling kernels: affine warps and displacement-field remaps of an image and its mask.

Images are bands-first ``(bands, rows, cols)``; masks are ``(rows, cols)`` bool
(True = valid). Image bands are interpolated bicubically (OpenCV, border
replicated so that no black fringe bleeds into valid pixels); the mask is
resampled with nearest neighbour and everything sampled from outside the input
is marked invalid. Invalid pixels are set to 0 in the output image. Pure
functions: nothing is modified in place.
"""

from __future__ import annotations

import cv2
import numpy as np

from geosim.augment.geometry import integer_permutation, is_identity, to_cv2_inverse

__all__ = ["affine_resample", "remap_resample", "INTERPOLATION"]

#: OpenCV interpolation flags by name.
INTERPOLATION = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR,
                 "cubic": cv2.INTER_CUBIC}

#: Output rows per block when remapping (bounds the memory of the coordinate maps).
REMAP_BLOCK_ROWS = 512

_CV2_DTYPES = {np.dtype(t) for t in (np.uint8, np.uint16, np.int16, np.float32, np.float64)}


def _check(image: np.ndarray, mask: np.ndarray) -> None:
    if image.ndim != 3:
        raise ValueError(f"image must be (bands, rows, cols), got shape {image.shape}")
    if mask.shape != image.shape[1:] or mask.dtype != bool:
        raise ValueError(f"mask must be bool {image.shape[1:]}, got {mask.dtype} {mask.shape}")
    if image.dtype not in _CV2_DTYPES:
        raise ValueError(f"unsupported image dtype {image.dtype}; use uint8, uint16, int16 "
                         "or float32")


def _finish(image: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if not mask.all():
        image *= mask  # invalid pixels → 0 (a broadcast multiply is faster than indexing)
    return image, mask


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
    perm = integer_permutation(matrix)
    if perm is not None:
        return _permute(image, mask, perm)
    rows, cols = mask.shape
    inv = to_cv2_inverse(matrix)
    flag = INTERPOLATION[interpolation] | cv2.WARP_INVERSE_MAP
    if image.shape[0] in (3, 4):
        # One multi-channel warp computes each pixel's source position once for all
        # bands (cheaper than band by band), by blocks of output rows so that each
        # block is split back into bands while it is in cache.
        out = np.empty_like(image)
        hwc = cv2.merge(list(image))
        for r0 in range(0, rows, REMAP_BLOCK_ROWS):
            r1 = min(rows, r0 + REMAP_BLOCK_ROWS)
            block_inv = inv.copy()
            block_inv[:, 2] += inv[:, 1] * r0  # output row r of the block is row r0 + r
            block = cv2.warpAffine(hwc, block_inv, (cols, r1 - r0), flags=flag,
                                   borderMode=cv2.BORDER_REPLICATE)
            cv2.split(block, [out[i, r0:r1] for i in range(out.shape[0])])  # in place
        del hwc
    else:
        out = np.empty_like(image)
        for i, band in enumerate(image):
            out[i] = cv2.warpAffine(band, inv, (cols, rows), flags=flag,
                                    borderMode=cv2.BORDER_REPLICATE)
    out_mask = cv2.warpAffine(mask.view(np.uint8), inv, (cols, rows),
                              flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(bool)
    return _finish(out, out_mask)


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


def _permute(image: np.ndarray, mask: np.ndarray, back: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Exact resampling when the backward index map ``back`` (2 × 3 int) permutes pixels.

    ``back`` maps output (col, row) to source (col, row). With an off-diagonal
    linear part (odd multiples of 90°) the source is read transposed.
    """
    rows, cols = mask.shape
    lin, t = back[:, :2], back[:, 2]
    if lin[0, 0] == 0:
        # source col = lin01·row + t0 and source row = lin10·col + t1: index the transposed
        # source (its axis 1 is the source col) with (output row, output col).
        src_img, src_mask = image.transpose(0, 2, 1), mask.T
        sr, sc = int(lin[0, 1]), int(lin[1, 0])
        tr, tc = int(t[0]), int(t[1])
    else:
        src_img, src_mask = image, mask
        sr, sc = int(lin[1, 1]), int(lin[0, 0])
        tr, tc = int(t[1]), int(t[0])
    out = np.zeros_like(image)
    out_mask = np.zeros_like(mask)
    along_r = _axis_slices(sr, tr, rows, src_mask.shape[0])
    along_c = _axis_slices(sc, tc, cols, src_mask.shape[1])
    if along_r is not None and along_c is not None:
        (o_r, s_r), (o_c, s_c) = along_r, along_c
        out[:, o_r, o_c] = src_img[:, s_r, s_c]
        out_mask[o_r, o_c] = src_mask[s_r, s_c]
    return _finish(out, out_mask)


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
    rows, cols = mask.shape
    if u_px.shape != (rows, cols) or v_px.shape != (rows, cols):
        raise ValueError(f"field shape {u_px.shape}/{v_px.shape} != image {(rows, cols)}")
    inv = None if matrix is None or is_identity(matrix) else to_cv2_inverse(matrix)
    out = np.empty_like(image)
    out_mask = np.empty_like(mask)
    # 3/4 bands: one multi-channel remap per block (source positions computed once; same bits)
    hwc = cv2.merge(list(image)) if image.shape[0] in (3, 4) else None
    col_idx = np.arange(cols, dtype=np.float32)[np.newaxis, :]
    for r0 in range(0, rows, REMAP_BLOCK_ROWS):
        r1 = min(rows, r0 + REMAP_BLOCK_ROWS)
        # Maps for this block of output rows (bounded memory); the source is the whole image.
        map_x = u_px[r0:r1].astype(np.float32, copy=True)
        map_x += col_idx
        map_y = v_px[r0:r1].astype(np.float32, copy=True)
        map_y += np.arange(r0, r1, dtype=np.float32)[:, np.newaxis]
        inside = None
        if inv is not None:
            # positions in the intermediate image -> source positions (OpenCV index frame),
            # one 2-channel map transformed in one pass
            xy = cv2.merge([map_x, map_y])
            inside = cv2.inRange(xy, (-0.5, -0.5), (cols - 0.5, rows - 0.5))  # 0 / 255
            map_x, map_y = cv2.split(cv2.transform(xy, inv))
        block_mask = cv2.remap(mask.view(np.uint8), map_x, map_y, cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if inside is not None:
            block_mask &= inside  # (0 / 1) & (0 / 255)
        out_mask[r0:r1] = block_mask.view(bool)
        if interpolation != "nearest":
            # Fixed-point maps: computed once, reused for every band.
            m1, m2 = cv2.convertMaps(map_x, map_y, cv2.CV_16SC2)
        else:
            m1, m2 = map_x, map_y
        if hwc is not None:
            block = cv2.remap(hwc, m1, m2, INTERPOLATION[interpolation],
                              borderMode=cv2.BORDER_REPLICATE)
            cv2.split(block, [out[i, r0:r1] for i in range(out.shape[0])])  # in place
            continue
        for i, band in enumerate(image):
            out[i, r0:r1] = cv2.remap(band, m1, m2, INTERPOLATION[interpolation],
                                      borderMode=cv2.BORDER_REPLICATE)
    return _finish(out, out_mask)
