"""Map polygons -> clipped YOLO boxes per tile, and the 0.05 m / 0.5 m correspondence."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
from affine import Affine

from geosim.errors import ConfigError
from geosim.labels.georef import boxes_to_polygons
from geosim.labels.tiles import sat_tile_geometry, tile_boxes

# A 200 x 200 px UAV tile at 0.05 m (10 m x 10 m), north-up, origin (300000, 6200000).
T = Affine(0.05, 0.0, 300000.0, 0.0, -0.05, 6200000.0)
N = 200


def test_box_inside_tile_known_answer():
    cow = shapely.box(300002.0, 6199995.0, 300004.0, 6199996.0)   # 2 m x 1 m
    out = tile_boxes([cow], T, N, N, min_visible_fraction=0.5)
    # Pixel cols 40..80, rows 80..100 of 200.
    np.testing.assert_allclose(out.boxes, [[0.3, 0.45, 0.2, 0.1]], atol=1e-9)
    assert out.index.tolist() == [0]
    assert out.visible_fraction[0] == pytest.approx(1.0)
    assert not out.clipped[0]


def test_box_cut_by_tile_edge_is_clipped_and_kept_above_fraction():
    # 2 m wide cow with 1.2 m (60 %) on the tile, across its east edge at x = 300010.
    cow = shapely.box(300008.8, 6199995.0, 300010.8, 6199996.0)
    out = tile_boxes([cow], T, N, N, min_visible_fraction=0.5)
    assert out.index.tolist() == [0] and out.clipped[0]
    assert out.visible_fraction[0] == pytest.approx(0.6)
    # Clipped box: cols 176..200 -> cx = 188/200, w = 24/200.
    np.testing.assert_allclose(out.boxes[0], [0.94, 0.45, 0.12, 0.1], atol=1e-9)


def test_box_below_visible_fraction_is_dropped():
    # 40 % visible across the north edge.
    cow = shapely.box(300002.0, 6199999.6, 300004.0, 6200000.6)
    out = tile_boxes([cow], T, N, N, min_visible_fraction=0.5)
    assert len(out) == 0
    assert out.dropped.tolist() == [0]
    kept = tile_boxes([cow], T, N, N, min_visible_fraction=0.4)
    assert len(kept) == 1 and kept.visible_fraction[0] == pytest.approx(0.4)


def test_polygons_off_the_tile_are_absent():
    far = shapely.box(300020.0, 6199995.0, 300022.0, 6199996.0)
    touching = shapely.box(300010.0, 6199995.0, 300012.0, 6199996.0)  # shares the edge only
    out = tile_boxes([far, touching], T, N, N, min_visible_fraction=0.01)
    assert len(out) == 0 and out.dropped.size == 0


def test_rotated_label_box_is_bounding_box_of_clipped_part():
    # A 45-degree diamond centred on the tile's west edge: half is visible.
    d = shapely.Polygon([(300000, 6199996), (300001, 6199995), (300000, 6199994),
                         (299999, 6199995)])
    out = tile_boxes([d], T, N, N, min_visible_fraction=0.5)
    assert out.visible_fraction[0] == pytest.approx(0.5)
    # Visible half spans x 300000..300001 (cols 0..20), y 6199994..6199996 (rows 80..120).
    np.testing.assert_allclose(out.boxes[0], [0.05, 0.5, 0.1, 0.2], atol=1e-9)


def test_sat_tile_geometry_same_origin_phi_times_pixel():
    t_sat, w, h = sat_tile_geometry(T, 200, 200, 10)
    assert (w, h) == (20, 20)
    assert t_sat == Affine(0.5, 0.0, 300000.0, 0.0, -0.5, 6200000.0)
    with pytest.raises(ConfigError, match="multiple"):
        sat_tile_geometry(T, 205, 200, 10)


def test_uav_and_sat_boxes_cover_the_same_ground():
    """Random cattle, some across tile edges: the box on the 0.05 m tile and its 0.5 m
    counterpart, each taken back to map coordinates through its own tile transform,
    cover the same ground within half a 0.5 m pixel."""
    rng = np.random.default_rng(7)
    n = 300
    cx = rng.uniform(299998.0, 300012.0, n)
    cy = rng.uniform(6199988.0, 6200002.0, n)
    half_w, half_h = rng.uniform(0.1, 1.3, (2, n))   # includes boxes below one 0.5 m pixel
    cows = shapely.box(cx - half_w, cy - half_h, cx + half_w, cy + half_h)
    t_sat, ws, hs = sat_tile_geometry(T, N, N, 10)
    uav = tile_boxes(cows, T, N, N, min_visible_fraction=0.5)
    sat = tile_boxes(cows, t_sat, ws, hs, min_visible_fraction=0.5)
    assert uav.index.tolist() == sat.index.tolist()
    assert uav.clipped.any() and uav.dropped.size > 0   # edges were exercised
    ground_uav = shapely.bounds(boxes_to_polygons(uav.boxes, T, N, N))
    ground_sat = shapely.bounds(boxes_to_polygons(sat.boxes, t_sat, ws, hs))
    assert np.max(np.abs(ground_uav - ground_sat)) <= 0.25
    # And both equal the cow clipped to the tile's ground (10 m x 10 m), independently.
    tile_ground = shapely.box(300000.0, 6199990.0, 300010.0, 6200000.0)
    truth = shapely.bounds(shapely.intersection(cows[uav.index], tile_ground))
    np.testing.assert_allclose(ground_uav, truth, atol=1e-6)
    np.testing.assert_allclose(ground_sat, truth, atol=1e-6)


def test_no_polygons():
    out = tile_boxes([], T, N, N, min_visible_fraction=0.5)
    assert len(out) == 0 and out.boxes.shape == (0, 4)


def test_bad_fraction_is_refused():
    with pytest.raises(ConfigError):
        tile_boxes([], T, N, N, min_visible_fraction=1.5)


def test_zero_fraction_keeps_any_visible_part():
    sliver = shapely.box(300009.99, 6199995.0, 300011.99, 6199996.0)   # 0.5 % visible
    out = tile_boxes([sliver], T, N, N, min_visible_fraction=0.0)
    assert len(out) == 1 and out.visible_fraction[0] == pytest.approx(0.005)
