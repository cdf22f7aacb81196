"""Geometry and resampling of the pair augmentations, against known answers."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from geosim.augment import geometry as geo
from geosim.augment.resample import affine_resample, remap_resample


def _spot(shape: tuple[int, int], r: int, c: int, bands: int = 1) -> np.ndarray:
    img = np.zeros((bands, *shape), np.uint8)
    img[:, r, c] = 200
    return img


def test_rotation_matrix_turns_counter_clockwise_about_centre() -> None:
    # 10 x 20 image, centre (10, 5); a point 4 px right of the centre goes 4 px up at +90°.
    m = geo.rotation_matrix(90.0, (10, 20))
    assert np.allclose(m @ [14.0, 5.0, 1.0], [10.0, 1.0, 1.0])
    assert np.allclose(m @ [10.0, 5.0, 1.0], [10.0, 5.0, 1.0])  # centre fixed
    # Same convention as OpenCV's getRotationMatrix2D (centre in pixel-index convention).
    import cv2

    cvm = cv2.getRotationMatrix2D((9.5, 4.5), 30.0, 1.0)
    ours = geo.to_cv2_inverse(geo.rotation_matrix(30.0, (10, 20)))
    assert np.allclose(np.linalg.inv(np.vstack([cvm, [0, 0, 1]]))[:2], ours)


def test_mirror_is_an_involution_and_an_exact_flip() -> None:
    shape = (7, 9)
    m = geo.mirror_matrix(True, True, shape)
    assert np.array_equal(m @ m, np.eye(3))
    img = np.random.default_rng(0).integers(0, 255, (2, *shape), dtype=np.uint8)
    out, mask = affine_resample(img, np.ones(shape, bool), m)
    assert np.array_equal(out, img[:, ::-1, ::-1]) and mask.all()
    out, _ = affine_resample(img, np.ones(shape, bool), geo.mirror_matrix(False, True, shape))
    assert np.array_equal(out, img[:, :, ::-1])


@pytest.mark.parametrize("angle, k", [(90.0, 1), (180.0, 2), (-90.0, -1), (270.0, 3)])
def test_quarter_turns_of_a_square_image_are_exact(angle: float, k: int) -> None:
    img = np.arange(2 * 64, dtype=np.uint16).reshape(2, 8, 8)
    out, mask = affine_resample(img, np.ones((8, 8), bool), geo.rotation_matrix(angle, (8, 8)))
    assert np.array_equal(out, np.rot90(img, k, axes=(1, 2))) and mask.all()


def test_whole_pixel_shift_is_exact_and_marks_the_entering_strip_invalid() -> None:
    img = np.random.default_rng(1).integers(1, 255, (3, 12, 10), dtype=np.uint8)
    out, mask = affine_resample(img, np.ones((12, 10), bool), geo.shift_matrix(3, -2))
    assert np.array_equal(out[:, :10, 3:], img[:, 2:, :7])
    assert not mask[:, :3].any() and not mask[10:, :].any()
    assert mask[:10, 3:].all()
    assert (out[:, ~mask] == 0).all()  # invalid pixels are not just black-filled data


def test_subpixel_shift_moves_a_spot_by_the_shift() -> None:
    img = np.zeros((1, 21, 21), np.float32)
    img[0, 10, 10] = 1.0
    out, mask = affine_resample(img, np.ones((21, 21), bool), geo.shift_matrix(2.5, -1.25),
                                interpolation="linear")
    rows, cols = np.indices((21, 21))
    w = out[0] / out[0].sum()
    assert np.isclose((w * cols).sum(), 12.5, atol=0.05)
    assert np.isclose((w * rows).sum(), 8.75, atol=0.05)


def test_mask_follows_with_nearest_and_outside_becomes_invalid() -> None:
    shape = (40, 40)
    mask = np.ones(shape, bool)
    mask[10:20, 10:20] = False
    img = np.full((1, *shape), 100, np.uint8)
    out, om = affine_resample(img, mask, geo.shift_matrix(5.3, 0.0))
    # The hole moves by 5.3 px → columns 15..24 (nearest), rows unchanged.
    assert not om[10:20, 16:25].any() and om[10:20, 26:].all()
    assert not om[:, :5].any()  # came from outside
    assert (out[0][om] == 100).all()  # no black fringe from the border in valid pixels


def test_remap_with_constant_field_equals_affine_shift() -> None:
    rng = np.random.default_rng(2)
    img = rng.random((1, 30, 30)).astype(np.float32)
    mask = np.ones((30, 30), bool)
    u = np.full((30, 30), -2.0, np.float32)  # out(x) = in(x - 2): content moves right by 2
    v = np.full((30, 30), 1.0, np.float32)
    a, am = remap_resample(img, mask, u, v)
    b, bm = affine_resample(img, mask, geo.shift_matrix(2.0, -1.0))
    assert np.array_equal(am, bm)
    assert np.allclose(a[:, am], b[:, bm], atol=1e-5)


def test_yolo_round_trip() -> None:
    yolo = np.array([[0, 0.5, 0.25, 0.1, 0.2], [1, 0.1, 0.9, 0.05, 0.1]])
    boxes = geo.Boxes.from_yolo(yolo, (200, 400))
    assert np.allclose(boxes.xyxy_px[0], [180, 30, 220, 70])
    assert np.allclose(boxes.to_yolo((200, 400)), yolo)


def test_rotating_a_box_there_and_back_does_not_inflate_it() -> None:
    shape = (100, 100)
    boxes = geo.Boxes(np.array([0]), np.array([[40.0, 45.0, 60.0, 55.0]]))
    track = geo.BoxTrack.from_boxes(boxes, shape)
    once = track.affine(geo.rotation_matrix(30.0, shape), shape)
    b1, _ = once.to_boxes(min_visible_fraction=0.5)
    # Enclosing box of a 20 x 10 box turned by 30°: 20cos+10sin by 20sin+10cos.
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    assert np.allclose(b1.xyxy_px[0, 2] - b1.xyxy_px[0, 0], 20 * c + 10 * s)
    assert np.allclose(b1.xyxy_px[0, 3] - b1.xyxy_px[0, 1], 20 * s + 10 * c)
    back = once.affine(geo.rotation_matrix(-30.0, shape), shape)
    b2, _ = back.to_boxes(min_visible_fraction=0.5)
    assert np.allclose(b2.xyxy_px, boxes.xyxy_px)


def test_visible_fraction_and_drop() -> None:
    shape = (100, 100)
    boxes = geo.Boxes(np.array([0, 0]), np.array([[0.0, 0.0, 20.0, 20.0], [50, 50, 60, 60]]))
    track = geo.BoxTrack.from_boxes(boxes, shape).affine(geo.shift_matrix(-12.0, 0.0), shape)
    assert np.allclose(track.visible_fraction(), [0.4, 1.0])
    kept_boxes, kept = track.to_boxes(min_visible_fraction=0.5)
    assert kept.tolist() == [False, True]
    assert np.allclose(kept_boxes.xyxy_px, [[38, 50, 48, 60]])
    kept_boxes, kept = track.to_boxes(min_visible_fraction=0.3)
    assert np.allclose(kept_boxes.xyxy_px[0], [0, 0, 8, 20])  # clipped to the image


def test_parts_that_leave_the_image_do_not_come_back() -> None:
    shape = (100, 100)
    boxes = geo.Boxes(np.array([0]), np.array([[0.0, 40.0, 20.0, 60.0]]))
    track = geo.BoxTrack.from_boxes(boxes, shape)
    track = track.affine(geo.shift_matrix(-10.0, 0.0), shape).affine(
        geo.shift_matrix(10.0, 0.0), shape)
    assert np.isclose(track.visible_fraction()[0], 0.5)
    assert np.allclose(shapely.bounds(track.visible[0]), [10, 40, 20, 60])


def test_integer_permutation_detection() -> None:
    assert geo.integer_permutation(geo.shift_matrix(2.0, -3.0)) is not None
    assert geo.integer_permutation(geo.shift_matrix(2.5, 0.0)) is None
    assert geo.integer_permutation(geo.rotation_matrix(10.0, (8, 8))) is None
    assert geo.integer_permutation(geo.rotation_matrix(90.0, (8, 8))) is not None
    assert geo.integer_permutation(geo.scale_matrix(2.0, (8, 8))) is None


@pytest.mark.parametrize("k", [1, 2, 3])
def test_exact_permutation_is_the_same_in_both_layouts(k: int) -> None:
    from geosim.augment.resample import interleave, permute_exact, planar

    img = np.random.default_rng(k).integers(0, 255, (3, 6, 6), dtype=np.uint8)
    mask = np.ones((6, 6), bool)
    mask[0, :2] = False
    m = geo.shift_matrix(1.0, 0.0) @ geo.rotation_matrix(90.0 * k, (6, 6))
    planes, pm = permute_exact(img, mask, m, bands_last=False)
    hwc, hm = permute_exact(interleave(img), mask, m, bands_last=True)
    assert np.array_equal(planes, planar(hwc)) and np.array_equal(pm, hm)
    expect = np.zeros_like(img)
    expect[:, :, 1:] = np.rot90(img * mask, k, axes=(1, 2))[:, :, :-1]
    assert np.array_equal(planes, expect)
    assert permute_exact(img, mask, geo.shift_matrix(0.5, 0.0), bands_last=False) is None
