"""The sample world's layout: paddocks, fences, a track, cattle pads, a dam, a
trough and trees, all in map coordinates (GDA94 / MGA zone 56, EPSG:28356).

The layout is vector data; :mod:`geosim.samples.ground` turns the static ground
into an albedo raster and :mod:`geosim.samples.render` renders the world on any
grid.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Point, Polygon, box
from shapely.ops import split

WORLD_CRS = "EPSG:28356"


@dataclass(frozen=True)
class Tree:
    """A eucalypt.

    Attributes
    ----------
    id
        Tree number.
    x, y
        Trunk position, metres (EPSG:28356).
    crown_radius_m
        Mean crown radius, metres.
    height_m
        Height of the crown top above the ground, metres.
    crown_base_m
        Height of the lowest foliage, metres.
    """

    id: int
    x: float
    y: float
    crown_radius_m: float
    height_m: float
    crown_base_m: float


@dataclass(frozen=True)
class Trough:
    """A concrete water trough (rectangle).

    Attributes
    ----------
    x, y
        Centre, metres.
    heading_deg
        Direction of the long side, clockwise from grid north, degrees.
    length_m, width_m, height_m
        Outer size, metres.
    """

    x: float
    y: float
    heading_deg: float
    length_m: float = 3.0
    width_m: float = 0.8
    height_m: float = 0.6


@dataclass(frozen=True)
class Layout:
    """Vector description of the world.

    Attributes
    ----------
    centre_xy
        Site centre, metres.
    bounds
        (minx, miny, maxx, maxy) where the ground is defined, metres.
    fences
        Fence polylines, each an (N, 2) array of map coordinates.
    posts
        Wooden posts: (M, 2) positions; star pickets: (K, 2) positions.
    paddocks
        Paddock name → polygon (covering ``bounds``).
    track
        Centreline of the dirt track, (N, 2); ``track_gauge_m`` between wheel ruts.
    trails
        Cattle pads (narrow bare paths), polylines.
    dam
        Water surface polygon; ``dam_wall`` the earth embankment polygon.
    trough
        The water trough.
    trees
        Trees.
    """

    centre_xy: tuple[float, float]
    bounds: tuple[float, float, float, float]
    fences: tuple[np.ndarray, ...]
    posts: np.ndarray
    pickets: np.ndarray
    paddocks: dict[str, Polygon]
    track: np.ndarray
    track_gauge_m: float
    trails: tuple[np.ndarray, ...]
    dam: Polygon
    dam_wall: Polygon
    trough: Trough
    trees: tuple[Tree, ...]

    def paddock_of(self, x: float, y: float) -> str | None:
        """Name of the paddock containing a point, or None."""
        p = Point(x, y)
        for name, poly in self.paddocks.items():
            if poly.contains(p):
                return name
        return None


def catmull_rom(points: np.ndarray, *, step_m: float = 0.5) -> np.ndarray:
    """Smooth curve through control points (centripetal-free uniform Catmull–Rom),
    resampled about every ``step_m`` metres."""
    p = np.asarray(points, dtype=float)
    ext = np.vstack([2 * p[0] - p[1], p, 2 * p[-1] - p[-2]])
    out = []
    for i in range(1, len(ext) - 2):
        p0, p1, p2, p3 = ext[i - 1], ext[i], ext[i + 1], ext[i + 2]
        n = max(2, int(math.ceil(np.linalg.norm(p2 - p1) / step_m)))
        t = np.linspace(0.0, 1.0, n, endpoint=False)[:, None]
        out.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3))
    out.append(p[-1:])
    return np.vstack(out)


def _along(line: np.ndarray, spacing_m: float, phase_m: float) -> np.ndarray:
    """Points every ``spacing_m`` along a polyline, starting ``phase_m`` in."""
    ls = LineString(line)
    d = np.arange(phase_m, ls.length, spacing_m)
    return np.array([[q.x, q.y] for q in (ls.interpolate(v) for v in d)]).reshape(-1, 2)


def _random_walk(rng: np.random.Generator, start: np.ndarray, heading_deg: float, length_m: float,
                 region: Polygon, *, step_m: float = 0.5, wander_deg: float = 2.5) -> np.ndarray:
    """A meandering cattle pad from ``start``, stopping where it would leave ``region``."""
    pts = [np.asarray(start, dtype=float)]
    h = math.radians(heading_deg)
    turn = 0.0
    for _ in range(int(length_m / step_m)):
        turn = 0.85 * turn + math.radians(wander_deg) * float(rng.standard_normal())
        h += turn * step_m
        nxt = pts[-1] + step_m * np.array([math.sin(h), math.cos(h)])
        if not region.contains(Point(*nxt)):
            break
        pts.append(nxt)
    return np.array(pts)


def build_layout(rng: np.random.Generator, centre_xy: tuple[float, float], *,
                 half_size_m: float = 96.0) -> Layout:
    """Lay out the sample world around ``centre_xy``.

    Parameters
    ----------
    rng
        Random generator (fence angles, dam shape, trees, pads).
    centre_xy
        Site centre in EPSG:28356, metres.
    half_size_m
        Half the side of the square where the ground is defined, metres.
    """
    cx, cy = centre_xy
    bounds = (cx - half_size_m, cy - half_size_m, cx + half_size_m, cy + half_size_m)
    big = half_size_m + 60.0

    # Fence A runs roughly north–south with a kink; fence B leaves it eastwards.
    ang_a = math.radians(rng.uniform(5.0, 11.0))
    kink = math.radians(rng.uniform(-5.0, -2.0))
    x_a = cx - rng.uniform(4.0, 8.0)
    y_kink = cy + rng.uniform(20.0, 30.0)

    def fence_a_x(y: float) -> float:
        if y <= y_kink:
            return x_a + (y - cy) * math.tan(ang_a)
        return x_a + (y_kink - cy) * math.tan(ang_a) + (y - y_kink) * math.tan(ang_a + kink)

    fence_a = np.array([[fence_a_x(y), y] for y in (cy - big, y_kink, cy + big)])
    y_b = cy + rng.uniform(14.0, 20.0)
    bear_b = math.radians(rng.uniform(94.0, 100.0))
    b0 = np.array([fence_a_x(y_b), y_b])
    fence_b = np.array([b0, b0 + (big + 10) * np.array([math.sin(bear_b), math.cos(bear_b)])])
    fences = (fence_a, fence_b)

    world_box = box(cx - big, cy - big, cx + big, cy + big)
    west, east = sorted(split(world_box, LineString(fence_a)).geoms,
                        key=lambda g: g.centroid.x)
    ext_b = LineString([b0 - 5 * (fence_b[1] - b0) / np.linalg.norm(fence_b[1] - b0), fence_b[1]])
    south_east, north_east = sorted(split(east, ext_b).geoms, key=lambda g: g.centroid.y)
    clip = box(*bounds).buffer(20.0, join_style="mitre")
    paddocks = {"Dam Paddock": west.intersection(clip),
                "Top Paddock": north_east.intersection(clip),
                "Yards Paddock": south_east.intersection(clip)}

    posts = np.vstack([_along(f, 10.0, rng.uniform(0, 10)) for f in fences])
    pickets = np.vstack([_along(f, 2.5, rng.uniform(0, 2.5)) for f in fences])
    # No picket on top of a post.
    d = np.min(np.hypot(pickets[:, None, 0] - posts[None, :, 0],
                        pickets[:, None, 1] - posts[None, :, 1]), axis=1)
    pickets = pickets[d > 0.6]

    # Track: 7 m west of fence A, then bending north-west.
    ctrl = [[fence_a_x(y) - 7.0 + rng.uniform(-1.0, 1.0), y]
            for y in (cy - big, cy - 60, cy - 25, cy + 5)]
    ctrl += [[fence_a_x(cy + 5) - 7.0 - 15.0, cy + 35.0], [cx - 60.0, cy + 75.0],
             [cx - 90.0, cy + big]]
    track = catmull_rom(np.array(ctrl), step_m=0.5)

    # Dam: an irregular blob in the west paddock with an embankment on its south-east side.
    dam_c = np.array([cx - rng.uniform(34.0, 40.0), cy - rng.uniform(14.0, 22.0)])
    theta = np.linspace(0, 2 * np.pi, 72, endpoint=False)
    rot = rng.uniform(0, np.pi)
    radial = 1.0 + sum(rng.uniform(0.03, 0.08) * np.cos(k * theta + rng.uniform(0, 2 * np.pi))
                       for k in (2, 3, 5))
    ax_a, ax_b = rng.uniform(10.0, 12.0), rng.uniform(7.0, 8.5)
    px = ax_a * radial * np.cos(theta)
    py = ax_b * radial * np.sin(theta)
    dam = Polygon(np.c_[dam_c[0] + px * math.cos(rot) - py * math.sin(rot),
                        dam_c[1] + px * math.sin(rot) + py * math.cos(rot)])
    wall_dir = np.array([math.sin(math.radians(135)), math.cos(math.radians(135))])
    wall = dam.buffer(5.0).difference(dam.buffer(1.0)).intersection(
        Point(*(dam_c + 9.0 * wall_dir)).buffer(12.0))

    trough_y = cy - rng.uniform(26.0, 34.0)
    trough = Trough(x=fence_a_x(trough_y) + 4.0, y=trough_y,
                    heading_deg=math.degrees(ang_a) % 180.0)

    # Trees: a shelter line along fence B, then paddock trees.
    trees: list[Tree] = []

    def new_tree(x: float, y: float) -> Tree:
        h = rng.uniform(12.0, 20.0)
        return Tree(id=len(trees) + 1, x=float(x), y=float(y),
                    crown_radius_m=float(rng.uniform(3.5, 6.5)), height_m=float(h),
                    crown_base_m=float(h * rng.uniform(0.35, 0.5)))

    ub = (fence_b[1] - b0) / np.linalg.norm(fence_b[1] - b0)
    nb = np.array([-ub[1], ub[0]])  # left of fence B's direction = north side
    for s in (16.0, 33.0, 51.0, 70.0):
        p = b0 + s * ub + rng.uniform(6.5, 8.0) * nb
        trees.append(new_tree(*p))
    fence_geom = shapely.MultiLineString([LineString(f) for f in fences])
    track_geom = LineString(track)
    trough_pt = Point(trough.x, trough.y)

    def tree_ok(x: float, y: float, r: float) -> bool:
        p = Point(x, y)
        return (fence_geom.distance(p) > r + 1.0 and track_geom.distance(p) > r + 2.0
                and dam.distance(p) > r + 4.0 and trough_pt.distance(p) > r + 5.0
                and all(math.hypot(x - t.x, y - t.y) > 16.0 for t in trees))

    for reach, wanted in ((38.0, 3), (half_size_m - 8.0, 5)):
        placed = 0
        for _ in range(500):
            x, y = cx + rng.uniform(-reach, reach), cy + rng.uniform(-reach, reach)
            if tree_ok(x, y, 6.5):
                trees.append(new_tree(x, y))
                placed += 1
                if placed == wanted:
                    break

    # Cattle pads: from the dam and the trough, along fences, and a few wandering ones.
    trails: list[np.ndarray] = []
    for name, poly in paddocks.items():
        region = poly.buffer(-1.0)
        starts: list[tuple[np.ndarray, float]] = []
        if name == "Dam Paddock":
            for _ in range(3):
                a = rng.uniform(0, 2 * np.pi)
                starts.append((dam_c + 16.0 * np.array([math.sin(a), math.cos(a)]),
                               math.degrees(a)))
        if poly.contains(trough_pt):
            for _ in range(3):
                a = rng.uniform(0, 2 * np.pi)
                starts.append((np.array([trough.x, trough.y])
                               + 3.0 * np.array([math.sin(a), math.cos(a)]), math.degrees(a)))
        for _ in range(2):
            starts.append((np.array([cx + rng.uniform(-60, 60), cy + rng.uniform(-60, 60)]),
                           rng.uniform(0, 360)))
        for start, heading in starts:
            if region.contains(Point(*start)):
                walk = _random_walk(rng, start, heading, rng.uniform(40, 110), region)
                if len(walk) > 10:
                    trails.append(walk)
    for f in fences:  # pads along the fences, 1.5 m off, on both sides
        ls = LineString(f)
        for side in (-1.0, 1.0):
            off = ls.offset_curve(side * rng.uniform(1.3, 1.9))
            a0 = rng.uniform(0.0, 0.4) * off.length
            seg = shapely.ops.substring(off, a0, a0 + rng.uniform(0.3, 0.6) * off.length)
            trails.append(np.asarray(seg.coords))

    return Layout(centre_xy=(float(cx), float(cy)), bounds=bounds, fences=fences, posts=posts,
                  pickets=pickets, paddocks=paddocks, track=track, track_gauge_m=1.7,
                  trails=tuple(trails), dam=dam, dam_wall=wall, trough=trough,
                  trees=tuple(trees))
