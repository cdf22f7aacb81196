"""A flight's pixels as the diagnosis reads them (``geosim.diagnose.grids.diagnose_pixels``):
what it refuses, and how."""

from __future__ import annotations

import numpy as np
import pytest


def test_a_flight_too_small_to_diagnose_is_refused_by_name():
    """A flight imaging a 22 × 60 px strip of its 80 px window: one clear DiagnosisError
    (how many blocks, what to give), not a numerical error from deep inside."""
    from affine import Affine
    from rasterio.crs import CRS

    from geosim.diagnose.grids import FlightPixels, diagnose_pixels
    from geosim.errors import DiagnosisError

    rng = np.random.default_rng(2)
    uav = rng.normal(120, 20, (3, 800, 800)).astype(np.float32)
    uav_valid = np.zeros((800, 800), bool)
    uav_valid[100:320, 100:700] = True
    sat = rng.normal(120, 5, (3, 80, 80)).round()
    pixels = FlightPixels.of_arrays(uav, sat, sat_transform=Affine(0.5, 0, 0, 0, -0.5, 0),
                                    crs=CRS.from_epsg(32755), phi=10, uav_valid=uav_valid,
                                    q_base=1.5)
    with pytest.raises(DiagnosisError, match=r"only \d fully valid 32×32 blocks.*at least 8"):
        diagnose_pixels(pixels, phi=10)
