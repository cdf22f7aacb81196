"""A flight's pixels as the diagnosis reads them (``geosim.diagnose.grids.diagnose_pixels``):
what it refuses, and how."""

from __future__ import annotations

import numpy as np
import pytest


def _strip(rows_fine: int):
    """A flight imaging a (rows_fine / 10) × 60 px strip of its 80 px window, whose scene
    is unrelated to the UAV image (everything reads as changed)."""
    from affine import Affine
    from rasterio.crs import CRS

    from geosim.diagnose.grids import FlightPixels

    rng = np.random.default_rng(2)
    uav = rng.normal(120, 20, (3, 800, 800)).astype(np.float32)
    uav_valid = np.zeros((800, 800), bool)
    uav_valid[100:100 + rows_fine, 100:700] = True
    sat = rng.normal(120, 5, (3, 80, 80)).round()
    return FlightPixels.of_arrays(uav, sat, sat_transform=Affine(0.5, 0, 0, 0, -0.5, 0),
                                  crs=CRS.from_epsg(32755), phi=10, uav_valid=uav_valid,
                                  q_base=1.5)


def test_a_flight_too_small_to_diagnose_is_refused_by_name():
    """A 22 × 60 px strip holds no whole 32 px block: one clear DiagnosisError (what is
    too small, what to give), not a numerical error from deep inside (a strip with no
    whole Welch block made the shift estimate raise ValueError)."""
    from geosim.diagnose.grids import diagnose_pixels
    from geosim.errors import DiagnosisError

    with pytest.raises(DiagnosisError,
                       match=r"no fully valid 32×32 block .*give a larger common extent"):
        diagnose_pixels(_strip(220), phi=10)


def test_a_small_changed_strip_is_measured_in_the_blocks_its_extent_holds():
    """A 40 × 60 px strip holds two whole 32 px blocks and 24 of 16 px. Its changes used to
    be tapered at 32 px, leaving 2 blocks, and the flight was refused ("only 2 fully valid
    32×32 blocks", as 12 of 128 development flights with moved objects were, round 38);
    the block size now follows the extent, so it is diagnosed in 16 px blocks."""
    from geosim.diagnose.grids import diagnose_pixels

    diagnosis = diagnose_pixels(_strip(400), phi=10)
    assert diagnosis.summary["settings"]["block_px"] == 16
