"""The sample site's satellite scene: the same world seen from orbit on another day.

The scene is 0.5 m RGB in WGS 84 / UTM zone 56S (EPSG:32756). It is rendered on
a grid ten times finer (0.05 m) in its own CRS, at the true position of every
pixel (EPSG:32756 → EPSG:28356 with pyproj), then passed through a physics chain
richer than the paper's model, at realistic magnitudes:

1. optics: circular-aperture diffraction OTF with Q near 1.5
   (:func:`geosim.physics.otf.optics_otf`);
2. atmospheric blur: turbulence / adjacency MTF ``exp(−(f/f0)^(5/3))``
   (:func:`~geosim.physics.otf.atmospheric_otf`);
3. motion smear: a linear smear of under a satellite pixel along one direction
   (:func:`~geosim.physics.otf.motion_otf`);
4. detector integration: each 0.5 m detector averages its whole footprint — the
   10×10 block mean of the fine grid, identical to the box transfer function
   :func:`~geosim.physics.otf.detector_otf` with ``pitch_px = 1`` followed by
   sampling at the pixel centres;
5. haze: per-band transmission < 1 and path radiance > 0, blue strongest
   (:func:`geosim.physics.radiometry.haze`);
6. sensor noise: variance ``gain_dn · signal + read_var_dn2``
   (:func:`~geosim.physics.radiometry.add_sensor_noise`), then 8-bit rounding;
7. misregistration: the file's georeference is off by ``shift_m``: a feature at
   true position p appears at ``p + shift_m`` when the file is read with its
   transform.

Noise raises the Laplacian variance and the extra blurs lower it, so the paper's
single blur metric calibrates an "apparent" Q well above the optical 1.5 while
the physics it absorbed stays hidden: the effects are concealed from it.

All parameters are in satellite pixels (0.5 m) and digital numbers.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np
from affine import Affine
from pyproj import Transformer

from geosim.physics.otf import (
    apply_transfer,
    atmospheric_otf,
    compose,
    motion_otf,
    optics_otf,
)
from geosim.physics.radiometry import add_sensor_noise, haze
from geosim.samples.render_grid import RenderGrid, fit_affine

SAT_CRS = "EPSG:32756"
SAT_GSD_M = 0.5
FINE_FACTOR = 10


@dataclass(frozen=True)
class SatelliteChain:
    """The physics that made the satellite scene (units: satellite pixels, DN).

    Attributes
    ----------
    q
        Optical Q = λf/(Dp) of the circular aperture.
    detector_pitch_px
        Width of the detector's integrating box, satellite pixels.
    atmospheric_f0_cyc_per_px
        Atmospheric MTF scale f0, cycles per satellite pixel.
    motion_length_px, motion_direction_deg
        Smear length, satellite pixels, and direction clockwise from grid north in [0, 180).
    transmission, path_radiance_dn
        Haze per band (R, G, B): multiplicative transmission and additive path radiance, DN.
    noise_gain_dn, noise_read_var_dn2
        Noise variance = gain · signal + read variance (DN, DN²).
    shift_m
        Misregistration (east, north), metres.
    """

    q: float
    detector_pitch_px: float
    atmospheric_f0_cyc_per_px: float
    motion_length_px: float
    motion_direction_deg: float
    transmission: tuple[float, float, float]
    path_radiance_dn: tuple[float, float, float]
    noise_gain_dn: float
    noise_read_var_dn2: float
    shift_m: tuple[float, float]

    def effects(self) -> dict:
        """The chain in the effect vocabulary of the diagnosis (``truth.json``)."""
        return {
            "optics": {"q": self.q},
            "detector_integration": {"pitch_px": self.detector_pitch_px},
            "atmospheric_blur": {"f0_cyc_per_px": self.atmospheric_f0_cyc_per_px},
            "motion_smear": {"length_px": self.motion_length_px,
                             "direction_deg": self.motion_direction_deg},
            "haze": {"transmission": list(self.transmission),
                     "path_radiance_dn": list(self.path_radiance_dn)},
            "sensor_noise": {"gain_dn": self.noise_gain_dn,
                             "read_var_dn2": self.noise_read_var_dn2},
            "misregistration": {"shift_m": list(self.shift_m)},
        }


def draw_chain(rng: np.random.Generator) -> SatelliteChain:
    """Draw realistic chain parameters (see the module docstring)."""
    t_r = rng.uniform(0.90, 0.94)
    t_g = t_r - rng.uniform(0.02, 0.04)
    t_b = t_g - rng.uniform(0.04, 0.07)
    l_r = rng.uniform(5.0, 9.0)
    l_g = l_r + rng.uniform(2.0, 4.0)
    l_b = l_g + rng.uniform(5.0, 9.0)
    mag = rng.uniform(0.3, 0.9)
    ang = rng.uniform(0.0, 2 * math.pi)
    return SatelliteChain(
        q=round(rng.uniform(1.4, 1.6), 3),
        detector_pitch_px=1.0,
        atmospheric_f0_cyc_per_px=round(rng.uniform(0.9, 1.3), 3),
        motion_length_px=round(rng.uniform(0.6, 1.0), 3),
        motion_direction_deg=round(rng.uniform(0.0, 180.0), 2),
        transmission=(round(t_r, 3), round(t_g, 3), round(t_b, 3)),
        path_radiance_dn=(round(l_r, 2), round(l_g, 2), round(l_b, 2)),
        noise_gain_dn=round(rng.uniform(0.02, 0.04), 4),
        noise_read_var_dn2=round(rng.uniform(0.6, 1.4), 3),
        shift_m=(round(mag * math.sin(ang), 4), round(mag * math.cos(ang), 4)),
    )


@dataclass(frozen=True)
class SatelliteSpec:
    """Grid and chain of the satellite scene.

    Attributes
    ----------
    acquired
        Acquisition time.
    width, height
        Scene size, satellite pixels.
    transform
        Stated (file) transform in EPSG:32756, 0.5 m pixels.
    chain
        The physics chain.
    to_world
        Affine EPSG:32756 → EPSG:28356 fitted to pyproj over the scene.
    to_world_residual_m
        Largest difference between that affine and pyproj over the scene, metres.
    """

    acquired: dt.datetime
    width: int
    height: int
    transform: Affine
    chain: SatelliteChain
    to_world: Affine
    to_world_residual_m: float

    def fine_grid(self) -> RenderGrid:
        """The 0.05 m rendering grid: fine pixel → true EPSG:28356 coordinates."""
        fine = self.transform @ Affine.scale(1.0 / FINE_FACTOR)
        dx, dy = self.chain.shift_m
        # A feature at true p appears at p + shift: stated position q shows true q − shift.
        return RenderGrid(self.width * FINE_FACTOR, self.height * FINE_FACTOR,
                          self.to_world @ Affine.translation(-dx, -dy) @ fine)

    def world_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) in the satellite file of true EPSG:28356 points (with misregistration)."""
        inv_world = ~self.to_world
        xs = inv_world.a * x + inv_world.b * y + inv_world.c + self.chain.shift_m[0]
        ys = inv_world.d * x + inv_world.e * y + inv_world.f + self.chain.shift_m[1]
        inv = ~self.transform
        return inv.a * xs + inv.b * ys + inv.c, inv.d * xs + inv.e * ys + inv.f


