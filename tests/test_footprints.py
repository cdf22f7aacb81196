"""Footprints are traced from masks (not bounding boxes); the common extent refuses empties."""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
import shapely
from affine import Affine
from shapely.geometry import box

from geosim.errors import ExtentError
from geosim.prepare.footprints import (
    common_extent,
    mask_to_footprint,
    raster_footprint,
    reduce_mask,
)

T = Affine(0.05, 0.0, 300000.0, 0.0, -0.05, 6200000.0)


def irregular_mask(rows: int = 400, cols: int = 500) -> np.ndarray:
    """A disc with a hole plus a diagonal arm: far from its bounding box."""
    yy, xx = np.mgrid[0:rows, 0:cols]
    r = np.hypot(yy - 150, xx - 150)
    disc = (r < 120) & (r > 40)
    arm = (np.abs((yy - 150) - 0.5 * (xx - 150)) < 15) & (xx > 150) & (xx < 480)
    return disc | arm


def test_footprint_area_matches_mask_not_bbox():
    mask = irregular_mask()
    geom = mask_to_footprint(mask, T)
    pixel_area = 0.05 * 0.05
    mask_area = mask.sum() * pixel_area
    assert geom.area == pytest.approx(mask_area, rel=1e-9)      # exact pixel outlines
    assert geom.area < 0.6 * geom.envelope.area                    # not a bounding box
    interiors = sum(len(p.interiors) for p in getattr(geom, "geoms", [geom]))
    assert interiors >= 1                                          # the hole survives
    # simplification in metres keeps the area close (error ≲ tolerance × perimeter)
    simp = mask_to_footprint(mask, T, simplify_m=0.1)
    assert abs(simp.area - mask_area) < 0.1 * geom.length
    assert shapely.get_num_coordinates(simp) < shapely.get_num_coordinates(geom) / 2


def test_footprint_position_is_exact():
    mask = np.zeros((100, 100), bool)
    mask[10:30, 40:90] = True
    geom = mask_to_footprint(mask, T)
    assert geom.bounds == pytest.approx((T.c + 40 * 0.05, T.f - 30 * 0.05,
                                         T.c + 90 * 0.05, T.f - 10 * 0.05), abs=1e-9)
    assert mask_to_footprint(np.zeros((5, 5), bool), T).is_empty


def test_reduce_mask_majority():
    m = np.zeros((20, 20), bool)
    m[:10, :5] = True          # half of block (0, 0)
    m[10:, 10:] = True         # all of block (1, 1)
    m[:3, 10:] = True          # 30 % of block (0, 1)
    assert reduce_mask(m, 10).tolist() == [[True, False], [False, True]]
    assert reduce_mask(m, 1) is not m and reduce_mask(m, 1).sum() == m.sum()


def test_bali_alpha_footprint_matches_alpha_area(realdata):
    path = realdata / "bali_farmland_35cm_rgba_epsg32750.tif"
    with rasterio.open(path) as ds:
        alpha = ds.read(4) > 0
        px_area = abs(ds.transform.a * ds.transform.e)
        bbox_area = ds.width * ds.height * px_area
        crs = ds.crs
    alpha_area = alpha.sum() * px_area
    geom = raster_footprint(path, simplify_m=0.5)
    assert crs.to_epsg() == 32750
    assert abs(geom.area - alpha_area) / alpha_area < 0.03
    assert geom.area < 0.95 * bbox_area                    # the footprint is irregular
    # windowed + reduced tracing agrees too (memory-bounded path used on grids)
    coarse = raster_footprint(path, reduce_px=4, simplify_m=0.5, block_px=128)
    assert abs(coarse.area - alpha_area) / alpha_area < 0.03


def test_common_extent_intersection_and_errors():
    a = box(0, 0, 100, 100)
    b = box(50, 20, 150, 120)
    c = box(60, 0, 90, 200)
    inter = common_extent({"A": a, "B": b, "C": c}, min_area_m2=10)
    assert inter.area == pytest.approx(30 * 80)
    with pytest.raises(ExtentError) as err:
        common_extent({"PA1": a, "PA2": box(200, 200, 300, 300), "PA3": b}, min_area_m2=10)
    msg = str(err.value)
    assert "PA1" in msg and "PA2" in msg and "empty" in msg and "PA1∩PA2" in msg
    with pytest.raises(ExtentError, match="minimum"):   # tiny: 1 m² overlap
        common_extent({"A": a, "B": box(99, 99, 200, 200)}, min_area_m2=10)
    assert isinstance(ExtentError("x"), ValueError)
