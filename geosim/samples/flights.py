"""UAV flights of the sample site: footprints, georeferencing errors, camera
response and stitching artefacts.

Each flight is an orthomosaic at 0.05 m in EPSG:28356, north-up as its file
states. Its true georeference differs from the stated one by a small similarity
transform (the georeferencing error). The image is rendered through the *true*
mapping and written with the *stated* transform, as a stitched mosaic with GPS
errors would be.

Georeferencing error convention
-------------------------------
``stated_to_true`` maps a point's coordinates in the file's stated frame to
where that ground really is (both EPSG:28356, metres)::

    p_true = c + shift + scale · R(rotation) · (p_stated − c)

with ``c`` the image centre in the stated frame, ``R`` a counter-clockwise
rotation in the east–north plane, ``shift = (shift_x, shift_y)`` metres. As a
2×3 matrix ``[[a, b, c], [d, e, f]]``: ``x_true = a·x + b·y + c``,
``y_true = d·x + e·y + f``. A pixel ``(col, row)`` shows the ground at
``stated_to_true · stated_transform · (col, row)``; a correction that
re-georeferences the file is ``stated_to_true`` itself.
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import shapely
from affine import Affine
from shapely.affinity import affine_transform, rotate
from shapely.geometry import Polygon, box

from geosim.samples.render_grid import LocalWarp, RenderGrid, rotation_scale_about
from geosim.samples.textures import smooth_noise

UAV_GSD_M = 0.05


@dataclass(frozen=True)
class GeorefError:
    """A flight's georeferencing error (see the module docstring for the convention).

    Attributes
    ----------
    shift_m
        (x, y) translation, metres (east, north).
    rotation_deg
        Rotation about the image centre, counter-clockwise positive, degrees.
    scale
        Scale factor (1 = none).
    """

    shift_m: tuple[float, float]
    rotation_deg: float
    scale: float

    def stated_to_true(self, centre_xy: tuple[float, float]) -> Affine:
        """Map-to-map affine from stated coordinates to true coordinates."""
        return rotation_scale_about(centre_xy, rotation_deg=self.rotation_deg, scale=self.scale,
                                    shift_xy=self.shift_m)


@dataclass(frozen=True)
class ExposureSeam:
    """A straight seam between mosaic parts exposed differently (cloud shadow).

    Pixels left of the directed line ``p0 → p1`` (pixel coordinates) are
    multiplied by ``gain``, those on the right by 1, with a ``width_px`` ramp.
    """

    p0_px: tuple[float, float]
    p1_px: tuple[float, float]
    gain: float
    width_px: float = 2.0

    def factor(self, rows: int, cols: int) -> np.ndarray:
        """(rows, cols) float32 multiplicative exposure factor."""
        (x0, y0), (x1, y1) = self.p0_px, self.p1_px
        dx, dy = x1 - x0, y1 - y0
        n = math.hypot(dx, dy)
        c = np.arange(cols, dtype=np.float32)[None, :] + 0.5
        r = np.arange(rows, dtype=np.float32)[:, None] + 0.5
        side = ((c - x0) * dy - (r - y0) * dx) / n  # > 0 on the left in image (y down) terms
        t = np.clip(0.5 + side / self.width_px, 0.0, 1.0)
        return (1.0 + (self.gain - 1.0) * t).astype(np.float32)


@dataclass(frozen=True)
class FlightSpec:
    """Everything that defines one flight's image apart from the cattle.

    Attributes
    ----------
    id
        Flight id (PA1, PA2, PA3).
    acquired
        Acquisition time (AEST).
    width, height
        Image size, pixels.
    stated_transform
        The north-up transform written into the file (EPSG:28356).
    error
        The georeferencing error.
    footprint_px
        Valid-data polygon in pixel coordinates (col, row).
    exposure_gain
        Overall camera exposure relative to scene radiance.
    white_balance
        Per-band gains (R, G, B).
    warps
        Local stitching warps.
    seam
        The exposure seam.
    noise_dn
        Standard deviation of the camera noise left after mosaicking, DN.
    mask_encoding
        How the file marks nodata: ``alpha``, ``nodata`` (value 0) or ``internal_mask``.
    lawnmower_heading_deg
        Direction of the survey lines, clockwise from grid north.
    dropped_frames
        Photos removed for bad GPS (gaps in the footprint's edge).
    """

    id: str
    acquired: dt.datetime
    width: int
    height: int
    stated_transform: Affine
    error: GeorefError
    footprint_px: Polygon
    exposure_gain: float
    white_balance: tuple[float, float, float]
    warps: tuple[LocalWarp, ...] = field(default_factory=tuple)
    seam: ExposureSeam | None = None
    noise_dn: float = 0.8
    mask_encoding: str = "alpha"
    lawnmower_heading_deg: float = 0.0
    dropped_frames: int = 0

    @property
    def centre_stated(self) -> tuple[float, float]:
        """Image centre in the stated frame, metres."""
        x, y = self.stated_transform @ (self.width / 2, self.height / 2)
        return float(x), float(y)

    @property
    def stated_to_true(self) -> Affine:
        """Stated → true map coordinates."""
        return self.error.stated_to_true(self.centre_stated)

    @property
    def true_transform(self) -> Affine:
        """Pixel → true map coordinates (what the transform should have been)."""
        return self.stated_to_true @ self.stated_transform

    def render_grid(self) -> RenderGrid:
        """The grid to render: true mapping plus warps."""
        return RenderGrid(self.width, self.height, self.true_transform, self.warps)

    def footprint_stated(self) -> Polygon:
        """Valid-data polygon in stated map coordinates."""
        return _apply(self.stated_transform, self.footprint_px)

    def footprint_true(self) -> Polygon:
        """Valid-data polygon where it really is on the ground."""
        return _apply(self.true_transform, self.footprint_px)

    def true_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(col, row) of true map points (warps ignored)."""
        inv = ~self.true_transform
        return inv.a * x + inv.b * y + inv.c, inv.d * x + inv.e * y + inv.f


def _apply(a: Affine, geom: Polygon) -> Polygon:
    return affine_transform(geom, [a.a, a.b, a.d, a.e, a.c, a.f])


def lawnmower_footprint(rng: np.random.Generator, *, heading_deg: float, extent_px: float,
                        frame_px: tuple[float, float] = (520.0, 390.0),
                        sidelap: float = 0.6, frontlap: float = 0.8,
                        drop_probability: float = 0.04) -> tuple[Polygon, int]:
    """Union of photo footprints along a lawnmower pattern, centred on (0, 0).

    Parameters
    ----------
    heading_deg
        Direction of the flight lines, clockwise from grid north.
    extent_px
        Side of the planned square survey area, pixels.
    frame_px
        (across-track, along-track) size of one photo on the ground, pixels.
    sidelap, frontlap
        Overlap between neighbouring lines / consecutive photos.
    drop_probability
        Chance that a photo was removed (bad GPS), leaving a notch at the edge.

    Returns
    -------
    footprint, n_dropped
        Polygon in pixel units (x = col, y = row, centred on 0) and the number of
        photos dropped at the edge.
    """
    fw, fh = frame_px
    dt_ = fw * (1.0 - sidelap)
    ds = fh * (1.0 - frontlap)
    half = (extent_px - fw) / 2
    n_lines = int(round(2 * half / dt_)) + 1
    frames = []
    dropped = 0
    for k in range(n_lines):
        t = -half + k * (2 * half / max(1, n_lines - 1))
        s0 = -(extent_px - fh) / 2 + rng.uniform(-70.0, 50.0)
        s1 = (extent_px - fh) / 2 + rng.uniform(-50.0, 70.0)
        for s in np.arange(s0, s1 + 1e-6, ds):
            edge = k in (0, n_lines - 1) or s - s0 < 2 * ds or s1 - s < 2 * ds
            if edge and rng.uniform() < drop_probability * 4:
                dropped += 1
                continue
            yaw = rng.normal(0.0, 2.0)
            cx, cy = t + rng.normal(0.0, 6.0), s + rng.normal(0.0, 6.0)
            frames.append(rotate(box(cx - fw / 2, cy - fh / 2, cx + fw / 2, cy + fh / 2), yaw))
    union = shapely.union_all(frames)
    # Lines run along +row before rotation; rotating by h (x towards y) turns them to
    # ±(sin h, −cos h) in (col, row), i.e. heading h clockwise from grid north.
    union = rotate(union, heading_deg, origin=(0, 0))
    if union.geom_type != "Polygon":
        union = max(union.geoms, key=lambda g: g.area)
    return Polygon(union.exterior), dropped


def make_flight_spec(rng: np.random.Generator, flight_id: str, acquired: dt.datetime,
                     centre_xy: tuple[float, float], *, mask_encoding: str,
                     extent_m: float = 92.0) -> FlightSpec:
    """Draw one flight: footprint, georeferencing error, camera response.

    Warps and seams are added later (:func:`add_artefacts`), once the trees
    inside the footprint are known.
    """
    # Survey lines roughly along the paddock's grid (as planners lay them out).
    heading = float((rng.uniform(-10.0, 10.0) + 90.0 * rng.integers(0, 2)) % 180.0)
    extent_px = extent_m / UAV_GSD_M
    poly, dropped = lawnmower_footprint(rng, heading_deg=heading, extent_px=extent_px)
    minx, miny, maxx, maxy = poly.bounds
    margin = 6
    width = int(math.ceil(maxx - minx)) + 2 * margin
    height = int(math.ceil(maxy - miny)) + 2 * margin
    poly = affine_transform(poly, [1, 0, 0, 1, margin - minx, margin - miny])
    # Stated origin: where the footprint's centre is meant to be, to the millimetre.
    fcx, fcy = poly.centroid.x, poly.centroid.y
    x0 = round(centre_xy[0] - fcx * UAV_GSD_M + rng.uniform(-0.5, 0.5), 3)
    y0 = round(centre_xy[1] + fcy * UAV_GSD_M + rng.uniform(-0.5, 0.5), 3)
    stated = Affine(UAV_GSD_M, 0.0, x0, 0.0, -UAV_GSD_M, y0)

    mag = rng.uniform(0.5, 1.5)
    ang = rng.uniform(0.0, 2 * math.pi)
    err = GeorefError(shift_m=(round(mag * math.sin(ang), 4), round(mag * math.cos(ang), 4)),
                      rotation_deg=round(float(rng.choice([-1, 1]) * rng.uniform(0.1, 0.5)), 4),
                      scale=round(1.0 + float(rng.choice([-1, 1]) * rng.uniform(0.001, 0.005)),
                                  6))
    wb = (round(rng.uniform(0.94, 1.06), 4), 1.0, round(rng.uniform(0.92, 1.08), 4))
    return FlightSpec(id=flight_id, acquired=acquired, width=width, height=height,
                      stated_transform=stated, error=err, footprint_px=poly,
                      exposure_gain=round(rng.uniform(0.9, 1.1), 4), white_balance=wb,
                      noise_dn=0.6, mask_encoding=mask_encoding,
                      lawnmower_heading_deg=round(heading, 3), dropped_frames=dropped)


def add_artefacts(rng: np.random.Generator, spec: FlightSpec,
                  tree_positions: list[tuple[float, float, float]]) -> FlightSpec:
    """Add a local warp near a tree at the footprint's edge and a diagonal exposure seam.

    Parameters
    ----------
    tree_positions
        (x, y, crown radius) of trees in true map coordinates, metres.
    """
    fp = spec.footprint_px
    boundary = fp.exterior
    best = None
    for x, y, r in tree_positions:
        c, rr = spec.true_to_pixel(np.array(x), np.array(y))
        p = shapely.Point(float(c), float(rr))
        if fp.contains(p):
            d = boundary.distance(p)
            if best is None or d < best[0]:
                best = (d, float(c), float(rr), r)
    if best is None:  # no tree inside: warp near the edge closest to the centre
        q = boundary.interpolate(boundary.project(fp.centroid))
        best = (0.0, q.x, q.y, 4.0)
    _, c, r, crown = best
    del crown
    sigma_px = rng.uniform(2.0, 3.5) / UAV_GSD_M
    warp = LocalWarp(centre_px=(round(c, 2), round(r, 2)), sigma_px=round(sigma_px, 2),
                     amplitude_px=round(rng.uniform(3.0, 6.0), 3),
                     direction_rad=round(rng.uniform(0, 2 * math.pi), 4),
                     swirl_px=round(rng.uniform(1.0, 2.5), 3))
    # Seam: a diagonal line through a point near the centre of the footprint.
    cx, cy = fp.centroid.x + rng.uniform(-300, 300), fp.centroid.y + rng.uniform(-300, 300)
    ang = math.radians(rng.choice([1, -1]) * rng.uniform(30.0, 60.0))
    L = 4000.0
    seam = ExposureSeam(p0_px=(round(cx - L * math.cos(ang), 2), round(cy - L * math.sin(ang), 2)),
                        p1_px=(round(cx + L * math.cos(ang), 2), round(cy + L * math.sin(ang), 2)),
                        gain=round(float(rng.choice([-1, 1]) * rng.uniform(0.04, 0.08)) + 1.0, 4))
    return FlightSpec(**{**spec.__dict__, "warps": (warp,), "seam": seam})


def valid_mask(rng: np.random.Generator, spec: FlightSpec) -> np.ndarray:
    """Rasterised footprint with a ragged (±2 px) edge; True = valid."""
    canvas = np.zeros((spec.height, spec.width), dtype=np.uint8)
    pts = np.round((np.asarray(spec.footprint_px.exterior.coords) - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(canvas, [pts], 255, cv2.LINE_8, shift=4)
    inside = cv2.distanceTransform(canvas, cv2.DIST_L2, 3)
    outside = cv2.distanceTransform(255 - canvas, cv2.DIST_L2, 3)
    signed = inside - outside
    jitter = smooth_noise(rng, canvas.shape, 3.0) * np.float32(1.6)
    mask = signed + jitter > 0.5
    mask[:2, :] = mask[-2:, :] = False
    mask[:, :2] = mask[:, -2:] = False
    return mask


def camera(radiance: np.ndarray, spec: FlightSpec, mask: np.ndarray,
           rng: np.random.Generator) -> np.ndarray:
    """Exposure, white balance, seam, noise and 8-bit quantisation of a flight.

    Valid pixels are clipped to 1–255 (so no valid pixel is ever (0, 0, 0));
    invalid pixels are 0.
    """
    gains = spec.exposure_gain * np.asarray(spec.white_balance, dtype=np.float32)
    img = radiance * gains[:, None, None]
    if spec.seam is not None:
        img *= spec.seam.factor(spec.height, spec.width)[None]
    img += rng.standard_normal(img.shape, dtype=np.float32) * np.float32(spec.noise_dn)
    out = np.clip(np.rint(img), 1, 255).astype(np.uint8)
    out[:, ~mask] = 0
    return out


def flight_truth(spec: FlightSpec) -> dict:
    """JSON-able description of a flight's geometry and camera (for truth.json)."""
    a = spec.stated_to_true
    inv = ~a
    t = spec.true_transform
    return {
        "crs": "EPSG:28356",
        "acquired": spec.acquired.isoformat(),
        "width": spec.width, "height": spec.height,
        "stated_transform": [spec.stated_transform.a, spec.stated_transform.b,
                             spec.stated_transform.c, spec.stated_transform.d,
                             spec.stated_transform.e, spec.stated_transform.f],
        "true_transform": [_r(t.a, 12), _r(t.b, 12), _r(t.c, 6), _r(t.d, 12), _r(t.e, 12),
                           _r(t.f, 6)],
        "georef_error": {
            "shift_m": list(spec.error.shift_m),
            "rotation_deg": spec.error.rotation_deg,
            "scale": spec.error.scale,
            "about_stated_xy": [_r(v, 6) for v in spec.centre_stated],
            "stated_to_true": [[_r(a.a, 12), _r(a.b, 12), _r(a.c, 6)],
                               [_r(a.d, 12), _r(a.e, 12), _r(a.f, 6)]],
            "true_to_stated": [[_r(inv.a, 12), _r(inv.b, 12), _r(inv.c, 6)],
                               [_r(inv.d, 12), _r(inv.e, 12), _r(inv.f, 6)]],
        },
        "camera": {"exposure_gain": spec.exposure_gain,
                   "white_balance_rgb": list(spec.white_balance),
                   "noise_sigma_dn": spec.noise_dn},
        "mask_encoding": spec.mask_encoding,
        "lawnmower_heading_deg": spec.lawnmower_heading_deg,
        "dropped_frames": spec.dropped_frames,
        "artefacts": {
            "local_warps": [{"centre_px": list(w.centre_px), "sigma_px": w.sigma_px,
                             "amplitude_px": w.amplitude_px,
                             "direction_rad": w.direction_rad, "swirl_px": w.swirl_px,
                             "centre_stated_xy": [_r(v, 4) for v in
                                                  spec.stated_transform @ w.centre_px]}
                            for w in spec.warps],
            "exposure_seam": None if spec.seam is None else {
                "p0_px": list(spec.seam.p0_px), "p1_px": list(spec.seam.p1_px),
                "gain_left": spec.seam.gain, "width_px": spec.seam.width_px},
        },
    }


def _r(v: float, nd: int) -> float:
    return round(float(v), nd)
