"""Solar position for rendering shadows.

The NOAA solar-position equations (after Meeus, *Astronomical Algorithms*),
accurate to about 0.01° in elevation and azimuth for 1950–2050, without
atmospheric refraction (under 0.1° above 15° elevation). Shadows on the map grid
need the sun's azimuth relative to *grid* north, which differs from true north by
the meridian convergence of the projection; :func:`grid_azimuth_deg` does that
conversion with pyproj.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SunPosition:
    """Where the sun is, seen from the ground.

    Attributes
    ----------
    azimuth_deg
        Azimuth clockwise from true north, degrees in [0, 360).
    elevation_deg
        Elevation above the horizon, degrees (no refraction).
    grid_azimuth_deg
        Azimuth clockwise from the map grid's north, degrees in [0, 360).
    """

    azimuth_deg: float
    elevation_deg: float
    grid_azimuth_deg: float

    def horizontal_unit(self) -> np.ndarray:
        """Unit vector (east, north) on the map grid pointing towards the sun."""
        a = math.radians(self.grid_azimuth_deg)
        return np.array([math.sin(a), math.cos(a)])

    def vector(self) -> np.ndarray:
        """Unit vector (east, north, up) on the map grid pointing towards the sun."""
        e = math.radians(self.elevation_deg)
        h = self.horizontal_unit() * math.cos(e)
        return np.array([h[0], h[1], math.sin(e)])

    def shadow_offset_m(self, height_m: float) -> np.ndarray:
        """Horizontal (east, north) shift of the shadow of a point ``height_m`` up, metres."""
        return -self.horizontal_unit() * height_m / math.tan(math.radians(self.elevation_deg))


def solar_position(when: dt.datetime, lon_deg: float, lat_deg: float) -> tuple[float, float]:
    """Solar azimuth and elevation (NOAA equations).

    Parameters
    ----------
    when
        Timezone-aware time of observation.
    lon_deg, lat_deg
        Observer longitude (east positive) and latitude (north positive), degrees.

    Returns
    -------
    azimuth_deg, elevation_deg
        Azimuth clockwise from true north in [0, 360) and elevation, degrees.
    """
    if when.tzinfo is None:
        raise ValueError("solar_position needs a timezone-aware datetime")
    utc = when.astimezone(dt.UTC)
    j2000 = dt.datetime(2000, 1, 1, 12, tzinfo=dt.UTC)
    jc = (utc - j2000).total_seconds() / 86400.0 / 36525.0  # Julian centuries since J2000
    l0 = (280.46646 + jc * (36000.76983 + jc * 0.0003032)) % 360.0
    m = 357.52911 + jc * (35999.05029 - 0.0001537 * jc)
    ecc = 0.016708634 - jc * (0.000042037 + 0.0000001267 * jc)
    mr = math.radians(m)
    centre = (math.sin(mr) * (1.914602 - jc * (0.004817 + 0.000014 * jc))
              + math.sin(2 * mr) * (0.019993 - 0.000101 * jc) + math.sin(3 * mr) * 0.000289)
    omega = math.radians(125.04 - 1934.136 * jc)
    app_long = math.radians(l0 + centre - 0.00569 - 0.00478 * math.sin(omega))
    eps0 = 23 + (26 + (21.448 - jc * (46.815 + jc * (0.00059 - jc * 0.001813))) / 60) / 60
    eps = math.radians(eps0 + 0.00256 * math.cos(omega))
    decl = math.asin(math.sin(eps) * math.sin(app_long))
    y = math.tan(eps / 2) ** 2
    l0r = math.radians(l0)
    eot_min = 4 * math.degrees(y * math.sin(2 * l0r) - 2 * ecc * math.sin(mr)
                               + 4 * ecc * y * math.sin(mr) * math.cos(2 * l0r)
                               - 0.5 * y * y * math.sin(4 * l0r)
                               - 1.25 * ecc * ecc * math.sin(2 * mr))
    minutes = utc.hour * 60 + utc.minute + utc.second / 60 + utc.microsecond / 6e7
    true_solar_min = (minutes + eot_min + 4 * lon_deg) % 1440
    hour_angle = math.radians(true_solar_min / 4 - 180)
    lat = math.radians(lat_deg)
    cos_zen = (math.sin(lat) * math.sin(decl)
               + math.cos(lat) * math.cos(decl) * math.cos(hour_angle))
    elevation = 90.0 - math.degrees(math.acos(max(-1.0, min(1.0, cos_zen))))
    azimuth = (math.degrees(math.atan2(math.sin(hour_angle),
                                       math.cos(hour_angle) * math.sin(lat)
                                       - math.tan(decl) * math.cos(lat))) + 180.0) % 360.0
    return azimuth, elevation


def grid_azimuth_deg(azimuth_deg: float, lon_deg: float, lat_deg: float, crs: str) -> float:
    """Convert an azimuth from true north to the grid north of a projected CRS.

    Steps 100 m along the azimuth on the ellipsoid and measures the direction of
    that step on the map grid (this includes the meridian convergence).
    """
    from pyproj import Geod, Transformer

    lon2, lat2, _ = Geod(ellps="WGS84").fwd(lon_deg, lat_deg, azimuth_deg, 100.0)
    to_map = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    x1, y1 = to_map.transform(lon_deg, lat_deg)
    x2, y2 = to_map.transform(lon2, lat2)
    return math.degrees(math.atan2(x2 - x1, y2 - y1)) % 360.0


def sun_for(when: dt.datetime, lon_deg: float, lat_deg: float, crs: str) -> SunPosition:
    """The sun's position at ``when`` over (lon, lat), with its azimuth on ``crs``'s grid."""
    az, el = solar_position(when, lon_deg, lat_deg)
    return SunPosition(azimuth_deg=az, elevation_deg=el,
                       grid_azimuth_deg=grid_azimuth_deg(az, lon_deg, lat_deg, crs))
