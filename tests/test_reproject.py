"""Reprojection onto the shared grid: any CRS lands on the same pixels; masks and dtypes kept."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from affine import Affine
from pyproj import Transformer
from rasterio.crs import CRS
from rasterio.enums import ColorInterp, Resampling
from rasterio.warp import calculate_default_transform, reproject
from scipy import ndimage

from geosim.align import phase_correlate
from geosim.errors import RasterError
from geosim.prepare.footprints import raster_footprint
from geosim.prepare.grid import resolve_site_crs, snap_grid
from geosim.prepare.reproject import bounds_in_crs, reproject_to_grid

UTM56 = CRS.from_epsg(32756)
X0, Y0 = Transformer.from_crs(4326, 32756, always_xy=True).transform(150.4, -34.5)
SRC_T = Affine(0.05, 0.0, round(X0) + 0.013, 0.0, -0.05, round(Y0) - 0.021)  # off-grid origin
BLOBS_PX = [(60.0, 70.0), (200.0, 90.0), (120.0, 230.0), (250.0, 260.0), (80.0, 270.0)]


def textured(rows: int = 320, cols: int = 320, seed: int = 0) -> np.ndarray:
    """Smooth low-contrast texture plus bright Gaussian blobs at BLOBS_PX (col, row centres)."""
    rng = np.random.default_rng(seed)
    base = ndimage.gaussian_filter(rng.normal(size=(rows, cols)), 3.0)
    base = 60 + 12 * base / base.std()
    yy, xx = np.mgrid[0:rows, 0:cols]
    for c, r in BLOBS_PX:
        base += 150 * np.exp(-((xx - c) ** 2 + (yy - r) ** 2) / (2 * 3.0 ** 2))
    img = np.stack([base, 0.8 * base + 10, 0.6 * base + 20])
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def write(path, img, transform, crs, **extra):
    with rasterio.open(path, "w", driver="GTiff", width=img.shape[2], height=img.shape[1],
                       count=img.shape[0], dtype=img.dtype, crs=crs, transform=transform,
                       **extra) as dst:
        dst.write(img)
    return path


def warp_to(src_path, dst_path, crs):
    """An independent reprojection (plain rasterio, whole array) into another CRS."""
    with rasterio.open(src_path) as src:
        t, w, h = calculate_default_transform(src.crs, crs, src.width, src.height, *src.bounds)
        out = np.zeros((src.count, h, w), dtype=np.uint8)
        reproject(src.read(), out, src_transform=src.transform, src_crs=src.crs,
                  dst_transform=t, dst_crs=crs, resampling=Resampling.cubic, src_nodata=0,
                  dst_nodata=0)
    return write(dst_path, out, t, crs, nodata=0)


def blob_positions(img: np.ndarray, valid: np.ndarray) -> list[tuple[float, float]]:
    """Intensity centroids (col, row) of the bright blobs, in pixel-centre coordinates."""
    g = img[0].astype(float)
    g[~valid] = 0
    labels, n = ndimage.label(g > 140)
    out = []
    for i in range(1, n + 1):
        sel = labels == i
        if sel.sum() < 5:
            continue
        w = (g - 100).clip(0) * sel
        r, c = ndimage.center_of_mass(w)
        out.append((c, r))
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("reproj")
    src = write(d / "utm56.tif", textured(), SRC_T, UTM56)
    paths = {"utm56": src}
    for name, epsg in [("wgs84", 4326), ("webmerc", 3857), ("utm55", 32755), ("gda94", 28356)]:
        paths[name] = warp_to(src, d / f"{name}.tif", CRS.from_epsg(epsg))
    with rasterio.open(src) as ds:
        b = bounds_in_crs(ds, UTM56)
    grid = snap_grid(b, UTM56, uav_gsd_m=0.05, sat_gsd_m=0.5)
    out = {}
    for name, p in paths.items():
        dst = d / f"grid_{name}.tif"
        reproject_to_grid(p, dst, crs=grid.crs, transform=grid.uav_transform,
                          shape=grid.uav_shape, block_px=128, what=name, progress=False)
        with rasterio.open(dst) as ds:
            out[name] = (ds.read(), ds.dataset_mask() > 0, ds.transform, ds.crs)
    return grid, out


def test_every_crs_lands_on_the_same_grid(inputs):
    grid, out = inputs
    for _name, (_img, valid, transform, crs) in out.items():
        assert transform == grid.uav_transform and crs == grid.crs
        assert valid.mean() > 0.8
    # truth: blob centres are known map points; find them on each gridded raster
    truth = [grid_px(SRC_T @ (c + 0.5, r + 0.5), grid.uav_transform) for c, r in BLOBS_PX]
    for name, (img, valid, _t, _c) in out.items():
        found = blob_positions(img, valid)
        assert len(found) == len(truth), name
        for tc, tr in truth:
            err = min(np.hypot(fc - tc, fr - tr) for fc, fr in found)
            assert err < 0.5, (name, err)     # well within 1 UAV pixel
    # and pairwise, by phase correlation over the common valid area
    ref_img, ref_valid = out["utm56"][0], out["utm56"][1]
    for name in ("wgs84", "webmerc", "utm55", "gda94"):
        img, valid = out[name][0], out[name][1]
        both = ref_valid & valid
        pc = phase_correlate(ref_img, img, valid_reference=both, valid_moving=both)
        assert pc.confidence > 0.3
        assert np.hypot(*pc.shift_px) < 1.0, (name, pc.shift_px)


def grid_px(xy, transform):
    c, r = ~transform @ xy
    return c - 0.5, r - 0.5


def test_identity_on_grid_is_exact_and_masks_follow_alpha(tmp_path):
    grid = snap_grid((300000.0, 6200000.0, 300010.0, 6200008.0), UTM56, uav_gsd_m=0.05,
                     sat_gsd_m=0.5)
    rows, cols = grid.uav_shape
    rng = np.random.default_rng(3)
    rgb = rng.integers(1, 255, size=(3, rows, cols), dtype=np.uint8)
    alpha = np.zeros((rows, cols), np.uint8)
    alpha[20:150, 30:190] = 255
    alpha[60:90, 60:80] = 0
    src = write(tmp_path / "rgba.tif", np.concatenate([rgb, alpha[None]]), grid.uav_transform,
                UTM56, photometric="RGB", alpha="YES")
    with rasterio.open(src) as ds:
        assert ds.colorinterp[3] == ColorInterp.alpha
    dst = tmp_path / "out.tif"
    summary = reproject_to_grid(src, dst, crs=grid.crs, transform=grid.uav_transform,
                                shape=grid.uav_shape, block_px=64, progress=False)
    with rasterio.open(dst) as ds:
        assert ds.count == 3 and ds.dtypes[0] == "uint8"
        valid = ds.dataset_mask() > 0
        out = ds.read()
    assert np.array_equal(valid, alpha > 0)
    assert summary["valid_px"] == int((alpha > 0).sum())
    assert np.array_equal(out[:, valid], rgb[:, valid])
    assert not out[:, ~valid].any()


def test_16bit_nodata_and_internal_mask_inputs(tmp_path):
    grid = snap_grid((300000.0, 6200000.0, 300006.0, 6200006.0), UTM56, uav_gsd_m=0.05,
                     sat_gsd_m=0.5)
    rows, cols = grid.uav_shape
    yy, xx = np.mgrid[0:rows, 0:cols]
    img16 = (1000 + 20 * xx + 7 * yy).astype(np.uint16)[None].repeat(3, 0)
    img16[:, :, :40] = 0                                     # nodata strip
    # shifted by half a pixel so the values are interpolated
    t = grid.uav_transform @ Affine.translation(0.5, 0.0)
    src = write(tmp_path / "u16.tif", img16, t, UTM56, nodata=0)
    dst = tmp_path / "u16_grid.tif"
    reproject_to_grid(src, dst, crs=grid.crs, transform=grid.uav_transform,
                      shape=grid.uav_shape, block_px=50, progress=False)
    with rasterio.open(dst) as ds:
        assert ds.dtypes[0] == "uint16"
        out, valid = ds.read(1), ds.dataset_mask() > 0
    # a linear ramp is reproduced by the cubic kernel: value at grid col c = src col c - 0.5
    inner = valid.copy()
    inner[:, :45] = False
    inner[:, -3:] = False
    inner[:3] = inner[-3:] = False
    expect = 1000 + 20 * (xx - 0.5) + 7 * yy
    assert np.abs(out[inner] - expect[inner]).max() <= 1
    assert not valid[:, :40].any() and valid[:, 42:-1].all()
    assert out[valid].min() >= 1000 - 20                     # no nodata bled in

    # an internal (GDAL) mask instead of nodata
    from geosim.io.raster import write_geotiff

    m = np.ones((rows, cols), bool)
    m[10:30, 10:30] = False
    src2 = write_geotiff(tmp_path / "masked.tif", img16.astype(np.uint16), mask=m,
                         transform=grid.uav_transform, crs=UTM56)
    dst2 = tmp_path / "masked_grid.tif"
    reproject_to_grid(src2, dst2, crs=grid.crs, transform=grid.uav_transform,
                      shape=grid.uav_shape, progress=False)
    with rasterio.open(dst2) as ds:
        assert np.array_equal(ds.dataset_mask() > 0, m)   # no nodata value: zeros are data


def test_unsupported_input_is_refused(tmp_path):
    src = write(tmp_path / "c.tif", np.zeros((1, 8, 8), np.complex64), SRC_T, UTM56)
    with pytest.raises(RasterError, match="data type"):
        reproject_to_grid(src, tmp_path / "o.tif", crs=UTM56, transform=SRC_T, shape=(8, 8),
                          what="flight X")


def test_brazil_world_mercator_onto_utm(realdata, tmp_path):
    path = realdata / "brazil_pasture_10cm_epsg3395.tif"
    with rasterio.open(path) as ds:
        assert ds.crs.to_epsg() == 3395
        lonlat = bounds_in_crs(ds, CRS.from_epsg(4326))
    crs = resolve_site_crs("auto", [lonlat])
    assert crs.to_epsg() == 32722                          # UTM 22S
    with rasterio.open(path) as ds:
        grid = snap_grid(bounds_in_crs(ds, crs), crs, uav_gsd_m=0.1, sat_gsd_m=0.5)
    dst = tmp_path / "brazil.tif"
    reproject_to_grid(path, dst, crs=grid.crs, transform=grid.uav_transform,
                      shape=grid.uav_shape, progress=False)
    with rasterio.open(dst) as ds:
        assert ds.crs.to_epsg() == 32722 and ds.transform == grid.uav_transform
        valid_frac = (ds.dataset_mask() > 0).mean()
    assert valid_frac > 0.85
    # the footprint lands where the source is: compare centroids in lon/lat
    fp = raster_footprint(dst, reduce_px=5)
    to_ll = Transformer.from_crs(crs.to_wkt(), 4326, always_xy=True)
    lon, lat = to_ll.transform(fp.centroid.x, fp.centroid.y)
    clon, clat = (lonlat[0] + lonlat[2]) / 2, (lonlat[1] + lonlat[3]) / 2
    assert abs(lon - clon) * 111320 * np.cos(np.radians(lat)) < 0.5
    assert abs(lat - clat) * 110600 < 0.5
    # ground size preserved: Mercator 0.1 "m" pixels are 0.1·cos(lat) m on the ground
    assert fp.area == pytest.approx(2048 * 2048 * 0.01 * np.cos(np.radians(lat)) ** 2, rel=0.02)