def make_satellite_spec(rng: np.random.Generator, acquired: dt.datetime,
                        centre_world_xy: tuple[float, float], *, size_m: float = 180.0
                        ) -> SatelliteSpec:
    """Place the scene (snapped to whole 0.5 m pixels in EPSG:32756) and draw its chain."""
    chain = draw_chain(rng)
    to_sat = Transformer.from_crs("EPSG:28356", SAT_CRS, always_xy=True)
    cx, cy = to_sat.transform(*centre_world_xy)
    n = int(round(size_m / SAT_GSD_M))
    x0 = math.floor((cx - size_m / 2) / SAT_GSD_M) * SAT_GSD_M
    y1 = math.ceil((cy + size_m / 2) / SAT_GSD_M) * SAT_GSD_M
    transform = Affine(SAT_GSD_M, 0.0, x0, 0.0, -SAT_GSD_M, y1)
    to_world = Transformer.from_crs(SAT_CRS, "EPSG:28356", always_xy=True)
    fit, res = fit_affine(to_world, (x0 - 5, y1 - size_m - 5, x0 + size_m + 5, y1 + 5))
    return SatelliteSpec(acquired=acquired, width=n, height=n, transform=transform, chain=chain,
                         to_world=fit, to_world_residual_m=res)


class _CachedTransfer:
    """A transfer function evaluated once per frequency-grid shape (bands share it)."""

    def __init__(self, transfer):  # noqa: ANN001 - a TransferFunction
        self._transfer = transfer
        self._cache: dict[tuple, np.ndarray] = {}

    def __call__(self, fy: np.ndarray, fx: np.ndarray) -> np.ndarray:
        key = (fy.shape, fx.shape)
        if key not in self._cache:
            self._cache[key] = self._transfer(fy, fx).astype(np.float32)
        return self._cache[key]


