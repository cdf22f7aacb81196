"""geosim: UAV surveys of cattle paddocks to aligned, labelled patch pairs and
calibrated 0.5 m satellite simulations, all in map coordinates."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("geosim")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from geosim.errors import GeosimError  # noqa: E402

__all__ = ["GeosimError", "__version__"]
