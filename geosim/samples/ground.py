"""The static ground as an albedo raster in map coordinates.

The ground (pasture, tussocks, bare patches, dung, cattle pads, the track, the
dam and the ungrazed strips under fences) does not change between acquisitions,
so it is made once on a fine north-up raster in EPSG:28356 and every rendering
samples it at its own pixel positions (bicubic). Values are the digital numbers
(0–255 scale) that flat ground shows in full sun; shadows and exposure are
applied by the renderer.

Colour anchors: pasture, soil and dry grass of a Southern Highlands winter
paddock. Relative statistics measured on a real nadir frame of cattle on NSW
pasture (``../shared/realdata/cattle_frame_nsw.jpg``, 11 boxed animals; the file
itself is not used at run time) are used in :mod:`geosim.samples.cattle` and
:mod:`geosim.samples.render`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from affine import Affine
from shapely.geometry import Polygon

from geosim.samples.textures import multiscale_noise, smooth_noise, smoothstep
from geosim.samples.world import Layout

GREEN = np.array([70.0, 96.0, 56.0], dtype=np.float32)      # grazed winter pasture
DRY = np.array([136.0, 126.0, 90.0], dtype=np.float32)      # senescent grass
TUSSOCK = np.array([156.0, 150.0, 112.0], dtype=np.float32)  # Poa tussock tops
SOIL = np.array([156.0, 136.0, 108.0], dtype=np.float32)    # dry bare soil
DARK_SOIL = np.array([116.0, 99.0, 80.0], dtype=np.float32)  # compacted / damp soil
MUD = np.array([84.0, 74.0, 62.0], dtype=np.float32)        # wet margin of the dam
WATER = np.array([50.0, 58.0, 50.0], dtype=np.float32)      # turbid farm dam
DUNG = np.array([66.0, 58.0, 44.0], dtype=np.float32)


@dataclass(frozen=True)
class GroundRaster:
    """Albedo of the static ground: colour on one north-up raster, grass grain on a
    finer one.

    The albedo at a map point is ``rgb · (1 + amp · grain)``: ``rgb`` and ``amp``
    (the local strength of the grain: grass, not water) come from ``rgba``,
    ``grain`` (unit-variance blade-scale texture) from the finer raster.

    Attributes
    ----------
    transform
        Affine of ``rgba`` (pixel corner → map).
    rgba
        (rows, cols, 4) float32: red, green, blue digital numbers of sunlit flat
        ground and the grain amplitude (dimensionless).
    grain_transform
        Affine of ``grain``.
    grain
        (rows, cols) float32 blade-scale texture, unit variance.
    """

    transform: Affine
    rgba: np.ndarray
    grain_transform: Affine
    grain: np.ndarray

    @property
    def res_m(self) -> float:
        """Colour raster pixel size, metres."""
        return float(self.transform.a)

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bicubic sample at map points; returns (3, …) float32 bands-first albedo (DN)."""
        mx, my = _remap_coords(self.transform, x, y)
        out = cv2.remap(self.rgba, mx, my, interpolation=cv2.INTER_CUBIC,
                        borderMode=cv2.BORDER_REFLECT)
        gx, gy = _remap_coords(self.grain_transform, x, y)
        grain = cv2.remap(self.grain, gx, gy, interpolation=cv2.INTER_CUBIC,
                          borderMode=cv2.BORDER_REFLECT)
        mod = 1.0 + out[..., 3] * grain
        return np.moveaxis(out[..., :3], -1, 0) * mod[np.newaxis]


