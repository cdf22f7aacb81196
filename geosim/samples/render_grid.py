"""Where each pixel of a rendered image looks on the ground.

A :class:`RenderGrid` maps pixel coordinates to *true* map coordinates (the
world's CRS, EPSG:28356 for the sample site): an affine part (the image's true
georeference, including any georeferencing error relative to what its file
states) and optional :class:`LocalWarp` displacements (stitching artefacts).
The renderer evaluates the world at these coordinates, so a flight with a
georeferencing error or a warp is a rendering of the same world through a
different mapping.

Pixel coordinates follow rasterio: ``(col, row)`` of a pixel's outer corner,
pixel centres at ``+0.5``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from affine import Affine


@dataclass(frozen=True)
class LocalWarp:
    """A smooth local displacement of image content, as mosaicking software makes
    near tall objects at the edge of a survey.

    The pixel at ``p`` shows what the undistorted image shows at ``p + d(p)``, with
    ``d(p) = g(p) · (amplitude_px · (cos a, sin a) + swirl_px · (p − c)⊥ / sigma_px)``
    and ``g(p) = exp(−|p − c|² / (2 sigma_px²))`` (``(col, row)`` pixel units,
    ``a = direction_rad`` measured from the +col axis towards +row).

    Attributes
    ----------
    centre_px
        (col, row) centre of the warp, pixels.
    sigma_px
        Gaussian radius of the warp, pixels.
    amplitude_px
        Peak translation, pixels.
    direction_rad
        Direction of the translation in the pixel frame (+col towards +row), radians.
    swirl_px
        Peak rotational component, pixels.
    """

    centre_px: tuple[float, float]
    sigma_px: float
    amplitude_px: float
    direction_rad: float
    swirl_px: float = 0.0

    def displacement(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (dcol, drow) in pixels at pixel coordinates (col, row)."""
        dc = col - self.centre_px[0]
        dr = row - self.centre_px[1]
        g = np.exp(-(dc * dc + dr * dr) / (2.0 * self.sigma_px**2))
        tx = self.amplitude_px * math.cos(self.direction_rad)
        ty = self.amplitude_px * math.sin(self.direction_rad)
        k = self.swirl_px / self.sigma_px
        return g * (tx - k * dr), g * (ty + k * dc)

    def reach_px(self) -> float:
        """Radius beyond which the displacement is below 0.01 px."""
        peak = abs(self.amplitude_px) + abs(self.swirl_px)
        if peak <= 0.01:
            return 0.0
        return self.sigma_px * math.sqrt(2.0 * math.log(peak / 0.01)) + 1.0

    def max_displacement_px(self) -> float:
        """Upper bound of |d|, pixels."""
        return abs(self.amplitude_px) + abs(self.swirl_px)


