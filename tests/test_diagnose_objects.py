"""Moved objects (scene change modelled): fits against objects drawn without geosim.

The objects are drawn with OpenCV on a grid ten times finer than the product, blurred by a
Gaussian of the Airy core's width and block-averaged to the product grid; the fit renders
its own ellipses through geosim's Airy transfer, so agreement is not agreement with itself.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.locate import Region
from geosim.diagnose.stage_objects import SceneObjects, fit_moved_objects, render_ellipse

PHI = 10


def _draw(shape: tuple[int, int], objects: list[tuple[float, float, float, float, float, float]],
          q: float) -> np.ndarray:
    """Product image (rows, cols) of uniform ellipses (col, row, a, b, angle anticlockwise
    on the map in degrees, contrast DN; product pixels), drawn on a 10× grid, blurred by a
    Gaussian of σ = 0.42·Q product px and block-averaged."""
    fine = np.zeros((shape[0] * PHI, shape[1] * PHI), np.float32)
    for col, row, a, b, ang, contrast in objects:
        layer = np.zeros_like(fine)
        # OpenCV's angle turns from +x towards +y (rows, i.e. south): clockwise on the map
        cv2.ellipse(layer, (int(round(col * PHI * 16)), int(round(row * PHI * 16))),
                    (int(round(a * PHI * 16)), int(round(b * PHI * 16))), -ang, 0, 360, 1.0,
                    -1, cv2.LINE_AA, 4)
        fine += contrast * layer
    fine = ndimage.gaussian_filter(fine, 0.42 * q * PHI, mode="constant")
    return fine.reshape(shape[0], PHI, shape[1], PHI).mean(axis=(1, 3))


def _region(labels: np.ndarray, mask: np.ndarray, label: int) -> Region:
    rows, cols = np.nonzero(mask)
    labels[mask] = label
    return Region(rank=label, kind="scene_change", area_px=int(mask.sum()),
                  bbox=(int(rows.min()), int(cols.min()), int(rows.max()) + 1,
                        int(cols.max()) + 1), excess_energy=1.0, mean_ratio=10.0,
                  label=label)


def test_render_ellipse_area_and_orientation():
    ind = render_ellipse((200, 200), (100.0, 100.0), (40.0, 15.0), 30.0)
    assert ind.sum() == pytest.approx(np.pi * 40 * 15, rel=0.01)
    # the major axis 30° anticlockwise on the map from east: up-right on the image
    ys, xs = np.nonzero(ind > 0.5)
    cov = np.cov(np.stack([xs - 100.0, -(ys - 100.0)]))
    lam, vec = np.linalg.eigh(cov)
    ang = np.degrees(np.arctan2(vec[1, 1], vec[0, 1])) % 180
    assert ang == pytest.approx(30.0, abs=1.0)


@pytest.mark.parametrize("q", [1.0, 2.0])
def test_moved_objects_recovered(q):
    rng = np.random.default_rng(3)
    shape = (64, 64)
    ground = 100.0 + 20.0 * ndimage.gaussian_filter(rng.normal(0, 1, shape), 4.0)
    # a dark animal (-60 DN against the ground) left A, one arrived at B
    left = (20.3, 24.6, 2.4, 1.0, 20.0, -60.0)
    arrived = (44.8, 40.2, 2.4, 1.0, 110.0, -60.0)
    tint = np.array([1.0, 0.9, 0.7])[:, None, None]
    model = tint * (ground + _draw(shape, [left], q))
    real = tint * (ground + _draw(shape, [arrived], q)) + rng.normal(0, 1.0, (3, *shape))
    residual = real - model
    clean = _draw(shape, [arrived], q) - _draw(shape, [left], q)
    labels = np.zeros(shape, np.int32)
    energy = ndimage.gaussian_filter(clean ** 2, 1.5)
    regions = []
    for k, (col, row, *_rest) in enumerate((left, arrived), start=1):
        near = np.zeros(shape, bool)
        near[int(row) - 5:int(row) + 6, int(col) - 5:int(col) + 6] = True
        regions.append(_region(labels, near & (energy > 4.0), k))
    fit = fit_moved_objects(residual, np.ones(shape, bool), labels, regions, q=q, model=model)
    assert isinstance(fit, SceneObjects)
    assert len(fit.objects) == 2, [o.to_json(0.5) for o in fit.objects]
    # the residual shows the departure with the opposite sign
    expected = [(left, 60.0, "left"), (arrived, -60.0, "appeared")]
    for ((col, row, a, b, ang, _), contrast, change), o in zip(expected, fit.objects,
                                                                strict=True):
        assert o.centre_px[0] == pytest.approx(col, abs=0.2)
        assert o.centre_px[1] == pytest.approx(row, abs=0.2)
        assert o.semi_axes_px[0] == pytest.approx(a, rel=0.15)
        assert o.semi_axes_px[1] == pytest.approx(b, rel=0.25)
        assert abs((o.angle_deg - ang + 90) % 180 - 90) < 8
        assert o.contrast_dn[0] == pytest.approx(contrast, rel=0.15)
        assert o.contrast_dn[2] / o.contrast_dn[0] == pytest.approx(0.7, abs=0.05)
        assert o.rss_drop > 0.9
        assert o.change == change
    # the layer explains the residual down to its noise
    rest = residual - fit.layer
    assert np.sqrt(np.mean(rest ** 2)) < 1.3


def test_noise_alone_gives_no_object():
    rng = np.random.default_rng(4)
    shape = (48, 48)
    residual = rng.normal(0, 2.0, (3, *shape))
    labels = np.zeros(shape, np.int32)
    mask = np.zeros(shape, bool)
    mask[20:28, 20:28] = True
    regions = [_region(labels, mask, 1)]
    assert fit_moved_objects(residual, np.ones(shape, bool), labels, regions, q=1.5) is None


def test_global_regions_are_not_modelled_as_objects():
    shape = (48, 48)
    clean = _draw(shape, [(24.0, 24.0, 2.4, 1.0, 0.0, 80.0)], 1.5)
    residual = np.stack([clean] * 3)
    labels = np.zeros(shape, np.int32)
    region = _region(labels, np.abs(clean) > 2.0, 1)
    glob = Region(**{**region.__dict__, "kind": "global"})
    assert fit_moved_objects(residual, np.ones(shape, bool), labels, [glob], q=1.5) is None
