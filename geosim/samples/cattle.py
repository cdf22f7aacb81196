"""Cattle seen from above: body and head shapes, coats, shading, cast shadows, and
where a herd stands at each acquisition.

Seen at nadir from 5 cm pixels a cow is a rounded-rectangular body
(superellipse) with a narrower head on a neck that may be turned; legs are
hidden under the body but show in the shadow. Sizes: nose-to-rump length 2.0–2.6 m
and body width 0.7–1.0 m. Coats follow common Southern Highlands breeds.

Colour statistics from a real nadir frame of stock on NSW pasture
(``../shared/realdata/cattle_frame_nsw.jpg``, 11 boxed animals, not used at run
time): light coats are 1.95× as bright as the pasture around them, and the
brightness of sunlit coat pixels varies by 12–16 % (coefficient of variation),
which the shading and hair texture reproduce.

Conventions: ``heading_deg`` is the direction the head points, clockwise from
grid north of EPSG:28356; ``(x, y)`` is the animal's body-axis mid-point
(midway between rump and nose with the head straight); its label centre
``centre_xy`` is the centre of the outline's axis-aligned box on the map.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import shapely

from geosim.samples.illumination import Illumination
from geosim.samples.render_grid import RenderGrid
from geosim.samples.textures import smoothstep
from geosim.samples.trees import segment_coverage

# name → (body RGB, face RGB or None, stripe RGB or None, sheen DN, share of the herd)
COATS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float] | None,
                       tuple[float, float, float] | None, float, float]] = {
    "black_angus": ((30.0, 27.0, 26.0), None, None, 34.0, 0.33),
    "black_baldy": ((31.0, 28.0, 27.0), (212.0, 206.0, 194.0), None, 30.0, 0.15),
    "hereford": ((128.0, 60.0, 34.0), (214.0, 208.0, 196.0), None, 16.0, 0.20),
    "red_angus": ((140.0, 72.0, 40.0), None, None, 20.0, 0.10),
    "murray_grey": ((170.0, 163.0, 152.0), None, None, 10.0, 0.13),
    "brindle": ((100.0, 66.0, 43.0), None, (44.0, 33.0, 27.0), 14.0, 0.09),
}

BODY_EXPONENT = 2.6        # superellipse exponent of the body outline
BODY_HEIGHTS_M = (0.6, 1.35)   # torso: bottom and top of the part that casts the shadow
HEAD_HEIGHTS_M = {True: (0.15, 0.45), False: (1.0, 1.3)}  # grazing / head up
LEG_TOP_M = 0.6
SLICE_STEP_M = 0.1             # largest shadow displacement between height slices


@dataclass(frozen=True)
class Animal:
    """One animal's identity and appearance (constant between acquisitions).

    Attributes
    ----------
    id
        Animal number, stable across acquisitions.
    coat
        Coat name (a key of :data:`COATS`).
    length_m, width_m
        Nose-to-rump length and body width, metres.
    body_rgb, face_rgb, stripe_rgb
        Coat albedo (DN of a sunlit flat surface); white face and brindle stripes
        where the breed has them.
    sheen_dn
        Strength of the specular highlight, DN.
    texture_seed
        Seed of the hair texture.
    """

    id: int
    coat: str
    length_m: float
    width_m: float
    body_rgb: tuple[float, float, float]
    face_rgb: tuple[float, float, float] | None
    stripe_rgb: tuple[float, float, float] | None
    sheen_dn: float
    texture_seed: int


@dataclass(frozen=True)
class Cow:
    """An animal's pose at one acquisition.

    Attributes
    ----------
    animal
        Who it is.
    x, y
        Body-axis mid-point, metres (EPSG:28356).
    heading_deg
        Direction the head points, clockwise from grid north, degrees in [0, 360).
    head_turn_deg
        Neck bend relative to the body axis (positive to the right), degrees.
    grazing
        Head down (its shadow is short) or up.
    """

    animal: Animal
    x: float
    y: float
    heading_deg: float
    head_turn_deg: float
    grazing: bool

    # ---------------------------------------------------------------- geometry
    def _axes(self) -> tuple[np.ndarray, np.ndarray]:
        h = math.radians(self.heading_deg)
        forward = np.array([math.sin(h), math.cos(h)])
        right = np.array([math.cos(h), -math.sin(h)])
        return forward, right

    def _parts(self) -> dict[str, float]:
        L, W = self.animal.length_m, self.animal.width_m
        return {"ub": -0.1 * L, "ab": 0.4 * L, "bb": W / 2, "un": 0.24 * L,
                "ah": 0.13 * L, "bh": 0.22 * W}

    def local(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Body coordinates: u forward along the heading, v to the right, metres."""
        f, r = self._axes()
        dx, dy = x - self.x, y - self.y
        return dx * f[0] + dy * f[1], dx * r[0] + dy * r[1]

    def _head_frame(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self._parts()
        t = math.radians(self.head_turn_deg)
        du, dv = u - p["un"], v
        return du * math.cos(t) + dv * math.sin(t), -du * math.sin(t) + dv * math.cos(t)

    def inside(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Boolean masks (body, head incl. ears) at body coordinates."""
        p = self._parts()
        body = (np.abs((u - p["ub"]) / p["ab"]) ** BODY_EXPONENT
                + np.abs(v / p["bb"]) ** BODY_EXPONENT) <= 1.0
        hu, hv = self._head_frame(u, v)
        head = ((hu - p["ah"]) / p["ah"]) ** 2 + (hv / p["bh"]) ** 2 <= 1.0
        for side in (-1.0, 1.0):
            head |= ((hu - 0.45 * p["ah"]) / 0.085) ** 2 \
                + ((hv - side * (p["bh"] + 0.05)) / 0.045) ** 2 <= 1.0
        return body, head

    def outline(self, n: int = 96) -> np.ndarray:
        """(N, 2) map coordinates of points on the outline (body, head and ears)."""
        p = self._parts()
        t = np.linspace(0, 2 * np.pi, n, endpoint=False)
        e = 2.0 / BODY_EXPONENT
        bu = p["ub"] + p["ab"] * np.sign(np.cos(t)) * np.abs(np.cos(t)) ** e
        bv = p["bb"] * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** e
        hu_l = np.r_[p["ah"] + p["ah"] * np.cos(t),
                     0.45 * p["ah"] + 0.085 * np.cos(t), 0.45 * p["ah"] + 0.085 * np.cos(t)]
        hv_l = np.r_[p["bh"] * np.sin(t), p["bh"] + 0.05 + 0.045 * np.sin(t),
                     -(p["bh"] + 0.05) + 0.045 * np.sin(t)]
        a = math.radians(self.head_turn_deg)
        hu = p["un"] + hu_l * math.cos(a) - hv_l * math.sin(a)
        hv = hu_l * math.sin(a) + hv_l * math.cos(a)
        u = np.r_[bu, hu]
        v = np.r_[bv, hv]
        f, r = self._axes()
        return np.c_[self.x + u * f[0] + v * r[0], self.y + u * f[1] + v * r[1]]

    def centre_xy(self) -> tuple[float, float]:
        """Centre of the outline's axis-aligned box on the map, metres."""
        o = self.outline()
        return (float((o[:, 0].min() + o[:, 0].max()) / 2),
                float((o[:, 1].min() + o[:, 1].max()) / 2))

    def leg_points(self) -> np.ndarray:
        """(4, 2) map positions of the hooves."""
        p = self._parts()
        f, r = self._axes()
        pts = []
        for uu in (p["ub"] + 0.68 * p["ab"], p["ub"] - 0.72 * p["ab"]):
            for vv in (-0.55 * p["bb"], 0.55 * p["bb"]):
                pts.append([self.x + uu * f[0] + vv * r[0], self.y + uu * f[1] + vv * r[1]])
        return np.array(pts)


# -------------------------------------------------------------------- herd


def make_herd(rng: np.random.Generator, n: int) -> list[Animal]:
    """``n`` animals with breed coats, sizes and colour variation.

    Lengths 2.0–2.6 m and widths 0.7–1.0 m, correlated (big animals are wide).
    """
    names = list(COATS)
    share = np.array([COATS[k][4] for k in names])
    animals = []
    for i in range(n):
        coat = names[int(rng.choice(len(names), p=share / share.sum()))]
        body, face, stripe, sheen, _ = COATS[coat]
        size = rng.uniform(0.0, 1.0)
        length = 2.0 + 0.6 * np.clip(size + rng.normal(0, 0.12), 0.0, 1.0)
        width = 0.7 + 0.3 * np.clip(size + rng.normal(0, 0.15), 0.0, 1.0)
        gain = rng.uniform(0.85, 1.15)
        tint = rng.normal(0.0, 0.03, 3)
        col = tuple(float(c * gain * (1 + t)) for c, t in zip(body, tint, strict=True))
        animals.append(Animal(id=i + 1, coat=coat, length_m=float(length), width_m=float(width),
                              body_rgb=col, face_rgb=face, stripe_rgb=stripe,
                              sheen_dn=float(sheen), texture_seed=int(rng.integers(0, 2**31))))
    return animals


def _spaced(x: float, y: float, placed: Sequence[Cow], min_spacing_m: float) -> bool:
    return all(math.hypot(x - c.x, y - c.y) >= min_spacing_m for c in placed)


def place_group(rng: np.random.Generator, animals: Sequence[Animal], centre: np.ndarray,
                spread_m: float, allowed: shapely.Geometry, placed: list[Cow], *,
                min_spacing_m: float = 2.8, mean_heading_deg: float | None = None) -> list[Cow]:
    """Place a group of animals around ``centre`` inside ``allowed``.

    Positions are drawn from a Gaussian of ``spread_m`` (widened when crowded);
    headings scatter ±50° about the group's grazing direction.
    """
    shapely.prepare(allowed)
    heading0 = rng.uniform(0, 360) if mean_heading_deg is None else mean_heading_deg
    out = []
    for a in animals:
        spread = spread_m
        for attempt in range(400):
            x, y = centre + rng.normal(0.0, spread, 2)
            if shapely.contains_xy(allowed, x, y) and _spaced(x, y, placed + out,
                                                              min_spacing_m):
                break
            if attempt % 40 == 39:
                spread *= 1.3
        else:
            raise RuntimeError(f"could not place animal {a.id} near {centre}")
        out.append(Cow(animal=a, x=float(x), y=float(y),
                       heading_deg=float((heading0 + rng.normal(0, 50)) % 360),
                       head_turn_deg=float(rng.uniform(-30, 30)),
                       grazing=bool(rng.uniform() < 0.7)))
    return out


def move_herd(rng: np.random.Generator, cows: Sequence[Cow], group_of: dict[int, int],
              group_centres: dict[int, np.ndarray], allowed: shapely.Geometry, *,
              stay_fraction: float = 0.35, spread_m: float = 7.0, min_spacing_m: float = 2.8
              ) -> list[Cow]:
    """The herd at the next acquisition: some animals stand where they were, the
    others graze around their group's new centre."""
    shapely.prepare(allowed)
    stay = rng.uniform(0, 1, len(cows)) < stay_fraction
    kept = [c for c, s in zip(cows, stay, strict=True) if s]
    out: list[Cow] = list(kept)
    for c, s in zip(cows, stay, strict=True):
        if s:
            continue
        g = group_of[c.animal.id]
        moved = place_group(rng, [c.animal], group_centres[g], spread_m, allowed, out,
                            min_spacing_m=min_spacing_m)[0]
        out.append(moved)
    order = {c.animal.id: i for i, c in enumerate(cows)}
    return sorted(out, key=lambda c: order[c.animal.id])


# -------------------------------------------------------------------- rendering

_SUB = (np.arange(4) + 0.5) / 4 - 0.5  # 4×4 sub-pixel offsets


def coverage(cow: Cow, grid: RenderGrid, x: np.ndarray, y: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
    """Supersampled (4×4) coverage of body and head at the pixels whose centres are x, y."""
    j = grid.jacobian
    body = np.zeros(x.shape, dtype=np.float32)
    head = np.zeros(x.shape, dtype=np.float32)
    for dc in _SUB:
        for dr in _SUB:
            u, v = cow.local(x + j[0, 0] * dc + j[0, 1] * dr, y + j[1, 0] * dc + j[1, 1] * dr)
            b, h = cow.inside(u, v)
            body += b
            head += h & ~b
    return body / 16.0, head / 16.0


def _shift(img: np.ndarray, grid: RenderGrid, offset_m: np.ndarray) -> np.ndarray:
    """Move an image patch by a map offset (bilinear), zeros shifted in."""
    d = np.linalg.solve(grid.jacobian, offset_m)
    m = np.array([[1.0, 0.0, d[0]], [0.0, 1.0, d[1]]], dtype=np.float64)
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def cow_window(grid: RenderGrid, cow: Cow, illum: Illumination | None = None
               ) -> tuple[int, int, int, int] | None:
    """Pixel window covering the animal and, when ``illum`` is given, its shadow."""
    r = cow.animal.length_m / 2 + 0.3
    extra = [] if illum is None else [tuple(illum.sun.shadow_offset_m(1.4))]
    return grid.window_for_disc(cow.x, cow.y, r, extra=extra, margin_px=3)


def shadow_coverage(cow: Cow, grid: RenderGrid, illum: Illumination, x: np.ndarray,
                    y: np.ndarray, body: np.ndarray, head: np.ndarray) -> np.ndarray:
    """Coverage of the animal's cast shadow on the ground at a window's pixels.

    Torso slices at 0.6–1.35 m, the head at 0.15–0.45 m (grazing) or 1.0–1.3 m, and
    four legs from the ground to 0.6 m, each moved by h · cot(el) away from the sun.

    Parameters
    ----------
    x, y
        Map coordinates of the window's pixel centres.
    body, head
        The animal's coverage (:func:`coverage`) on the same window.
    """
    shadow = np.zeros_like(body)
    cot = 1.0 / math.tan(math.radians(illum.sun.elevation_deg))
    for part, (h0, h1) in ((body, BODY_HEIGHTS_M), (head, HEAD_HEIGHTS_M[cow.grazing])):
        n = max(2, int(math.ceil((h1 - h0) * cot / SLICE_STEP_M)) + 1)
        for h in np.linspace(h0, h1, n):
            shadow = np.maximum(shadow, _shift(part, grid, illum.sun.shadow_offset_m(h)))
    px = grid.pixel_size_m
    top = illum.sun.shadow_offset_m(LEG_TOP_M)
    for lx, ly in cow.leg_points():
        shadow = np.maximum(shadow, segment_coverage(x, y, (lx, ly), (lx + top[0], ly + top[1]),
                                                     0.12, px))
    return shadow


def _hair(cow: Cow, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Hair texture (±5 %) fixed to the animal's body, from its texture seed."""
    rng = np.random.default_rng(cow.animal.texture_seed)
    res = 0.03
    n_u, n_v = int(3.2 / res), int(1.4 / res)
    tex = cv2.GaussianBlur(rng.standard_normal((n_v, n_u), dtype=np.float32), (0, 0), 1.2)
    tex /= max(float(tex.std()), 1e-6)
    mx = ((u + 1.6) / res).astype(np.float32)
    my = ((v + 0.7) / res).astype(np.float32)
    return 1.0 + 0.05 * cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def cow_layer(cow: Cow, illum: Illumination, x: np.ndarray, y: np.ndarray,
              body_cov: np.ndarray, head_cov: np.ndarray, shade_cover: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Coverage (rows, cols) and shaded radiance (3, rows, cols) of the animal.

    Parameters
    ----------
    x, y
        Map coordinates of the window's pixel centres.
    body_cov, head_cov
        The animal's coverage (:func:`coverage`) on the same window.
    shade_cover
        Shadow cast on the animal by trees, [0, 1], at the same pixels.
    """
    a = cow.animal
    p = cow._parts()
    cover = np.clip(body_cov + head_cov, 0.0, 1.0)
    u, v = cow.local(x, y)
    # Body as an ellipsoid (semi-height 0.32 m), head as a smaller one (0.14 m).
    bu = (u - p["ub"]) / p["ab"]
    bv = v / p["bb"]
    hu, hv = cow._head_frame(u, v)
    hu = (hu - p["ah"]) / p["ah"]
    hv = hv / p["bh"]
    in_head = head_cov > body_cov
    eu = np.where(in_head, hu, bu)
    ev = np.where(in_head, hv, bv)
    ea = np.where(in_head, p["ah"], p["ab"])
    eb = np.where(in_head, p["bh"], p["bb"])
    ec = np.where(in_head, 0.14, 0.32)
    rho2 = np.minimum(eu * eu + ev * ev, 0.985)
    z = ec * np.sqrt(1.0 - rho2)
    nu, nv, nz = eu / ea, ev / eb, z / (ec * ec)
    # Head axes are turned; rotate the head normal back into body axes.
    t = math.radians(cow.head_turn_deg)
    nu_b = np.where(in_head, nu * math.cos(t) - nv * math.sin(t), nu)
    nv_b = np.where(in_head, nu * math.sin(t) + nv * math.cos(t), nv)
    f, r = cow._axes()
    ne = nu_b * f[0] + nv_b * r[0]
    nn = nu_b * f[1] + nv_b * r[1]
    norm = np.sqrt(ne * ne + nn * nn + nz * nz)
    ne, nn, nz = ne / norm, nn / norm, nz / norm
    shade = illum.surface_factor(ne, nn, nz, shadow=shade_cover, sky_view=1.0)

    albedo = np.empty((3, *x.shape), dtype=np.float32)
    albedo[:] = np.asarray(a.body_rgb, dtype=np.float32)[:, None, None]
    if a.stripe_rgb is not None:  # irregular dark brindle streaks across the body
        streak = _hair(cow, u, 0.2 * v) - 1.0
        stripes = smoothstep(0.01, 0.06, streak) * (0.65 * ~in_head)
        albedo += (np.asarray(a.stripe_rgb, dtype=np.float32)[:, None, None] - albedo) \
            * stripes[None]
    if a.face_rgb is not None:
        face = in_head | ((bu > 0.82) & (np.abs(bv) < 0.35))
        albedo = np.where(face[None], np.asarray(a.face_rgb, dtype=np.float32)[:, None, None],
                          albedo)
    albedo *= _hair(cow, u, v)[None]
    # Sheen: a soft specular lobe around the half-vector of sun and nadir view.
    s = illum.sun.vector()
    hv_ = s + np.array([0.0, 0.0, 1.0])
    hv_ /= np.linalg.norm(hv_)
    spec = np.maximum(0.0, ne * hv_[0] + nn * hv_[1] + nz * hv_[2]) ** 14
    radiance = albedo * shade + (a.sheen_dn * spec * (1.0 - shade_cover))[None]
    return cover, radiance.astype(np.float32)
