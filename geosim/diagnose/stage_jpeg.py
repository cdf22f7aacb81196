"""Compression detection: block-edge steps of the residual (:func:`blockiness`), the JPEG's
quantisation lattice, the quality by moment matching (:func:`match_quality`), the IJG
step scale of a quality, and the JPEG's transfer linearised around a blurred model."""

from __future__ import annotations

import warnings

import numpy as np

from geosim.diagnose.jpeg_noise import MIN_LATTICE_GAIN, block_grid, lattice_evidence
from geosim.diagnose.jpeg_transfer import JpegTransfer, jpeg_transfer
from geosim.diagnose.model import CompressionFit, ForwardModel, Registration
from geosim.diagnose.noise import noise_dither
from geosim.diagnose.spectra import block_origins
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.diagnose.stage_radiometry import band_affine

__all__ = ["blockiness", "find_compression", "match_quality", "jpeg_linearised",
           "jpeg_step_scale", "jpeg_quality_for_scale", "MAX_CLAIMED_QUALITY",
           "MIN_BLOCK_RATIO", "MIN_BLOCK_Z"]

#: compression is claimed only below this JPEG quality (the top of the range is its null)
MAX_CLAIMED_QUALITY = 90
#: block-edge step test on the baseline residual (ratio to other phases and z-score, both
#: axes; tuned on the development half)
MIN_BLOCK_RATIO = 1.2
MIN_BLOCK_Z = 3.0


def blockiness(residual_grey: np.ndarray, mask: np.ndarray, *, period: int = 8
               ) -> dict[str, float]:
    """Excess of squared steps across block edges of size ``period``.

    For each phase p of columns (rows), the mean squared difference between
    neighbouring pixels across boundaries at c ≡ p (mod period); the phase with the
    largest mean is the candidate block edge. Returns the ratio to the mean of the other
    phases, a z-score from the spread of per-line means, the excess in DN², and the
    phases (row, col).
    """
    e = np.where(mask, residual_grey, 0.0)
    m2 = mask[:, 1:] & mask[:, :-1]
    dcol = np.where(m2, (e[:, 1:] - e[:, :-1]) ** 2, np.nan)   # step between c-1 and c
    m2r = mask[1:, :] & mask[:-1, :]
    drow = np.where(m2r, (e[1:, :] - e[:-1, :]) ** 2, np.nan)
    out: dict[str, float] = {}
    for axis, d in (("col", dcol), ("row", drow)):
        with warnings.catch_warnings():  # lines entirely outside the valid area are NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            line = np.nanmean(d, axis=0) if axis == "col" else np.nanmean(d, axis=1)
        idx = np.arange(1, line.size + 1)     # boundary index c (between c-1 and c)
        ok = np.isfinite(line)
        means = np.array([np.mean(line[ok & (idx % period == p)]) for p in range(period)])
        p = int(np.nanargmax(means))
        others = line[ok & (idx % period != p)]
        at = line[ok & (idx % period == p)]
        ratio = float(means[p] / max(np.mean(others), 1e-12))
        z = float((np.mean(at) - np.mean(others)) / max(np.std(others) / np.sqrt(at.size),
                                                         1e-12))
        out[f"{axis}_ratio"] = ratio
        out[f"{axis}_z"] = z
        out[f"{axis}_phase"] = p
        out[f"{axis}_excess_dn2"] = float(np.mean(at) - np.mean(others))
    return out


