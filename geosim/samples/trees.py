"""Eucalypt crowns: a clumped canopy with leaf gaps, its shading and its cast shadow.

Each tree is a small north-up raster (5 cm) of crown opacity, foliage albedo
and surface normal, built once from the seed. Renderings sample it at their own
pixel positions; the shadow on the ground is the crown's opacity looked up along
the ray towards the sun at several heights through the crown.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from affine import Affine

from geosim.samples.illumination import Illumination
from geosim.samples.render_grid import RenderGrid
from geosim.samples.textures import smooth_noise, smoothstep
from geosim.samples.world import Tree

FOLIAGE = np.array([60.0, 76.0, 54.0], dtype=np.float32)        # eucalypt leaves, sunlit
FOLIAGE_GREY = np.array([84.0, 94.0, 80.0], dtype=np.float32)   # glaucous clumps
PATCH_RES_M = 0.05


@dataclass(frozen=True)
class CrownPatch:
    """A tree's crown on a small north-up raster.

    Attributes
    ----------
    tree
        The tree.
    transform
        Patch affine (pixel corner → map).
    data
        (rows, cols, 7) float32: opacity, albedo R, G, B, normal east, north, up.
    extent_m
        Half-side of the patch, metres from the trunk.
    """

    tree: Tree
    transform: Affine
    data: np.ndarray
    extent_m: float

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(rows, cols, 7) bilinear samples at map points (zeros off the patch)."""
        inv = ~self.transform
        mx = (inv.a * x + inv.b * y + inv.c - 0.5).astype(np.float32)
        my = (inv.d * x + inv.e * y + inv.f - 0.5).astype(np.float32)
        return cv2.remap(self.data, mx, my, interpolation=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def build_crown(rng: np.random.Generator, tree: Tree) -> CrownPatch:
    """Make the crown patch of one tree.

    The crown is a union of 8–16 dome-shaped foliage clumps; leaf gaps come from
    a 10–20 cm texture; normals follow the clump domes plus leaf-scale relief.
    """
    r = tree.crown_radius_m
    extent = 1.45 * r + 0.5
    n = int(math.ceil(2 * extent / PATCH_RES_M))
    transform = Affine(PATCH_RES_M, 0.0, tree.x - extent, 0.0, -PATCH_RES_M, tree.y + extent)
    c = (np.arange(n) + 0.5) * PATCH_RES_M - extent
    dx, dy = np.meshgrid(c, -c)
    dx = dx.astype(np.float32)
    dy = dy.astype(np.float32)

    n_clumps = int(8 + 1.3 * r)
    height = np.full((n, n), -1.0, dtype=np.float32)
    cover = np.zeros((n, n), dtype=np.float32)
    tint = np.zeros((n, n), dtype=np.float32)
    for k in range(n_clumps):
        rho = math.sqrt(rng.uniform(0.0, 1.0)) * 0.72 * r
        phi = rng.uniform(0.0, 2 * math.pi)
        cx, cy = rho * math.cos(phi), rho * math.sin(phi)
        cr = r * rng.uniform(0.32, 0.52)
        d2 = (dx - cx) ** 2 + (dy - cy) ** 2
        inside = d2 < cr * cr
        dome = np.where(inside, np.sqrt(np.maximum(cr * cr - d2, 0.0)), -1.0)
        top = dome * 0.8 - 0.25 * rho
        upd = inside & (top > height)
        height = np.where(upd, top, height)
        tint = np.where(upd, np.float32(rng.uniform(-1.0, 1.0)), tint)
        edge = 1.0 - np.sqrt(d2) / cr
        cover = np.maximum(cover, np.clip(edge * 4.0, 0.0, 1.0))
        del k
    leaves = smooth_noise(rng, (n, n), 1.6) + 0.8 * smooth_noise(rng, (n, n), 6.0)
    density = smoothstep(-1.2, 0.4, leaves + 1.4 * cover - 1.0)
    alpha = np.clip(cover * density, 0.0, 1.0)

    relief = cv2.GaussianBlur(np.maximum(height, 0.0), (0, 0), 6.0) \
        + np.float32(0.02) * smooth_noise(rng, (n, n), 2.0)
    gy, gx = np.gradient(relief, PATCH_RES_M)
    # Row index grows southwards: d/dnorth = −d/drow.
    nx, ny, nz = -gx, gy, np.ones_like(gx)
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    albedo = FOLIAGE[None, None, :] + (FOLIAGE_GREY - FOLIAGE)[None, None, :] * \
        np.clip(0.5 + 0.5 * tint, 0.0, 1.0)[..., None] * 0.6
    albedo = albedo * (1.0 + 0.12 * leaves[..., None])
    data = np.concatenate([alpha[..., None], albedo, (nx / norm)[..., None],
                           (ny / norm)[..., None], (nz / norm)[..., None]], axis=-1)
    return CrownPatch(tree=tree, transform=transform, data=data.astype(np.float32),
                      extent_m=extent)


def _shadow_heights(tree: Tree) -> np.ndarray:
    depth = tree.height_m - tree.crown_base_m
    return tree.crown_base_m + depth * np.array([0.2, 0.4, 0.6, 0.8])


def shadow_window(grid: RenderGrid, patch: CrownPatch, illum: Illumination
                  ) -> tuple[int, int, int, int] | None:
    """Pixel window of a crown's cast shadow (including the trunk's)."""
    t = patch.tree
    offsets = [tuple(illum.sun.shadow_offset_m(h)) for h in (0.0, t.crown_base_m, t.height_m)]
    return grid.window_for_disc(t.x, t.y, patch.extent_m, extra=offsets, margin_px=4)


def shadow_coverage(patch: CrownPatch, illum: Illumination, x: np.ndarray, y: np.ndarray,
                    px_m: float) -> np.ndarray:
    """Shadow coverage in [0, 1] of a crown and trunk on the ground at map points.

    A ground point is shadowed by foliage at height h if the crown is opaque at
    the point h · cot(el) towards the sun; the crown's cross-section shrinks
    towards its base and top (ellipsoidal profile).
    """
    t = patch.tree
    depth = t.height_m - t.crown_base_m
    mid = t.crown_base_m + depth / 2
    cover = np.zeros(x.shape, dtype=np.float32)
    for h in _shadow_heights(t):
        off = illum.sun.shadow_offset_m(h)
        w = math.sqrt(max(0.15, 1.0 - ((h - mid) / (0.55 * depth)) ** 2))
        qx = t.x + (x - off[0] - t.x) / w
        qy = t.y + (y - off[1] - t.y) / w
        cover = np.maximum(cover, patch.sample(qx, qy)[..., 0])
    # Trunk: a 0.35 m wide post from the ground to the crown base.
    end = illum.sun.shadow_offset_m(t.crown_base_m)
    cover = np.maximum(cover, segment_coverage(x, y, (t.x, t.y), (t.x + end[0], t.y + end[1]),
                                               0.35, px_m))
    # Penumbra: the sun's disc (0.53°) blurs the edge by ~distance × 0.0093.
    sigma_px = max(0.5, 0.5 * 0.0093 * mid / max(illum.sin_el, 0.1) / px_m)
    return cv2.GaussianBlur(cover, (0, 0), sigma_px)


def segment_coverage(x: np.ndarray, y: np.ndarray, a: tuple[float, float],
                     b: tuple[float, float], width_m: float, px_m: float) -> np.ndarray:
    """Anti-aliased coverage of a capsule (segment a–b of ``width_m``) at map points.

    Widths under a pixel give a proportionally faint one-pixel line.
    """
    ax, ay = a
    vx, vy = b[0] - ax, b[1] - ay
    ll = vx * vx + vy * vy
    if ll > 0:
        t = np.clip(((x - ax) * vx + (y - ay) * vy) / ll, 0.0, 1.0)
    else:
        t = np.zeros_like(x)
    d = np.hypot(x - ax - t * vx, y - ay - t * vy)
    return line_profile(d, width_m, px_m)


def line_profile(d: np.ndarray, width_m: float, px_m: float) -> np.ndarray:
    """Coverage of a pixel whose centre is ``d`` metres from a line of ``width_m``."""
    if width_m >= px_m:
        return np.clip(0.5 + (width_m / 2 - d) / px_m, 0.0, 1.0).astype(np.float32)
    return (width_m / px_m * np.clip(1.0 - d / px_m, 0.0, 1.0)).astype(np.float32)


def crown_layer(patch: CrownPatch, illum: Illumination, x: np.ndarray, y: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """Crown opacity (rows, cols) and shaded radiance (3, rows, cols) at map points."""
    s = patch.sample(x, y)
    alpha = s[..., 0]
    shade = illum.surface_factor(s[..., 4], s[..., 5], s[..., 6], sky_view=0.75)
    radiance = np.moveaxis(s[..., 1:4], -1, 0) * shade
    return alpha, radiance
