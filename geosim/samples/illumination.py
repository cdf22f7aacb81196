"""Direct sun and diffuse sky light on surfaces, normalised to sunlit flat ground.

Radiance of a Lambertian surface with albedo ρ and unit normal n is
``ρ · (E_sky · V + E_sun · max(0, n·s) · (1 − S))`` with sky-view factor V and
shadow coverage S. Dividing by flat sunlit ground, ``E_sky + E_sun · sin(el)``,
gives a factor that is 1 for sunlit flat ground, so albedo rasters can hold the
digital numbers of sunlit flat ground.

The sky-to-sun irradiance ratio per band, ``SKY_RATIO = E_sky / E_sun``, was set
from shadow contrast measured on a real nadir drone frame of stock on NSW
pasture (``../shared/realdata/cattle_frame_nsw.jpg``): shadow / sunlit grass =
0.298, 0.307, 0.368 (R, G, B), taken at an assumed sun elevation of 35°, gives
ratio = r · sin(35°) / (1 − r). Blue skylight makes shadows bluer and, at a low
sun, less dark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from geosim.samples.sun import SunPosition

SKY_RATIO = np.array([0.244, 0.254, 0.334], dtype=np.float32)


@dataclass(frozen=True)
class Illumination:
    """Sun and sky for one acquisition.

    Attributes
    ----------
    sun
        Solar position.
    sky_ratio
        Diffuse sky / direct sun irradiance per band (R, G, B), dimensionless.
    """

    sun: SunPosition
    sky_ratio: np.ndarray = field(default_factory=lambda: SKY_RATIO.copy())

    @property
    def sin_el(self) -> float:
        """Sine of the solar elevation."""
        return math.sin(math.radians(self.sun.elevation_deg))

    def shadow_factor(self) -> np.ndarray:
        """(3,) radiance of fully shadowed flat ground relative to sunlit flat ground."""
        return (self.sky_ratio / (self.sky_ratio + self.sin_el)).astype(np.float32)

    def ground_factor(self, shadow: np.ndarray) -> np.ndarray:
        """(3, …) factor for flat ground with shadow coverage ``shadow`` in [0, 1]."""
        k = self.shadow_factor()[:, None, None]
        return (1.0 - shadow[None] * (1.0 - k)).astype(np.float32)

    def surface_factor(self, n_east: np.ndarray, n_north: np.ndarray, n_up: np.ndarray, *,
                       shadow: np.ndarray | float = 0.0, sky_view: np.ndarray | float = 1.0
                       ) -> np.ndarray:
        """(3, …) factor for a tilted surface with unit normal (east, north, up).

        Parameters
        ----------
        n_east, n_north, n_up
            Unit normal components on the map grid.
        shadow
            Coverage of cast shadow on the surface, [0, 1].
        sky_view
            Fraction of the sky the surface sees, [0, 1].
        """
        s = self.sun.vector()
        cos_i = np.maximum(0.0, n_east * s[0] + n_north * s[1] + n_up * s[2])
        direct = cos_i * (1.0 - np.asarray(shadow, dtype=np.float32))
        sky = np.asarray(sky_view, dtype=np.float32) * 0.5 * (1.0 + n_up)
        r = self.sky_ratio.reshape(3, *([1] * np.ndim(direct)))
        return ((r * sky + direct) / (r + self.sin_el)).astype(np.float32)
