"""The exception hierarchy.

One root, :class:`GeosimError`; each subclass also inherits the builtin it is
closest to, so callers may catch either. Every message names the input, says
what is wrong and what to do. The CLI turns these into one line on stderr and
exit code 2.
"""

from __future__ import annotations


class GeosimError(Exception):
    """Root of every error geosim raises on purpose."""


class ConfigError(GeosimError, ValueError):
    """A site or pipeline configuration is invalid (unknown key, wrong type, bad value)."""


class InputFileError(GeosimError, FileNotFoundError):
    """A named input file does not exist or cannot be opened."""


class RasterError(GeosimError, ValueError):
    """A raster is unusable as given (no CRS, no georeference, unsupported dtype or bands)."""


class CRSError(GeosimError, ValueError):
    """A coordinate reference system is missing, unknown or unsuitable (e.g. not projected)."""


class ExtentError(GeosimError, ValueError):
    """Footprints do not overlap enough (empty or tiny common extent)."""


class AlignmentError(GeosimError, RuntimeError):
    """Registration failed or is not trustworthy (low confidence, no texture, no overlap)."""


class LabelError(GeosimError, ValueError):
    """A label file or label geometry is malformed (bad YOLO line, box outside its image)."""


class CalibrationError(GeosimError, RuntimeError):
    """Calibration could not bracket or find a solution."""


class DiagnosisError(GeosimError, RuntimeError):
    """Mismatch diagnosis could not be carried out on the given data."""


class OutputError(GeosimError, OSError):
    """An output cannot be written (exists and overwrite not allowed, unwritable folder)."""


class GeosimWarning(UserWarning):
    """Something geosim repaired or assumed that the user should check (e.g. a paddock
    polygon made valid)."""


class EngineError(GeosimError, RuntimeError):
    """The Dask cluster could not be started or reached, or a worker was lost."""
