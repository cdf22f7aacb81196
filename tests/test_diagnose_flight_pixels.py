"""A flight's pixels as the diagnosis reads them (``geosim.diagnose.grids.diagnose_pixels``):
what it refuses, and how."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("rows_fine,match", [
    (220, r"no fully valid 32×32 block .*give a larger common extent"),
    (400, r"only \d fully valid 32×32 blocks.*at least 8"),
])
def test_a_flight_too_small_to_diagnose_is_refused_by_name(rows_fine, match):
    """A flight imaging a 22 (or 40) × 60 px strip of its 80 px window: one clear
    DiagnosisError (what is too small, what to give), not a numerical error from deep
    inside (a strip with no whole Welch block made the shift estimate raise ValueError)."""
    from affine import Affine
    from rasterio.crs import CRS

    from geosim.diagnose.grids import FlightPixels, diagnose_pixels
    from geosim.errors import DiagnosisError

    rng = np.random.default_rng(2)
    uav = rng.normal(120, 20, (3, 800, 800)).astype(np.float32)
    uav_valid = np.zeros((800, 800), bool)
    uav_valid[100:100 + rows_fine, 100:700] = True
    sat = rng.normal(120, 5, (3, 80, 80)).round()
    pixels = FlightPixels.of_arrays(uav, sat, sat_transform=Affine(0.5, 0, 0, 0, -0.5, 0),
                                    crs=CRS.from_epsg(32755), phi=10, uav_valid=uav_valid,
                                    q_base=1.5)
    with pytest.raises(DiagnosisError, match=match):
        diagnose_pixels(pixels, phi=10)
