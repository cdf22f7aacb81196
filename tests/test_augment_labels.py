"""Labels follow pixels: a marker painted inside each box stays inside its transformed box.

The truth is in the pixels: each marker is found by thresholding the augmented
image, independently of the box arithmetic under test.
"""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from geosim.augment.geometry import Boxes
from geosim.augment.pipeline import AugImage, Pipeline

SIZE = 160
GEOMETRIC = Pipeline.from_dict({
    "pipeline": {"min_visible_fraction": 0.5},
    "functions": [{"name": "mirror"}, {"name": "rotate"}, {"name": "scale"}, {"name": "shear"},
                  {"name": "shift"}, {"name": "local_warp", "max_px": 3.0,
                                      "filter_sigma_px": 12.0}],
})


@st.composite
def scenes(draw):
    """Up to four non-overlapping boxes in the central ±30 px, each with a 3 × 3 marker
    at least 3 px inside it."""
    boxes, markers = [], []
    for qx, qy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        if not draw(st.booleans()) and boxes:
            continue
        w, h = draw(st.integers(10, 28)), draw(st.integers(10, 28))
        x0 = 50 + 30 * qx + draw(st.integers(0, 28 - w))
        y0 = 50 + 30 * qy + draw(st.integers(0, 28 - h))
        mx = draw(st.integers(x0 + 3, x0 + w - 6))
        my = draw(st.integers(y0 + 3, y0 + h - 6))
        boxes.append([x0, y0, x0 + w, y0 + h])
        markers.append((mx, my))
    return np.array(boxes, float), markers


@st.composite
def records(draw):
    """Random parameters for every geometric function (each applied or not)."""
    f = st.floats
    params = [
        {"flip_ud": draw(st.booleans()), "flip_lr": draw(st.booleans())},
        {"rotation_deg": draw(f(-40, 40))},
        (lambda r: {"ratio": r, "factor": 1 + r})(draw(f(-0.25, 0.25))),
        {"shear_x": draw(f(-0.2, 0.2)), "shear_y": draw(f(-0.2, 0.2))},
        {"dx_px": draw(f(-10, 10)), "dy_px": draw(f(-10, 10))},
        {"max_px": draw(f(0.0, 3.0)), "filter_sigma_px": 12.0, "mode": "together",
         "seed": draw(st.integers(0, 2**32))},
    ]
    applied = [draw(st.booleans()) for _ in params]
    return [{"step": i, "function": s.function.name, "applied": a, "params": p}
            for i, (s, a, p) in enumerate(zip(GEOMETRIC.steps, applied, params, strict=True))]


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene=scenes(), recs=records())
def test_markers_stay_inside_their_transformed_boxes(scene, recs) -> None:
    xyxy, markers = scene
    empty = np.zeros((1, SIZE, SIZE), np.uint8)
    mask = np.ones((SIZE, SIZE), bool)
    for i, (mx, my) in enumerate(markers):
        img = empty.copy()
        img[0, my:my + 3, mx:mx + 3] = 255  # only this box's marker
        pair = AugImage(img, mask, Boxes(np.zeros(len(xyxy), int), xyxy))
        res = GEOMETRIC.replay(pair, pair, recs)
        assert len(res.a.boxes) == len(xyxy)  # all stay visible with these ranges
        rows, cols = np.nonzero(res.a.image[0] > 127)
        assert rows.size > 0, "marker lost"
        x0, y0, x1, y1 = res.a.boxes.xyxy_px[i]
        # pixel centres of the thresholded marker lie inside the transformed box
        assert x0 <= (cols + 0.5).min() and (cols + 0.5).max() <= x1
        assert y0 <= (rows + 0.5).min() and (rows + 0.5).max() <= y1


def test_boxes_leaving_the_image_are_dropped_and_markers_agree() -> None:
    shape = (100, 100)
    img = np.zeros((1, *shape), np.uint8)
    img[0, 48:51, 5:8] = 255  # marker in a box at the left edge
    boxes = Boxes(np.array([0, 0]), np.array([[2.0, 44.0, 14.0, 56.0], [60, 40, 80, 60]]))
    p = Pipeline.from_dict({"functions": [{"name": "shift"}]})
    recs = [{"step": 0, "function": "shift", "applied": True,
             "params": {"dx_px": -9.0, "dy_px": 0.0}}]
    res = p.replay(AugImage(img, np.ones(shape, bool), boxes), AugImage(img, np.ones(shape, bool),
                                                                      boxes), recs)
    # 5 of 12 px of the first box remain (< 50 %): dropped; the marker has left the image too.
    assert len(res.a.boxes) == 1 and res.dropped_a == 1
    assert np.allclose(res.a.boxes.xyxy_px, [[51, 40, 71, 60]])
    assert not (res.a.image > 127).any()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene=scenes(), recs=records())
def test_transformed_box_hugs_the_transformed_object(scene, recs) -> None:
    """Tight check both ways: paint each whole box, threshold at half intensity (the pixels
    whose centres fall inside the moved object) and compare their extent with the box."""
    xyxy, _ = scene
    mask = np.ones((SIZE, SIZE), bool)
    for i, (x0, y0, x1, y1) in enumerate(xyxy.astype(int)):
        img = np.zeros((1, SIZE, SIZE), np.uint8)
        img[0, y0:y1, x0:x1] = 255
        pair = AugImage(img, mask, Boxes(np.zeros(len(xyxy), int), xyxy))
        res = GEOMETRIC.replay(pair, pair, recs)
        rows, cols = np.nonzero(res.a.image[0] > 127)
        bx0, by0, bx1, by1 = res.a.boxes.xyxy_px[i]
        cx, cy = cols + 0.5, rows + 0.5
        # no object pixel outside its box (a quarter-pixel for the interpolated edge) ...
        assert cx.min() >= bx0 - 0.25 and cx.max() <= bx1 + 0.25
        assert cy.min() >= by0 - 0.25 and cy.max() <= by1 + 0.25
        # ... and the box no bigger than the object (pixel centres cut sharp corners by < 2 px)
        assert cx.min() - bx0 < 2.0 and bx1 - cx.max() < 2.0
        assert cy.min() - by0 < 2.0 and by1 - cy.max() < 2.0
