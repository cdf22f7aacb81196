"""Render the world on any grid: ground, shadows, fences, trough, cattle, trees.

:func:`render` evaluates the world at the true map position of every pixel of a
:class:`~geosim.samples.render_grid.RenderGrid`, so flights with georeferencing
errors or stitching warps and the satellite scene in another CRS are all
renderings of one world. The result is scene radiance in digital numbers
(0–255 scale, sunlit flat ground = its albedo), before any camera effects.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from geosim.samples import cattle as cattle_mod
from geosim.samples import trees as trees_mod
from geosim.samples.cattle import Cow
from geosim.samples.ground import GroundRaster, build_ground
from geosim.samples.illumination import Illumination
from geosim.samples.render_grid import RenderGrid
from geosim.samples.trees import CrownPatch, build_crown, line_profile, segment_coverage
from geosim.samples.world import Layout, build_layout

WIRE = np.array([168.0, 170.0, 172.0], dtype=np.float32)     # galvanised wire
POST = np.array([118.0, 104.0, 88.0], dtype=np.float32)      # weathered timber
PICKET = np.array([58.0, 60.0, 62.0], dtype=np.float32)      # steel star picket
CONCRETE = np.array([172.0, 170.0, 162.0], dtype=np.float32)
TROUGH_WATER = np.array([44.0, 54.0, 52.0], dtype=np.float32)
WIRE_WIDTH_M = 0.012     # four 3 mm wires, superposed at nadir
POST_RADIUS_M = 0.075
POST_HEIGHT_M = 1.2
PICKET_WIDTH_M = 0.035
PICKET_HEIGHT_M = 1.0


@dataclass(frozen=True)
class World:
    """Everything static: layout, ground albedo rasters and tree crowns."""

    layout: Layout
    ground: GroundRaster
    crowns: tuple[CrownPatch, ...]


def build_world(rngs: dict[str, np.random.Generator], centre_xy: tuple[float, float]) -> World:
    """Build the static world from generators named ``layout``, ``ground``, ``trees``."""
    layout = build_layout(rngs["layout"], centre_xy)
    ground = build_ground(rngs["ground"], layout)
    crowns = tuple(build_crown(rngs["trees"], t) for t in layout.trees)
    return World(layout=layout, ground=ground, crowns=crowns)


def _union(dst: np.ndarray, win: tuple[int, int, int, int], cover: np.ndarray) -> None:
    """dst ← 1 − (1 − dst)(1 − cover) in a window (coverage of overlapping shadows)."""
    r0, r1, c0, c1 = win
    sub = dst[r0:r1, c0:c1]
    sub += cover * (1.0 - sub)


def _composite(out: np.ndarray, win: tuple[int, int, int, int], cover: np.ndarray,
               radiance: np.ndarray) -> None:
    r0, r1, c0, c1 = win
    sub = out[:, r0:r1, c0:c1]
    sub += (radiance - sub) * cover[None]


def _box_coverage(x: np.ndarray, y: np.ndarray, cx: float, cy: float, heading_deg: float,
                  length_m: float, width_m: float, px_m: float) -> np.ndarray:
    h = math.radians(heading_deg)
    dx, dy = x - cx, y - cy
    u = dx * math.sin(h) + dy * math.cos(h)
    v = dx * math.cos(h) - dy * math.sin(h)
    return (np.clip(0.5 + (length_m / 2 - np.abs(u)) / px_m, 0, 1)
            * np.clip(0.5 + (width_m / 2 - np.abs(v)) / px_m, 0, 1)).astype(np.float32)


def _points_on_grid(grid: RenderGrid, pts: np.ndarray, margin_px: float) -> np.ndarray:
    if len(pts) == 0:
        return pts
    c, r = grid.map_to_pixel(pts[:, 0], pts[:, 1])
    ok = (c > -margin_px) & (c < grid.width + margin_px) & (r > -margin_px) \
        & (r < grid.height + margin_px)
    return pts[ok]


def render(world: World, grid: RenderGrid, illum: Illumination, cows: Sequence[Cow], *,
           block_rows: int = 256, progress: Callable[[int], None] | None = None) -> np.ndarray:
    """Scene radiance of the world on ``grid`` under ``illum`` with ``cows`` present.

    Parameters
    ----------
    world
        The static world.
    grid
        Where each pixel looks (true map coordinates, EPSG:28356).
    illum
        Sun and sky of the acquisition.
    cows
        The animals and their poses at this acquisition.
    block_rows
        Rows per block when sampling the ground.
    progress
        Called with a number of rows done (for a progress bar).

    Returns
    -------
    numpy.ndarray
        (3, height, width) float32 radiance in DN (unclipped).
    """
    h, w = grid.height, grid.width
    px = grid.pixel_size_m
    out = np.empty((3, h, w), dtype=np.float32)
    for r0 in range(0, h, block_rows):
        r1 = min(h, r0 + block_rows)
        x, y = grid.coords(r0, r1, 0, w)
        out[:, r0:r1] = world.ground.sample(x, y)
        if progress is not None:
            progress(r1 - r0)

    shadow = np.zeros((h, w), dtype=np.float32)       # on the ground
    tree_shadow = np.zeros((h, w), dtype=np.float32)  # on raised objects (cattle, posts)
    sun = illum.sun

    for patch in world.crowns:
        win = trees_mod.shadow_window(grid, patch, illum)
        if win is None:
            continue
        x, y = grid.coords(*win)
        cov = trees_mod.shadow_coverage(patch, illum, x, y, px)
        _union(shadow, win, cov)
        _union(tree_shadow, win, cov)

    layout = world.layout
    tops: list[tuple[tuple[int, int, int, int], np.ndarray, np.ndarray]] = []
    for pts, radius, height, colour in (
            (layout.posts, POST_RADIUS_M, POST_HEIGHT_M, POST),
            (layout.pickets, PICKET_WIDTH_M / 2, PICKET_HEIGHT_M, PICKET)):
        off = sun.shadow_offset_m(height)
        for p in _points_on_grid(grid, pts, 2 + abs(off).max() / px):
            win = grid.window_for_disc(p[0], p[1], radius + 0.05, extra=[tuple(off)])
            if win is None:
                continue
            x, y = grid.coords(*win)
            _union(shadow, win, segment_coverage(x, y, tuple(p), (p[0] + off[0], p[1] + off[1]),
                                                 2 * radius, px))
            top = line_profile(np.hypot(x - p[0], y - p[1]), 2 * radius, px)
            tops.append((win, top, colour))

    tr = layout.trough
    t_off = sun.shadow_offset_m(tr.height_m)
    t_win = grid.window_for_disc(tr.x, tr.y, tr.length_m / 2 + 0.1, extra=[tuple(t_off)])
    if t_win is not None:
        x, y = grid.coords(*t_win)
        cov = np.zeros(x.shape, dtype=np.float32)
        for frac in np.linspace(0.0, 1.0, 7):
            o = t_off * frac
            cov = np.maximum(cov, _box_coverage(x - o[0], y - o[1], tr.x, tr.y, tr.heading_deg,
                                                tr.length_m, tr.width_m, px))
        _union(shadow, t_win, cov)

    cow_layers = []
    for cow in cows:
        small = cattle_mod.cow_window(grid, cow)
        big = cattle_mod.cow_window(grid, cow, illum)
        if small is None or big is None:
            continue
        xs, ys = grid.coords(*small)
        body, head = cattle_mod.coverage(cow, grid, xs, ys)
        xb, yb = grid.coords(*big)
        body_b = np.zeros(xb.shape, dtype=np.float32)
        head_b = np.zeros(xb.shape, dtype=np.float32)
        sl = (slice(small[0] - big[0], small[1] - big[0]), slice(small[2] - big[2],
                                                                   small[3] - big[2]))
        body_b[sl] = body
        head_b[sl] = head
        _union(shadow, big, cattle_mod.shadow_coverage(cow, grid, illum, xb, yb, body_b, head_b))
        cow_layers.append((cow, small, xs, ys, body, head))

    for r0 in range(0, h, block_rows):
        r1 = min(h, r0 + block_rows)
        out[:, r0:r1] *= illum.ground_factor(shadow[r0:r1])

    # Overlays, lowest first: wires, post tops, trough, cattle, tree crowns.
    for fence in layout.fences:
        for a, b in zip(fence[:-1], fence[1:], strict=True):
            n = max(2, int(np.linalg.norm(b - a) / 5.0))
            pts = np.linspace(a, b, n)
            pts = _points_on_grid(grid, pts, 10)
            if len(pts) == 0:
                continue
            win = grid.window_for(pts, margin_px=3)
            if win is None:
                continue
            x, y = grid.coords(*win)
            cov = segment_coverage(x, y, tuple(a), tuple(b), WIRE_WIDTH_M, px)
            lit = illum.ground_factor(tree_shadow[win[0]:win[1], win[2]:win[3]])
            _composite(out, win, cov, WIRE[:, None, None] * lit)
    for win, top, colour in tops:
        lit = illum.ground_factor(tree_shadow[win[0]:win[1], win[2]:win[3]])
        _composite(out, win, top, colour[:, None, None] * lit)
    if t_win is not None:
        x, y = grid.coords(*t_win)
        lit = illum.ground_factor(tree_shadow[t_win[0]:t_win[1], t_win[2]:t_win[3]])
        rim = _box_coverage(x, y, tr.x, tr.y, tr.heading_deg, tr.length_m, tr.width_m, px)
        water = _box_coverage(x, y, tr.x, tr.y, tr.heading_deg, tr.length_m - 0.16,
                              tr.width_m - 0.16, px)
        _composite(out, t_win, rim, CONCRETE[:, None, None] * lit)
        _composite(out, t_win, water, TROUGH_WATER[:, None, None] * lit)
    for cow, win, xs, ys, body, head in cow_layers:
        shade = tree_shadow[win[0]:win[1], win[2]:win[3]]
        cov, rad = cattle_mod.cow_layer(cow, illum, xs, ys, body, head, shade)
        _composite(out, win, cov, rad)
    for patch in world.crowns:
        t = patch.tree
        win = grid.window_for_disc(t.x, t.y, patch.extent_m)
        if win is None:
            continue
        x, y = grid.coords(*win)
        alpha, rad = trees_mod.crown_layer(patch, illum, x, y)
        _composite(out, win, alpha, rad)
    return out