@dataclass(frozen=True)
class RenderGrid:
    """A raster grid and the true map position of each of its pixels.

    Attributes
    ----------
    width, height
        Raster size, pixels.
    pixel_to_map
        Affine from (col, row) pixel coordinates to true map coordinates, metres.
    warps
        Local content displacements applied before the affine.
    """

    width: int
    height: int
    pixel_to_map: Affine
    warps: tuple[LocalWarp, ...] = field(default_factory=tuple)

    @property
    def pixel_size_m(self) -> float:
        """Side of a (square-equivalent) pixel on the ground, metres."""
        a = self.pixel_to_map
        return math.sqrt(abs(a.a * a.e - a.b * a.d))

    @property
    def jacobian(self) -> np.ndarray:
        """2×2 matrix d(x, y)/d(col, row), metres per pixel (warps ignored)."""
        a = self.pixel_to_map
        return np.array([[a.a, a.b], [a.d, a.e]])

    def coords(self, row0: int, row1: int, col0: int, col1: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """True map coordinates (x, y) of the pixel centres of a window, float64.

        Parameters
        ----------
        row0, row1, col0, col1
            Window bounds (end exclusive), pixels.
        """
        cols = np.arange(col0, col1, dtype=np.float64) + 0.5
        rows = np.arange(row0, row1, dtype=np.float64) + 0.5
        cc, rr = np.meshgrid(cols, rows)
        for w in self.warps:
            reach = w.reach_px()
            if (reach == 0.0 or col1 < w.centre_px[0] - reach or col0 > w.centre_px[0] + reach
                    or row1 < w.centre_px[1] - reach or row0 > w.centre_px[1] + reach):
                continue
            dc, dr = w.displacement(cc, rr)
            cc = cc + dc
            rr = rr + dr
        a = self.pixel_to_map
        return a.a * cc + a.b * rr + a.c, a.d * cc + a.e * rr + a.f

    def map_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) pixel coordinates of true map points, ignoring warps."""
        inv = ~self.pixel_to_map
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        return inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f

    def window_for(self, points_xy: np.ndarray, *, margin_px: float = 2.0
                   ) -> tuple[int, int, int, int] | None:
        """Pixel window (row0, row1, col0, col1) covering map points, or None if off-grid.

        The margin also covers the largest warp displacement.
        """
        pts = np.asarray(points_xy, dtype=float).reshape(-1, 2)
        col, row = self.map_to_pixel(pts[:, 0], pts[:, 1])
        margin = margin_px + max((w.max_displacement_px() for w in self.warps), default=0.0)
        c0 = max(0, int(math.floor(col.min() - margin)))
        c1 = min(self.width, int(math.ceil(col.max() + margin)) + 1)
        r0 = max(0, int(math.floor(row.min() - margin)))
        r1 = min(self.height, int(math.ceil(row.max() + margin)) + 1)
        if c0 >= c1 or r0 >= r1:
            return None
        return r0, r1, c0, c1

    def window_for_disc(self, x: float, y: float, radius_m: float, *,
                        extra: Sequence[tuple[float, float]] = (), margin_px: float = 2.0
                        ) -> tuple[int, int, int, int] | None:
        """Window covering a disc of ``radius_m`` around (x, y), and that disc moved by
        each (dx, dy) offset in ``extra`` (e.g. where its shadow falls)."""
        pts = [(x + sx * radius_m + dx, y + sy * radius_m + dy)
               for dx, dy in [(0.0, 0.0), *extra] for sx in (-1, 1) for sy in (-1, 1)]
        return self.window_for(np.array(pts), margin_px=margin_px)


def fit_affine(transformer, bounds: tuple[float, float, float, float],  # noqa: ANN001
               n: int = 11) -> tuple[Affine, float]:
    """Least-squares affine of a CRS transformation over ``bounds`` and its worst residual.

    Parameters
    ----------
    transformer
        A ``pyproj.Transformer`` (``always_xy=True``).
    bounds
        (minx, miny, maxx, maxy) in the source CRS.
    n
        Samples per axis.

    Returns
    -------
    affine, max_residual
        The fitted source → target affine and the largest distance between it
        and the transformer at the samples (target units).
    """
    minx, miny, maxx, maxy = bounds
    gx, gy = np.meshgrid(np.linspace(minx, maxx, n), np.linspace(miny, maxy, n))
    sx, sy = gx.ravel(), gy.ravel()
    tx, ty = transformer.transform(sx, sy)
    a = np.c_[sx, sy, np.ones_like(sx)]
    cx, *_ = np.linalg.lstsq(a, tx, rcond=None)
    cy, *_ = np.linalg.lstsq(a, ty, rcond=None)
    res = float(np.max(np.hypot(a @ cx - tx, a @ cy - ty)))
    return Affine(cx[0], cx[1], cx[2], cy[0], cy[1], cy[2]), res


def grid_in_crs(crs: str, transform: Affine, width: int, height: int, *,
                world_crs: str = "EPSG:28356", max_residual_m: float = 0.005) -> RenderGrid:
    """A :class:`RenderGrid` for a raster grid in any CRS (its pixels' true positions).

    The CRS transformation to the world's CRS is replaced by an affine fitted over
    the grid, which holds to millimetres over a few hundred metres in projected
    CRSs; a grid where it does not raises ``ValueError``.
    """
    from pyproj import Transformer

    corners = np.array([transform @ (c, r) for c, r in
                        ((0, 0), (width, 0), (width, height), (0, height))])
    bounds = (corners[:, 0].min(), corners[:, 1].min(), corners[:, 0].max(),
              corners[:, 1].max())
    fit, res = fit_affine(Transformer.from_crs(crs, world_crs, always_xy=True), bounds)
    if res > max_residual_m:
        raise ValueError(f"{crs} → {world_crs} is not affine to {max_residual_m} m over this "
                         f"grid (worst {res:.3g} m); render a smaller grid")
    return RenderGrid(width, height, fit @ transform)


def rotation_scale_about(centre_xy: tuple[float, float], *, rotation_deg: float, scale: float,
                         shift_xy: tuple[float, float]) -> Affine:
    """Map-to-map affine: scale and rotate (counter-clockwise positive, in a
    east-north frame) about ``centre_xy``, then shift by ``shift_xy`` metres.

    ``p' = c + shift + scale · R(rotation) · (p − c)``.
    """
    t = math.radians(rotation_deg)
    cos_t, sin_t = scale * math.cos(t), scale * math.sin(t)
    cx, cy = centre_xy
    dx, dy = shift_xy
    return Affine(cos_t, -sin_t, cx + dx - cos_t * cx + sin_t * cy,
                  sin_t, cos_t, cy + dy - sin_t * cx - cos_t * cy)
