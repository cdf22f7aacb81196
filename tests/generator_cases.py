"""Scenes from the independent generator (``benchmarks/diagnose_generator.py``, no geosim
code), rendered on synthetic ground and diagnosed blind as a user would (LV baseline)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.engine import Diagnosis, diagnose_arrays  # noqa: E402
from geosim.diagnose.grids import calibrate_q_lv  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.stage_inputs import Inputs, make_inputs  # noqa: E402
from geosim.physics.radiometry import luma  # noqa: E402
from tests.helpers import no_registration  # noqa: E402, F401 (re-exported)


def render_scene(truth: dict, q: float, seed: int, sat_px: int = 96,
                 variant: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(UAV image on the 0.05 m grid, real scene on the 0.5 m grid) of ``truth`` at ``q``:
    synthetic ground of ``sat_px`` product pixels plus a 12 px margin, seed ``seed``."""
    rng = np.random.default_rng(seed)
    ground = gen.synthetic_ground(rng, (sat_px + 24) * gen.PHI)
    return gen.render(ground, q, truth, rng, margin_px=12, variant=variant)


def scene_inputs(truth: dict, q: float, seed: int, sat_px: int = 96
                 ) -> tuple[Inputs, np.ndarray]:
    """(the diagnosis's :class:`Inputs` at baseline Q ``q``, the real scene) of
    :func:`render_scene`'s scene, for testing a stage on its own."""
    uav, real = render_scene(truth, q, seed, sat_px)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    return make_inputs(real, sim, q, None, None, None, 0.5), real


def diagnose_scene(truth: dict, q: float, seed: int, sat_px: int = 96,
                   variant: dict | None = None
                   ) -> tuple[dict[str, Any], float, float, Diagnosis]:
    """(claimed effects by name, the generator's spectral error of the baseline and of the
    refined simulation, both in whole DN, the diagnosis) of :func:`render_scene`'s scene."""
    uav, real = render_scene(truth, q, seed, sat_px, variant)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    valid = np.ones(real.shape[-2:], bool)
    q_base = calibrate_q_lv(sim, luma(real), valid)
    d = diagnose_arrays(real, sim, q_base=q_base, rng=np.random.default_rng(0), q_lo=0.7)
    claimed = {e["name"]: e for e in d.summary["effects"]}
    se_base = gen.spectral_error(np.rint(d.baseline), real)
    se_ref = gen.spectral_error(np.rint(d.refined), real)
    return claimed, se_base, se_ref, d


def diagnose_flight_scene(truth: dict, q: float, seed: int, flight: dict, sat_px: int = 96
                          ) -> tuple[dict[str, Any], float, float, Diagnosis]:
    """As :func:`diagnose_scene`, for the scene as a surveyed flight delivers it (the
    generator's real-flight form: ``flight`` as :func:`gen.draw_flight` draws it, the UAV
    image 0 outside its footprint) through the user's path
    (:func:`geosim.diagnose.grids.diagnose_pixels`); the spectral errors are over the
    blocks the flight imaged."""
    from affine import Affine
    from rasterio.crs import CRS

    from geosim.diagnose.grids import FlightPixels, diagnose_pixels

    rng = np.random.default_rng(seed)
    ground = gen.synthetic_ground(rng, (sat_px + 24) * gen.PHI)
    uav, real = gen.render(ground, q, truth, rng, margin_px=12, flight=flight)
    uav_valid = gen.footprint_mask(uav.shape[-1], flight)
    uav = np.where(uav_valid, uav, np.float32(0.0))
    pixels = FlightPixels.of_arrays(uav, real, sat_transform=Affine(0.5, 0, 0, 0, -0.5, 0),
                                    crs=CRS.from_epsg(32755), phi=gen.PHI,
                                    uav_valid=uav_valid)
    d = diagnose_pixels(pixels, phi=gen.PHI)
    claimed = {e["name"]: e for e in d.summary["effects"]}
    r, c = real.shape[-2:]
    pv = uav_valid[:r * gen.PHI, :c * gen.PHI].reshape(r, gen.PHI, c, gen.PHI).all(axis=(1, 3))
    se_base = gen.spectral_error(np.rint(d.baseline), real, valid=pv)
    se_ref = gen.spectral_error(np.rint(d.refined), real, valid=pv)
    return claimed, se_base, se_ref, d
