"""A held-out flight with a known smooth warp + global similarity error, from real imagery.

Used by ``tests/test_align_local.py`` and ``benchmarks/bench_local_align.py``. Truth is the
known mapping ``W`` (stated site-CRS point of the moving flight → true ground), never the
code under test:

* reference flight: the real Brazil pasture orthomosaic (EPSG:3395, ~0.1 m) as delivered,
  with its south-east corner cut away (alpha 0), so part of the moving flight lies beyond
  the reference footprint (where AROSICS's local mode extrapolated to 20–44 px errors);
* moving flight: the same ground resampled onto an EPSG:4326 grid whose stated position is
  wrong by a similarity (rotation, scale, shift) *and* a smooth stitching-like displacement
  of up to ``amplitude_px`` per axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rasterio
from affine import Affine
from pyproj import Transformer

BRAZIL = "brazil_pasture_10cm_epsg3395.tif"
GSD_M = 0.1


@dataclass(frozen=True)
class WarpCase:
    """Files and truth of one case."""

    site_path: Path
    ref_path: Path
    mov_path: Path
    site_crs: str
    centre_m: tuple[float, float]
    rotation_deg: float
    scale: float
    shift_m: tuple[float, float]
    amplitude_px: float

    def warp_m(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Smooth displacement (metres, site CRS) added after the similarity."""
        cx, cy = self.centre_m
        a = self.amplitude_px * GSD_M
        ux = a * np.sin(2 * np.pi * (x - cx) / 140.0 + 0.3) * np.cos(2 * np.pi * (y - cy) / 170.0)
        uy = a * 0.8 * np.cos(2 * np.pi * (x - cx) / 110.0) * np.sin(2 * np.pi * (y - cy) / 130.0
                                                                   + 0.5)
        return ux, uy

    def truth(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``W``: a point as stated by the moving flight (site CRS) → the true ground point."""
        cx, cy = self.centre_m
        th = math.radians(self.rotation_deg)
        c, s = self.scale * math.cos(th), self.scale * math.sin(th)
        qx = cx + self.shift_m[0] + c * (x - cx) - s * (y - cy)
        qy = cy + self.shift_m[1] + s * (x - cx) + c * (y - cy)
        ux, uy = self.warp_m(qx, qy)
        return qx + ux, qy + uy


def utm_epsg(lon: float, lat: float) -> str:
    """WGS 84 / UTM zone of a point."""
    zone = int((lon + 180) // 6) + 1
    return f"EPSG:{(32600 if lat >= 0 else 32700) + zone}"


def _write_rgba(path: Path, rgb: np.ndarray, alpha: np.ndarray, crs: str, transform: Affine
                ) -> None:
    from rasterio.enums import ColorInterp

    with rasterio.open(path, "w", driver="GTiff", width=rgb.shape[2], height=rgb.shape[1],
                       count=4, dtype="uint8", crs=crs, transform=transform,
                       compress="deflate", tiled=True) as ds:
        ds.write(rgb, [1, 2, 3])
        ds.write(alpha, 4)
        ds.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue, ColorInterp.alpha]


def make_case(realdata: Path, folder: Path, *, amplitude_px: float = 2.5,
              rotation_deg: float = 0.35, scale: float = 1.004,
              shift_m: tuple[float, float] = (0.63, -0.41), align_model: str = "local"
              ) -> WarpCase:
    """Write the reference, the warped moving flight and a site file into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    with rasterio.open(realdata / BRAZIL) as ds:
        img = ds.read([1, 2, 3])
        src_t, src_crs = ds.transform, ds.crs.to_string()
        b = ds.bounds
    n_r, n_c = img.shape[1:]
    # reference: as delivered, minus a south-east triangle (beyond it: no reference)
    rr, cc = np.mgrid[0:n_r, 0:n_c]
    alpha = np.where(rr + cc > 1.45 * n_r, 0, 255).astype(np.uint8)
    ref_path = folder / "reference_epsg3395.tif"
    _write_rgba(ref_path, img, alpha, src_crs, src_t)

    to_ll = Transformer.from_crs(src_crs, "EPSG:4326", always_xy=True)
    lon0, lat0 = to_ll.transform((b.left + b.right) / 2, (b.bottom + b.top) / 2)
    site_crs = utm_epsg(lon0, lat0)
    site = Transformer.from_crs(src_crs, site_crs, always_xy=True)
    cx, cy = site.transform((b.left + b.right) / 2, (b.bottom + b.top) / 2)
    case = WarpCase(folder / "site.toml", ref_path, folder / "moving_epsg4326.tif", site_crs,
                    (cx, cy), rotation_deg, scale, tuple(shift_m), amplitude_px)

    # moving flight: an EPSG:4326 grid inside the reference's extent, ~0.1 m pixels
    ll = [to_ll.transform(x, y) for x, y in ((b.left, b.bottom), (b.right, b.top))]
    (lo0, la0), (lo1, la1) = ll
    m = 0.03
    lo0, lo1 = lo0 + m * (lo1 - lo0), lo1 - m * (lo1 - lo0)
    la0, la1 = la0 + m * (la1 - la0), la1 - m * (la1 - la0)
    dlat = GSD_M / 111_320.0
    dlon = dlat / math.cos(math.radians(lat0))
    w, h = int((lo1 - lo0) / dlon), int((la1 - la0) / dlat)
    mov_t = Affine(dlon, 0, lo0, 0, -dlat, la1)
    to_site = Transformer.from_crs("EPSG:4326", site_crs, always_xy=True)
    to_src = Transformer.from_crs(site_crs, src_crs, always_xy=True)
    inv_src = ~src_t
    rgb = np.zeros((3, h, w), np.uint8)
    valid = np.zeros((h, w), np.uint8)
    for r0 in range(0, h, 512):  # in strips: bounded memory
        r1 = min(h, r0 + 512)
        c, r = np.meshgrid(np.arange(w) + 0.5, np.arange(r0, r1) + 0.5)
        lon, lat = mov_t * (c, r)
        sx, sy = to_site.transform(lon, lat)
        gx, gy = case.truth(sx, sy)
        px, py = to_src.transform(gx, gy)
        col, row = inv_src * (px, py)
        mx, my = (col - 0.5).astype(np.float32), (row - 0.5).astype(np.float32)
        for k in range(3):
            rgb[k, r0:r1] = cv2.remap(img[k], mx, my, cv2.INTER_CUBIC,
                                      borderMode=cv2.BORDER_CONSTANT)
        inside = (mx >= 2) & (my >= 2) & (mx <= n_c - 3) & (my <= n_r - 3)
        valid[r0:r1] = np.where(inside, 255, 0)
    _write_rgba(case.mov_path, rgb, valid, "EPSG:4326", mov_t)
    case.site_path.write_text("\n".join([
        "[site]", 'name = "local warp case"', f'crs = "{site_crs}"', 'reference_flight = "REF"',
        "[parameters]", f"uav_gsd_m = {GSD_M}", "sat_gsd_m = 0.5", "tile_px = 500",
        "align_window_px = 1024", f'align_model = "{align_model}"',
        "keep_intermediates = true",  # aligned/ kept: the tests read whole aligned rasters
        "[[flights]]", 'id = "REF"', f'image = "{ref_path.name}"',
        'acquired = "2021-07-15T11:00:00+10:00"',
        "[[flights]]", 'id = "MOV"', f'image = "{case.mov_path.name}"',
        'acquired = "2021-07-15T14:00:00+10:00"', ""]))
    return case


@dataclass(frozen=True)
class Residual:
    """Misregistration of the aligned moving flight on the reference, UAV pixels."""

    median_px: float            # over aligned pixels valid in both flights
    worst_window_px: float      # worst 256 px window (mean over its valid pixels)
    beyond_reference_max_px: float | None  # where only the moving flight has data
    image_median_px: float      # skimage phase_cross_correlation per 256 px window
    image_worst_px: float
    n_windows: int


def evaluate(case: WarpCase, out_dir: Path, *, flight: str = "MOV", step_px: int = 4,
             window_px: int = 256) -> Residual:
    """Compare the pipeline's aligned moving flight with the truth ``W``.

    Geometric: for every ``step_px``-th aligned pixel centre ``p`` the pipeline samples the
    moving flight at stated point ``s = C⁻¹(p + D(p))`` (``alignment.json``: correction and
    field); its true ground is ``W(s)``; the error is ``|W(s) − p|``. Image: scikit-image's
    phase correlation (independent of geosim's) between the aligned rasters per window.
    """
    import json

    from skimage.registration import phase_cross_correlation

    from geosim.prepare.alignment import correction_affine
    from geosim.prepare.local_align import read_field_geotiff

    doc = json.loads((out_dir / "alignment.json").read_text())
    at = Affine(*doc["aligned_grid"]["transform"])
    entry = doc["flights"][flight]
    corr_inv = ~correction_affine(entry)
    field = (read_field_geotiff(out_dir / entry["local_field"]["path"])
             if "local_field" in entry else None)
    with rasterio.open(out_dir / "aligned" / f"{doc['reference']}.tif") as ds:
        ref = ds.read([1, 2, 3]).astype(np.float32).mean(axis=0)
        ref_ok = ds.read_masks(1) > 0
    with rasterio.open(out_dir / "aligned" / f"{flight}.tif") as ds:
        mov = ds.read([1, 2, 3]).astype(np.float32).mean(axis=0)
        mov_ok = ds.read_masks(1) > 0
    rows, cols = ref.shape
    r, c = np.mgrid[0:rows:step_px, 0:cols:step_px]
    px, py = at * (c + 0.5, r + 0.5)
    qx, qy = (px, py) if field is None else field.apply(px, py)
    sx, sy = corr_inv * (qx, qy)
    tx, ty = case.truth(sx, sy)
    err = np.hypot(tx - px, ty - py) / GSD_M
    both = ref_ok[::step_px, ::step_px] & mov_ok[::step_px, ::step_px]
    only_mov = ~ref_ok[::step_px, ::step_px] & mov_ok[::step_px, ::step_px]
    k = window_px // step_px
    worst = 0.0
    for i in range(0, both.shape[0] - k + 1, k):
        for j in range(0, both.shape[1] - k + 1, k):
            ok = both[i:i + k, j:j + k]
            if ok.mean() >= 0.5:
                worst = max(worst, float(err[i:i + k, j:j + k][ok].mean()))
    img = []
    for i in range(0, rows - window_px + 1, window_px):
        for j in range(0, cols - window_px + 1, window_px):
            sl = (slice(i, i + window_px), slice(j, j + window_px))
            if ref_ok[sl].all() and mov_ok[sl].all():
                shift, _, _ = phase_cross_correlation(ref[sl], mov[sl], upsample_factor=50)
                img.append(float(np.hypot(*shift)))
    return Residual(float(np.median(err[both])), worst,
                    float(err[only_mov].max()) if only_mov.any() else None,
                    float(np.median(img)), float(np.max(img)), len(img))


def single_remap_oracle(case: WarpCase, out: Path, r0: int, c0: int, n: int) -> np.ndarray:
    """Grey of aligned MOV pixels ``[r0:r0+n, c0:c0+n]`` by ONE bicubic remap of the original
    moving file, composed here point by point: aligned pixel → map → field (exact, per pixel)
    → inverse global correction → EPSG:4326 (pyproj) → source pixel."""
    import json

    from rasterio.windows import Window

    from geosim.prepare.alignment import correction_affine
    from geosim.prepare.local_align import read_field_geotiff

    doc = json.loads((out / "alignment.json").read_text())
    at = Affine(*doc["aligned_grid"]["transform"])
    entry = doc["flights"]["MOV"]
    field = read_field_geotiff(out / entry["local_field"]["path"])
    cc, rr = np.meshgrid(np.arange(c0, c0 + n) + 0.5, np.arange(r0, r0 + n) + 0.5)
    sx, sy = ~correction_affine(entry) * field.apply(*(at * (cc, rr)))
    with rasterio.open(case.mov_path) as ds:
        fx, fy = Transformer.from_crs(doc["crs"], ds.crs, always_xy=True).transform(sx, sy)
        col, row = ~ds.transform * (fx, fy)
        a0, b0 = int(np.floor(col.min())) - 4, int(np.floor(row.min())) - 4
        win = Window(a0, b0, int(np.ceil(col.max())) + 5 - a0, int(np.ceil(row.max())) + 5 - b0)
        img = ds.read([1, 2, 3], window=win).astype(np.float32).mean(axis=0)
    return cv2.remap(img, (col - 0.5 - a0).astype(np.float32), (row - 0.5 - b0).astype(np.float32),
                     cv2.INTER_CUBIC)