def _remap_coords(transform: Affine, x: np.ndarray, y: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """cv2.remap source coordinates (pixel centres at integers) of map points."""
    inv = ~transform
    mx = (inv.a * x + inv.b * y + inv.c - 0.5).astype(np.float32)
    my = (inv.d * x + inv.e * y + inv.f - 0.5).astype(np.float32)
    return mx, my


def _to_px(transform: Affine, xy: np.ndarray) -> np.ndarray:
    """Map coordinates → cv2 drawing coordinates (pixel centres at integers), ×16."""
    inv = ~transform
    xy = np.asarray(xy, dtype=float)
    col = inv.a * xy[:, 0] + inv.b * xy[:, 1] + inv.c - 0.5
    row = inv.d * xy[:, 0] + inv.e * xy[:, 1] + inv.f - 0.5
    return np.round(np.c_[col, row] * 16).astype(np.int32)


def _draw_lines(shape: tuple[int, int], transform: Affine, lines: list[np.ndarray],
                width_m: float) -> np.ndarray:
    """Anti-aliased polylines of ``width_m`` as a float32 coverage raster in [0, 1]."""
    canvas = np.zeros(shape, dtype=np.uint8)
    thickness = max(1, int(round(width_m / transform.a)))
    for line in lines:
        if len(line) >= 2:
            cv2.polylines(canvas, [_to_px(transform, line)], False, 255, thickness,
                          cv2.LINE_AA, shift=4)
    return canvas.astype(np.float32) / 255.0


def _fill_polygon(shape: tuple[int, int], transform: Affine, poly: Polygon) -> np.ndarray:
    canvas = np.zeros(shape, dtype=np.uint8)
    if not poly.is_empty:
        polys = poly.geoms if poly.geom_type == "MultiPolygon" else [poly]
        for p in polys:
            cv2.fillPoly(canvas, [_to_px(transform, np.asarray(p.exterior.coords))], 255,
                         cv2.LINE_AA, shift=4)
    return canvas.astype(np.float32) / 255.0


def _distance_m(mask: np.ndarray, res_m: float) -> np.ndarray:
    """Distance from every pixel to the nearest True pixel of ``mask``, metres."""
    src = np.where(mask, 0, 255).astype(np.uint8)
    return cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(res_m)


def _stamp_discs(rng: np.random.Generator, canvas: np.ndarray, transform: Affine,
                 centres: np.ndarray, radii_m: np.ndarray, values: np.ndarray) -> None:
    """Draw anti-aliased discs (max-composited) into a uint8 canvas."""
    px = _to_px(transform, centres)
    for (c, r), rad, v in zip(px, radii_m, values, strict=True):
        cv2.circle(canvas, (int(c), int(r)), int(round(rad / transform.a * 16)), int(v), -1,
                   cv2.LINE_AA, shift=4)


def build_ground(rng: np.random.Generator, layout: Layout, *, res_m: float = 0.1,
                 grain_res_m: float = 0.05) -> GroundRaster:
    """Make the ground albedo rasters over ``layout.bounds``.

    Parameters
    ----------
    rng
        Random generator for every texture.
    layout
        The world's vector layout.
    res_m
        Colour raster pixel size, metres.
    grain_res_m
        Grass grain raster pixel size, metres (the UAV GSD: blade-scale texture).

    Returns
    -------
    GroundRaster
    """
    minx, miny, maxx, maxy = layout.bounds
    cols = int(round((maxx - minx) / res_m))
    rows = int(round((maxy - miny) / res_m))
    shape = (rows, cols)
    transform = Affine(res_m, 0.0, minx, 0.0, -res_m, maxy)
    per_m = 1.0 / res_m
    area_m2 = (maxx - minx) * (maxy - miny)

    # Paddock grazing pressure: each paddock its own dryness.
    dry_bias = np.zeros(shape, dtype=np.float32)
    for name, poly in layout.paddocks.items():
        bias = {"Dam Paddock": -0.35, "Top Paddock": 0.25, "Yards Paddock": 0.05}.get(name, 0.0)
        dry_bias += np.float32(bias) * _fill_polygon(shape, transform, poly)
    dry_bias = cv2.GaussianBlur(dry_bias, (0, 0), 1.0 * per_m)

    # Multi-scale moisture / grazing field: 25 m, 6 m, 1.5 m, 0.4 m.
    field = multiscale_noise(rng, shape, (25 * per_m, 6 * per_m, 1.5 * per_m, 0.4 * per_m),
                             (1.0, 0.7, 0.45, 0.25))
    fence_dist = _distance_m(_draw_lines(shape, transform, list(layout.fences), res_m) > 0.3,
                             res_m)
    ungrazed = 1.0 - smoothstep(0.35, 0.9, fence_dist)  # long grass strip under the wires
    w_dry = smoothstep(-1.6, 1.6, 0.9 * field + dry_bias + 1.6 * ungrazed - 0.2)
    del field, dry_bias, fence_dist
    rgb = GREEN[None, None, :] + (DRY - GREEN)[None, None, :] * w_dry[..., None]

    # Grass clumps (~0.15 m) with a little straw showing between them.
    fine = smooth_noise(rng, shape, 0.15 * per_m)
    hue = smooth_noise(rng, shape, 0.5 * per_m)
    lum = 1.0 + np.float32(0.09) * fine * (1.0 + 0.6 * ungrazed)
    rgb += (DRY[None, None, :] - rgb) * (0.18 * smoothstep(0.0, 2.0, hue))[..., None]
    rgb *= lum[..., None]
    amp = np.full(shape, 0.09, dtype=np.float32)  # blade grain strength
    amp += np.float32(0.05) * ungrazed
    del lum, hue

    # Tussocks: sparse clumps, denser in drier ground and along fences.
    n_tuss = int(0.035 * area_m2)
    cand = np.c_[rng.uniform(minx, maxx, n_tuss), rng.uniform(miny, maxy, n_tuss)]
    ci = ((cand[:, 0] - minx) * per_m).astype(int).clip(0, cols - 1)
    ri = ((maxy - cand[:, 1]) * per_m).astype(int).clip(0, rows - 1)
    keep = rng.uniform(0, 1, n_tuss) < 0.25 + 0.75 * w_dry[ri, ci]
    cand = cand[keep]
    rad = rng.uniform(0.2, 0.45, len(cand))
    tuss = np.zeros(shape, dtype=np.uint8)
    _stamp_discs(rng, tuss, transform, cand, rad, np.full(len(cand), 170))
    _stamp_discs(rng, tuss, transform, cand + rng.normal(0, 0.04, cand.shape), rad * 0.65,
                 np.full(len(cand), 255))
    t_cov = np.clip(tuss.astype(np.float32) / 255.0 * (1.0 + 0.4 * fine), 0.0, 1.0)
    t_col = TUSSOCK[None, None, :] * (0.78 + 0.3 * t_cov[..., None])
    rgb += (t_col - rgb) * (0.9 * t_cov[..., None])
    amp += np.float32(0.06) * t_cov
    del tuss, t_cov, t_col

    # Bare patches (0.5–3 m), more near the dam, the trough and gateways; cattle pads.
    bare_f = multiscale_noise(rng, shape, (3.0 * per_m, 0.8 * per_m, 0.25 * per_m),
                              (0.8, 0.7, 0.45))
    dam_mask = _fill_polygon(shape, transform, layout.dam)
    dam_dist = _distance_m(dam_mask > 0.5, res_m)
    tr = layout.trough
    trough_dist = np.hypot(*np.meshgrid((np.arange(cols) + 0.5) * res_m + minx - tr.x,
                                        maxy - (np.arange(rows) + 0.5) * res_m - tr.y,
                                        sparse=True)).astype(np.float32)
    attract = 1.4 * np.exp(-dam_dist / 6.0) + 1.6 * np.exp(-trough_dist / 5.0)
    bare = smoothstep(1.25, 1.65, bare_f + attract + 0.35 * w_dry)
    pads = _draw_lines(shape, transform, list(layout.trails), 0.32)
    pads = cv2.GaussianBlur(pads, (0, 0), 0.6) * smoothstep(-1.2, 0.2, bare_f)
    bare = np.maximum(bare, 0.9 * pads)
    soil = SOIL[None, None, :] + (DARK_SOIL - SOIL)[None, None, :] * \
        smoothstep(-1.0, 1.0, fine + 0.5 * bare_f)[..., None]
    soil *= (1.0 + np.float32(0.07) * fine)[..., None]
    rgb += (soil - rgb) * bare[..., None]
    amp += (np.float32(0.05) - amp) * bare
    del bare_f, pads, bare, attract, trough_dist, soil

    # Dung pats.
    n_dung = int(0.02 * area_m2)
    dung = np.zeros(shape, dtype=np.uint8)
    _stamp_discs(rng, dung, transform,
                 np.c_[rng.uniform(minx, maxx, n_dung), rng.uniform(miny, maxy, n_dung)],
                 rng.uniform(0.09, 0.17, n_dung), rng.integers(120, 230, n_dung))
    d_cov = dung.astype(np.float32)[..., None] / 255.0
    rgb += (DUNG[None, None, :] * (1.0 + 0.1 * fine[..., None]) - rgb) * d_cov
    del dung, d_cov

    # The track: two compacted wheel ruts and a thin, drier centre strip.
    track = layout.track
    seg = np.diff(track, axis=0)
    normal = np.c_[-seg[:, 1], seg[:, 0]] / np.linalg.norm(seg, axis=1)[:, None]
    normal = np.vstack([normal, normal[-1:]])
    half = layout.track_gauge_m / 2.0
    ruts = _draw_lines(shape, transform, [track + half * normal, track - half * normal], 0.5)
    ruts = cv2.GaussianBlur(ruts, (0, 0), 0.8)
    verge = cv2.GaussianBlur(_draw_lines(shape, transform, [track], 2.6), (0, 0), 3.0)
    rgb += ((0.55 * DRY + 0.45 * rgb) - rgb) * (0.5 * verge[..., None])
    rut_a = np.clip(ruts * (1.05 + 0.2 * fine), 0, 1)
    rgb += (SOIL[None, None, :] * (0.92 + 0.1 * fine[..., None]) - rgb) * rut_a[..., None]
    amp += (np.float32(0.04) - amp) * rut_a
    del ruts, verge, rut_a

    # The dam: water, a muddy pugged margin, trampled banks and the earth wall.
    wall = cv2.GaussianBlur(_fill_polygon(shape, transform, layout.dam_wall), (0, 0),
                            0.6 * per_m)
    rgb += (SOIL[None, None, :] * (1.06 + 0.06 * fine[..., None]) - rgb) * \
        (0.85 * wall[..., None])
    margin = (1.0 - smoothstep(0.0, 1.2, dam_dist)) * (1.0 - dam_mask)
    pug = smoothstep(-0.2, 0.8, smooth_noise(rng, shape, 0.15 * per_m))
    rgb += (MUD[None, None, :] * (0.8 + 0.3 * pug[..., None]) - rgb) * margin[..., None]
    ripple = smooth_noise(rng, shape, 0.8 * per_m)
    depth = smoothstep(0.0, 4.0, _distance_m(dam_mask < 0.5, res_m))
    water = WATER[None, None, :] * (1.0 + 0.03 * ripple[..., None]) \
        + (MUD - WATER)[None, None, :] * (0.5 * (1.0 - depth[..., None]))
    rgb += (water - rgb) * dam_mask[..., None]
    amp *= 1.0 - dam_mask
    del wall, margin, pug, ripple, depth, water, dam_mask, dam_dist, fine, w_dry, ungrazed

    np.clip(rgb, 1.0, 255.0, out=rgb)
    rgba = np.concatenate([rgb, amp[..., None]], axis=-1)

    # Blade-scale grain on the finer raster (correlation ~1.5 cm and ~5 cm).
    g_cols = int(round((maxx - minx) / grain_res_m))
    g_rows = int(round((maxy - miny) / grain_res_m))
    grain = smooth_noise(rng, (g_rows, g_cols), 0.6) + np.float32(0.7) * \
        smooth_noise(rng, (g_rows, g_cols), 1.6)
    grain *= np.float32(1.0 / float(grain.std()))
    return GroundRaster(transform=transform, rgba=np.ascontiguousarray(rgba, dtype=np.float32),
                        grain_transform=Affine(grain_res_m, 0.0, minx, 0.0, -grain_res_m, maxy),
                        grain=np.ascontiguousarray(grain, dtype=np.float32))

