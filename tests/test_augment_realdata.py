"""Augmentation on real imagery (../shared/realdata; skipped when absent)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geosim.augment.io import read_tile
from geosim.augment.pipeline import Pipeline

GEOMETRIC = Pipeline.from_dict({"functions": [
    {"name": "mirror"}, {"name": "rotate"}, {"name": "scale"}, {"name": "shear"},
    {"name": "alignment", "image": "b"}]})


def _records(rotation_deg: float, factor: float, shear_x: float, align: tuple[float, float]):
    params = [{"flip_ud": False, "flip_lr": True}, {"rotation_deg": rotation_deg},
              {"ratio": factor - 1.0, "factor": factor}, {"shear_x": shear_x, "shear_y": 0.0},
              {"image": "b", "dx_px": align[0], "dy_px": align[1]}]
    return [{"step": i, "function": s.function.name, "applied": True, "params": p}
            for i, (s, p) in enumerate(zip(GEOMETRIC.steps, params, strict=True))]


def _shift(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shift of b relative to a (pixels, x and y) by phase correlation of the central crop."""
    r0, c0 = a.shape[1] // 4, a.shape[2] // 4
    crop = (slice(r0, 3 * r0), slice(c0, 3 * c0))
    la = a.astype(np.float32).mean(0)[crop]
    lb = b.astype(np.float32).mean(0)[crop]
    win = cv2.createHanningWindow(la.shape[::-1], cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(la.copy(), lb.copy(), win)  # OpenCV 5 writes into inputs
    return np.array([dx, dy])


@pytest.mark.parametrize("name", ["SJER_004.tif", "SJER_006.tif"])
def test_real_pair_keeps_its_misregistration_and_alignment_adds_exactly(realdata, name) -> None:
    """2017 vs 2018 flights of the same plot: real change, real small misregistration s.
    The same affine A on both images turns s into L·s (L = linear part of A); the alignment
    function then adds exactly its drawn shift to image b only."""
    a = read_tile(realdata / "sjer_2017" / name, what="2017").data
    b = read_tile(realdata / "sjer_2018" / name, what="2018").data
    s_in = _shift(a.image, b.image)
    for rot, fac, shx, align in ((12.0, 1.05, 0.04, (0.0, 0.0)), (-7.0, 0.95, -0.03, (3.0, -2.0))):
        res = GEOMETRIC.replay(a, b, _records(rot, fac, shx, align))
        lin = np.asarray(res.chain_a[0]["matrix_px"])[:2, :2]
        expect = lin @ s_in + np.array(align)
        assert np.abs(_shift(res.a.image, res.b.image) - expect).max() < 0.3


def test_irregular_alpha_footprint_rotates_with_the_image(realdata) -> None:
    """A real Pix4D footprint (alpha band): after a 20° rotation the valid pixels are those
    whose source pixel was valid and whose rotated centre stays in the frame."""
    tile = read_tile(realdata / "bali_farmland_35cm_rgba_epsg32750.tif", what="bali")
    img = tile.data
    assert 0.2 < img.mask.mean() < 0.95  # really irregular
    p = Pipeline.from_dict({"functions": [{"name": "rotate", "min_deg": 20, "max_deg": 20}]})
    res = p.apply(img, img, np.random.default_rng(0))
    rows, cols = img.shape
    # independent truth: rotate the valid pixel centres about the frame centre
    r, c = np.nonzero(img.mask)
    x, y = c + 0.5 - cols / 2, r + 0.5 - rows / 2
    t = np.deg2rad(20.0)
    xo, yo = x * np.cos(t) + y * np.sin(t) + cols / 2, -x * np.sin(t) + y * np.cos(t) + rows / 2
    expected = np.count_nonzero((xo >= 0) & (xo < cols) & (yo >= 0) & (yo < rows))
    assert abs(res.a.mask.sum() - expected) / expected < 0.01
    assert (res.a.image[:, ~res.a.mask] == 0).all()