def apply_chain(radiance_fine: np.ndarray, chain: SatelliteChain, rng: np.random.Generator
                ) -> np.ndarray:
    """Degrade fine-grid radiance (3, rows·10, cols·10) to the 8-bit satellite image.

    Returns
    -------
    numpy.ndarray
        (3, rows, cols) uint8.
    """
    phi = FINE_FACTOR
    transfer = _CachedTransfer(compose(
        lambda fy, fx: optics_otf(fy, fx, q=chain.q, phi=phi),
        lambda fy, fx: atmospheric_otf(fy, fx, f0_cyc_per_px=chain.atmospheric_f0_cyc_per_px / phi),
        lambda fy, fx: motion_otf(fy, fx, length_px=chain.motion_length_px * phi,
                                  direction_deg=chain.motion_direction_deg)))
    blurred = apply_transfer(radiance_fine.astype(np.float32, copy=False), transfer)
    bands, rows, cols = blurred.shape
    if abs(chain.detector_pitch_px - 1.0) > 1e-9:
        raise ValueError("the block-mean detector model needs detector_pitch_px = 1")
    detected = blurred.reshape(bands, rows // phi, phi, cols // phi, phi).mean(axis=(2, 4),
                                                                                  dtype=np.float64)
    hazy = haze(detected, transmission=chain.transmission, path_radiance_dn=chain.path_radiance_dn)
    noisy = add_sensor_noise(hazy, gain_dn=chain.noise_gain_dn,
                             read_var_dn2=chain.noise_read_var_dn2, rng=rng)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def satellite_truth(spec: SatelliteSpec) -> dict:
    """JSON-able description of the scene and its chain (for truth.json)."""
    t = spec.transform
    w = spec.to_world
    return {
        "crs": SAT_CRS,
        "acquired": spec.acquired.isoformat(),
        "width": spec.width, "height": spec.height,
        "gsd_m": SAT_GSD_M,
        "transform": [t.a, t.b, t.c, t.d, t.e, t.f],
        "render_fine_factor": FINE_FACTOR,
        # the fitted offsets (≈ 0.2 mm) and residual (nanometres) carry floating-point noise
        # of the fit that differs between CPUs in the micrometres: recorded to 0.1 mm and
        # 1 µm, so that the generator writes the same truth.json on every machine (the
        # rendering uses the unrounded fit)
        "epsg32756_to_epsg28356_affine": [round(w.a, 9), round(w.b, 9), round(w.c, 4) + 0.0,
                                          round(w.d, 9), round(w.e, 9), round(w.f, 4) + 0.0],
        "epsg32756_to_epsg28356_affine_max_residual_m": round(spec.to_world_residual_m, 6),
        "chain_order": ["optics", "atmospheric_blur", "motion_smear", "detector_integration",
                        "haze", "sensor_noise", "quantisation_uint8"],
        "effects": spec.chain.effects(),
        "units": "blur parameters in satellite pixels (0.5 m); radiometry in DN (0-255); "
                 "direction_deg clockwise from grid north in [0, 180); shift_m = (east, north) "
                 "metres by which features appear displaced in the file",
    }
