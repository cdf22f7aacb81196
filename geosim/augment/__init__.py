"""Pair augmentation: the paper's twelve functions, applied consistently to both
images of an aligned pair, with the YOLO boxes following the pixels.

Pure kernels live in :mod:`~geosim.augment.geometry`, :mod:`~geosim.augment.resample`,
:mod:`~geosim.augment.warp` and :mod:`~geosim.augment.photometric`; the functions and
their parameter draws in :mod:`~geosim.augment.functions`; the TOML-described pipeline in
:mod:`~geosim.augment.pipeline`; files in :mod:`~geosim.augment.io`; the local-warp
figure in :mod:`~geosim.augment.plot`.
"""

from geosim.augment.functions import FUNCTIONS, AugmentFunction
from geosim.augment.geometry import Boxes
from geosim.augment.pipeline import (
    AugImage,
    AugmentResult,
    AugmentStep,
    Pipeline,
    default_config_path,
    load_pipeline,
)

__all__ = ["FUNCTIONS", "AugImage", "AugmentFunction", "AugmentResult", "Boxes", "Pipeline",
           "AugmentStep", "default_config_path", "load_pipeline"]
