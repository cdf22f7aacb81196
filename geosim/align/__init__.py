"""Image registration kernels (pure numpy / OpenCV / SciPy, no file I/O).

Conventions shared by all of them (details in :mod:`geosim.align.phasecorr` and
:mod:`geosim.align.fourier_mellin`): pixel coordinates ``(x, y)`` = (column,
row), rows growing downward, pixel centres at integer coordinates; shifts are
the position of the moving content relative to the reference; transforms map
reference pixels to moving pixels; rotation is counter-clockwise as displayed.
"""

from geosim.align.fourier_mellin import (
    SimilarityTransform,
    register_similarity,
    similarity_matrix,
)
from geosim.align.local import LocalShiftField, local_shift_field
from geosim.align.phasecorr import DEFAULT_MIN_CONFIDENCE, PhaseCorrelation, phase_correlate
from geosim.align.refine import fit_similarity

__all__ = [
    "DEFAULT_MIN_CONFIDENCE",
    "LocalShiftField",
    "PhaseCorrelation",
    "SimilarityTransform",
    "fit_similarity",
    "local_shift_field",
    "phase_correlate",
    "register_similarity",
    "similarity_matrix",
]
