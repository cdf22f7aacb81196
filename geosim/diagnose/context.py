"""The contexts :func:`~geosim.diagnose.engine.diagnose_arrays` hands to its stages.

Three groups of values travel together through the diagnosis: where and over what the
blur is fitted (:class:`FitWindow`), how a refined simulation is judged against the real
scene (:class:`EvalContext`) and the scene changes the final pass found
(:class:`ChangedRegions`). Each is built once by the orchestrator and is read-only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from geosim.diagnose import locate
from geosim.diagnose.spectra import block_origins, spectral_error
from geosim.diagnose.stage_inputs import greys

__all__ = ["FitWindow", "EvalContext", "ChangedRegions", "whole_extents"]


@dataclass(frozen=True, eq=False)
class FitWindow:
    """Where the blur is fitted, over which Q range, with which candidate effects.

    Attributes
    ----------
    mask : numpy.ndarray
        Bool (rows, cols) on the 0.5 m grid: valid pixels outside the first pass's
        changed regions; the Welch blocks of the fit lie inside it.
    q_lo, q_hi : float
        Bottom and top of the Q grid of exact simulations (Q of the paper's model,
        dimensionless). :func:`~geosim.diagnose.stage_blur.select_with_q_room` may extend
        the top for one selection; the window itself does not change.
    candidates : tuple of str
        Names of the blur effects forward selection may add.
    q_starts : tuple of float
        Starting values of Q for the transfer fits (dimensionless): the baseline Q clipped
        to ``[q_lo, q_hi]``, and 1.5.
    """

    mask: np.ndarray
    q_lo: float
    q_hi: float
    candidates: tuple[str, ...]
    q_starts: tuple[float, float]


@dataclass(frozen=True, eq=False)
class EvalContext:
    """How a refined simulation is judged against the real scene after the fit.

    Attributes
    ----------
    mask : numpy.ndarray
        Bool (rows, cols) on the 0.5 m grid: the evaluation pixels, where both images show
        the same scene (the final pass's inner mask outside every changed region); RMSEs
        are taken over it.
    origins : list of tuple of int
        (row, col) origins, pixels, of the Welch blocks of the spectral error: the whole
        blocks inside ``mask`` (the fit's blocks when fewer than 4 fit).
    block_px : int
        Side of the Welch blocks, pixels.
    real_grey : numpy.ndarray
        Grey level (luma) of the real scene, (rows, cols), DN.
    noise_seed : int
        Seed of the refined simulation's noise realisation (realisation k of a noisy
        model uses ``noise_seed + k``).
    """

    mask: np.ndarray
    origins: list[tuple[int, int]]
    block_px: int
    real_grey: np.ndarray
    noise_seed: int

    def spectral_error(self, img: np.ndarray | list[np.ndarray]) -> float:
        """Spectral error of ``img`` against the real scene on :attr:`origins`
        (dimensionless); a list of images (noise realisations) by their mean Welch power.

        Parameters
        ----------
        img : numpy.ndarray or list of numpy.ndarray
            Bands-first or grey image(s) on the 0.5 m grid, DN.
        """
        return spectral_error(greys(img), self.real_grey, block_px=self.block_px,
                              origins=self.origins)


#: fewest whole Welch blocks a spectral error is taken over
MIN_WHOLE_BLOCKS = 4


def whole_extents(ev: EvalContext, valid: np.ndarray, block_sizes_px: Sequence[int]
                  ) -> list[EvalContext]:
    """``ev`` judged over every valid block (the changed regions included), once for each
    distinct size in ``block_sizes_px`` (pixels, in that order) that fits at least
    :data:`MIN_WHOLE_BLOCKS` whole blocks in ``valid``.

    Where scene changes leave the fit too few whole blocks it works on 16 px blocks,
    whose frequency grid (1/16 cycle per pixel) leaves most of the 12 × 8 radial × angular
    bins of :func:`~geosim.diagnose.spectra.spectral_error` with one sample or none and
    sees nothing below 1/16: judged on those alone, a refinement passed as better while
    the spectrum on the configured 32 px blocks got worse (development c865, a control with
    Q refined 4.41 → 4.47: 0.069 → 0.040 on 16 px blocks, 0.070 → 0.071 on 32 px; c868, a
    false smear under JPEG: 0.149 → 0.123 against 0.113 → 0.146). The engine therefore
    judges the refined simulation as delivered on the configured blocks as well
    (:func:`~geosim.diagnose.engine.judge_refined`).
    """
    out = []
    for block_px in dict.fromkeys(block_sizes_px):
        origins = block_origins(valid.shape, block_px=block_px, valid=valid)
        if len(origins) >= MIN_WHOLE_BLOCKS:
            out.append(replace(ev, mask=valid, origins=origins, block_px=block_px))
    return out


@dataclass(frozen=True, eq=False)
class ChangedRegions:
    """The scene changes of the final pass (against the refined model).

    Attributes
    ----------
    regions : list of geosim.diagnose.locate.Region
        Regions of significant residual energy, each of kind ``scene_change`` or
        ``global``.
    labels : numpy.ndarray
        Int (rows, cols) label image of ``regions`` on the 0.5 m grid.
    inner : numpy.ndarray
        Bool (rows, cols): the valid mask eroded by 5 × 5 pixels, where the residual
        energy was measured.
    """

    regions: list[locate.Region]
    labels: np.ndarray
    inner: np.ndarray