def find_compression(inp: Inputs, reg: Registration, model_img: np.ndarray | None = None
                     ) -> CompressionFit | None:
    """8×8 block steps in the baseline residual; the quality whose re-encoding gives the
    model as many block-edge steps as the real scene has (moment matching: robust to the
    blur misfit that dominates a residual-based criterion before the blur is fitted).

    ``model_img``: test against this (refined, uncompressed) model instead of the baseline
    — a blur misfit of the baseline can drown the block steps."""
    ref = reg.move(inp.base) if model_img is None else model_img
    base_aff = band_affine(ref, inp.real, inp.valid)
    blk = blockiness(grey(inp.real - base_aff), inp.valid)
    if not (min(blk["row_ratio"], blk["col_ratio"]) > MIN_BLOCK_RATIO
            and min(blk["row_z"], blk["col_z"]) > MIN_BLOCK_Z):
        return None
    # the JPEG's own trace: its DCT coefficients on a quantisation lattice, on the block
    # grid where they lie best (the step phase can be off by a few px under a blur misfit)
    offset = block_grid(inp.grey, inp.valid,
                        (int(blk["row_phase"]) % 8, int(blk["col_phase"]) % 8))
    if lattice_evidence(inp.grey, offset, inp.valid) < MIN_LATTICE_GAIN:
        return None  # steps without the JPEG's quantisation lattice: a structured residual
    quality = match_quality(inp, base_aff, offset)
    if quality > MAX_CLAIMED_QUALITY:  # at the null end of its range: no compression shown
        return None
    return CompressionFit(int(quality), offset, blk)


def match_quality(inp: Inputs, model_aff: np.ndarray, offset: tuple[int, int],
                  coarse_grid: tuple[int, ...] = (10, 20, 30, 40, 50, 60, 70, 80, 90, 95),
                  fine_step: int = 2) -> int:
    """The JPEG quality whose re-encoding of ``model_aff`` (an uncompressed model, matched
    to the scene's radiometry) gives as much block-edge step energy as the real scene.

    The step energy a quality leaves grows with the content's high-frequency power, so
    the answer depends on the model's sharpness: a model sharper than the scene (the LV
    baseline under JPEG) needs a higher quality to match (see
    :func:`~geosim.diagnose.stage_jpeg_refit.joint_jpeg_blur`)."""
    def excess(img_grey: np.ndarray) -> float:
        b = blockiness(img_grey, inp.valid)
        return max(b["row_excess_dn2"] + b["col_excess_dn2"], 1e-6)

    target = excess(inp.grey)

    def mismatch(qual: int) -> float:
        m = CompressionFit(qual, offset, {}).apply(model_aff)
        return abs(np.log(excess(grey(m)) / target))

    coarse = min(coarse_grid, key=mismatch)
    fine = list(range(max(5, coarse - 8), min(100, coarse + 9), fine_step))
    return int(min(fine, key=mismatch))


def jpeg_linearised(inp: Inputs, ref: ForwardModel, fit_mask: np.ndarray
                    ) -> JpegTransfer | None:
    """The JPEG of ``ref.compression`` linearised around ``ref`` (blurred, matched to the
    scene's radiometry): its coherent transfer on the scene's blocks; with noise claimed
    in ``ref``, of the JPEG of ``ref`` plus noise realisations (the noise dithers the
    quantisation)."""
    if ref.compression is None:
        return None
    img = band_affine(ref.without(compression=None, seam=None).blurred(inp.simulate),
                      inp.real, inp.valid)
    origins = block_origins(inp.valid.shape, block_px=inp.block_px, valid=fit_mask)
    if len(origins) < 4:
        origins = block_origins(inp.valid.shape, block_px=inp.block_px, valid=inp.valid)
    return jpeg_transfer(img, ref.compression.apply, origins, inp.block_px, grey,
                         dither=noise_dither(ref.noise))


def jpeg_step_scale(quality: int) -> float:
    """IJG quantisation-table scale (percent of the base tables) of a JPEG quality."""
    q = min(max(int(quality), 1), 100)
    return 5000.0 / q if q < 50 else 200.0 - 2.0 * q


def jpeg_quality_for_scale(scale: float) -> int:
    """Inverse of :func:`jpeg_step_scale` (nearest whole quality, 1–100)."""
    q = 5000.0 / scale if scale > 100.0 else (200.0 - scale) / 2.0
    return int(np.clip(round(q), 1, 100))
