"""How well a model explains a JPEG'd scene, read through the JPEG's own quantisation.

A JPEG stores each 8×8 block's luma DCT coefficient k as the index j = round(x / t_k) of
the coefficient x it was given, t_k the step; the decoded scene's coefficient j·t_k says
only that x lay in [(j − ½) t_k, (j + ½) t_k). The high frequencies where a blur differs
from a wider optical PSF are mostly quantised to j = 0 — but "|x| < t_k / 2" is a statement
about the model as well: a model that keeps more high-frequency contrast than the scene
had puts its coefficients outside the interval more often. The transfer fits see the JPEG
only through a linearised transfer measured where the JPEG passes signal
(:mod:`geosim.diagnose.jpeg_transfer`), and under strong quantisation that left a 2.4 px
smear at quality 53 untestable (development c14; Q took it up, 2.97 → 3.23).

:func:`log_likelihood` is the exact interval-censored likelihood of the scene's indices
given a model's pre-JPEG luma coefficients μ: P(j | μ) = Φ(((j + ½) t − μ)/s) −
Φ(((j − ½) t − μ)/s), with s² = σ² + the codec's arithmetic variance; σ² (noise and model
misfit, luma DN²) is profiled over a grid, and a small uniform outlier part keeps one
misfit coefficient from deciding (as :mod:`geosim.diagnose.jpeg_noise`, whose noise
estimate is the same likelihood with a gain per coefficient). Coefficients with step 1
(no quantisation) enter as Gaussians, the DC and coefficients quantised by the coarsest
step (always 0) not at all. The steps are read from the scene's own lattice
(:func:`~geosim.diagnose.jpeg_noise.lattice_steps`): no encoder's table is assumed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from geosim.diagnose.jpeg_noise import (
    ARITHMETIC_VAR_DN2,
    MAX_STEP,
    OUTLIER_FRACTION,
    block_dct,
    lattice_steps,
    whole_blocks,
)

__all__ = ["CensoredBlocks", "censored_blocks", "log_likelihood", "VAR_GRID_DN2"]

#: misfit variances (luma DN²) over which the likelihood is profiled
VAR_GRID_DN2 = np.concatenate([[0.0], np.geomspace(0.05, 400.0, 24)])
#: the outlier part's spread, in units of a coefficient's standard deviation over blocks
OUTLIER_SPREAD_SD = 6.0


@dataclass(frozen=True)
class CensoredBlocks:
    """The real scene's quantised luma coefficients on its JPEG block grid.

    Attributes
    ----------
    offset_px
        (row, col) phase of the block grid, px.
    mask
        Bool (rows, cols): the blocks used lie wholly inside it.
    index
        (n_blocks, n_coef) the scene's bin index j of each used coefficient (quantised
        coefficients) or its value (coefficients of step 1), coefficient units.
    steps
        (n_coef,) quantisation step of each used coefficient (1: not quantised).
    coef
        (n_coef,) which of the 64 row-major DCT coefficients each column is.
    outlier_density
        (n_coef,) the outlier part's probability per bin (or density per unit, step 1).
    block_col
        (n_blocks,) column of each block's centre, px (for spatial folds).
    """

    offset_px: tuple[int, int]
    mask: np.ndarray
    index: np.ndarray
    steps: np.ndarray
    coef: np.ndarray
    outlier_density: np.ndarray
    block_col: np.ndarray

    @property
    def n_blocks(self) -> int:
        """Number of 8×8 blocks read."""
        return int(self.index.shape[0])

    def model_coefficients(self, model_grey: np.ndarray) -> np.ndarray:
        """(n_blocks, n_coef) the used DCT coefficients of ``model_grey`` (luma, DN)."""
        return block_dct(model_grey, self.offset_px, self.mask)[:, self.coef]


def censored_blocks(real_grey: np.ndarray, offset_px: tuple[int, int], mask: np.ndarray
                    ) -> CensoredBlocks:
    """The :class:`CensoredBlocks` of ``real_grey`` (the scene's luma, BT.601 as the
    JPEG's Y) on the block grid at ``offset_px`` (row, col), blocks wholly in ``mask``."""
    mask = np.asarray(mask, bool)
    cr = block_dct(real_grey, offset_px, mask)
    steps = lattice_steps(cr) if cr.shape[0] else np.zeros(64)
    use = (steps >= 1) & (steps < MAX_STEP)
    use[0] = False                       # DC: the level shift and the radiometry's offset
    coef = np.flatnonzero(use)
    t = steps[coef]
    x = cr[:, coef]
    index = np.where(t > 1, np.rint(x / t), x)
    spread = OUTLIER_SPREAD_SD * np.std(x, axis=0) + t if x.size else t
    outlier = OUTLIER_FRACTION * np.where(t > 1, np.minimum(1.0, t / spread), 1.0 / spread)
    r0, c0 = int(offset_px[0]) % 8, int(offset_px[1]) % 8
    cols = c0 + 8.0 * np.nonzero(whole_blocks(mask, (r0, c0)))[1] + 4.0
    return CensoredBlocks((r0, c0), mask, index, t, coef, outlier, cols)


def log_likelihood(blocks: CensoredBlocks, model_coef: np.ndarray,
                   rows: np.ndarray | None = None) -> float:
    """Interval-censored log-likelihood (nats) of the scene's coefficients given the
    model's (``model_coef``, from :meth:`CensoredBlocks.model_coefficients`), maximised
    over the misfit variance :data:`VAR_GRID_DN2`; ``rows``: the blocks counted (None:
    all)."""
    j = blocks.index if rows is None else blocks.index[rows]
    mu = model_coef if rows is None else model_coef[rows]
    t = blocks.steps[np.newaxis, :]
    s = np.sqrt(VAR_GRID_DN2 + ARITHMETIC_VAR_DN2)[:, np.newaxis, np.newaxis]
    quantised = blocks.steps > 1
    total = np.zeros(VAR_GRID_DN2.size)
    if quantised.any():
        tq, jq, mq = t[:, quantised], j[:, quantised], mu[:, quantised]
        lo = ((jq - 0.5) * tq - mq)[np.newaxis] / s
        hi = ((jq + 0.5) * tq - mq)[np.newaxis] / s
        p = ndtr(hi) - ndtr(lo)
        out = blocks.outlier_density[quantised]
        total += np.sum(np.log((1.0 - OUTLIER_FRACTION) * p + out), axis=(1, 2))
    if (~quantised).any():
        d = (j[:, ~quantised] - mu[:, ~quantised])[np.newaxis] / s
        dens = np.exp(-0.5 * d * d) / (s * np.sqrt(2.0 * np.pi))
        out = blocks.outlier_density[~quantised]
        total += np.sum(np.log((1.0 - OUTLIER_FRACTION) * dens + out), axis=(1, 2))
    return float(np.max(total))
