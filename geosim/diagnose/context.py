"""The contexts :func:`~geosim.diagnose.engine.diagnose_arrays` hands to its stages.

Where and over what the blur is fitted travels through the diagnosis as one record
(:class:`FitWindow`), built once by the orchestrator and read-only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FitWindow"]


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
