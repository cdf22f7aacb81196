"""A shift + rotation + scale misregistration moved on the fine grid, before the optics.

The truth is made without geosim's warp: the UAV image is rotated and scaled on the fine
grid by OpenCV's ``warpAffine`` (Lanczos), then put through the paper's model.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.coregister import warp_by_field
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.simulate import QSimulator, paper_model
from geosim.diagnose.stage_inputs import make_inputs
from geosim.diagnose.stage_register import coregister
from geosim.physics.geometry import AffineField, affine_field, warp_to_fine_grid

PHI = 10
ROTATION_DEG = 0.6
SCALE = 0.996
SHIFT_PX = (0.37, -0.24)     # (d_col, d_row), satellite pixels


def _texture(n: int, seed: int, sigma_px: float = 2.0) -> np.ndarray:
    """A grey texture with content up to a few fine pixels (DN around 100)."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.normal(size=(n, n)), sigma_px)
    return 100.0 + 40.0 * img / img.std()


def _field_maps(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(d_col, d_row) of the misregistration on the satellite grid: out(x) = in(x − d(x)),
    rotation and scale about the scene's centre."""
    rows, cols = np.indices(shape).astype(float)
    cr, cc = (shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0
    th = np.deg2rad(ROTATION_DEG)
    a = SCALE * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) - np.eye(2)
    x, y = cols - cc, rows - cr
    return (SHIFT_PX[0] + a[0, 0] * x + a[0, 1] * y,
            SHIFT_PX[1] + a[1, 0] * x + a[1, 1] * y)


def _opencv_warp(fine: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The fine image moved by the field with OpenCV (inverse map: out(x) = in(M x)), the
    field carried to the fine grid from its affine coefficients worked out here."""
    f = affine_field(*maps)
    h = (PHI - 1) / 2.0
    a0, a1, a2 = f.col
    b0, b1, b2 = f.row
    # source x (col) = C − [φ a0 + a1 (C − h) + a2 (R − h)], y (row) likewise with b
    m = np.array([[1 - a1, -a2, -PHI * a0 + (a1 + a2) * h],
                  [-b1, 1 - b2, -PHI * b0 + (b1 + b2) * h]])
    return cv2.warpAffine(fine.astype(np.float64), m, fine.shape[::-1],
                          flags=cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def test_affine_field_reads_a_field_and_refuses_one_that_is_not():
    maps = _field_maps((20, 24))
    f = affine_field(*maps)
    rows, cols = np.indices((20, 24))
    assert np.allclose(f.col[0] + f.col[1] * cols + f.col[2] * rows, maps[0], atol=1e-12)
    assert np.allclose(f.row[0] + f.row[1] * cols + f.row[2] * rows, maps[1], atol=1e-12)
    bent = (maps[0] + 1e-3 * (cols - 12.0) ** 2, maps[1])
    with pytest.raises(ValueError, match="not affine"):
        affine_field(*bent)


def test_fine_grid_warp_matches_opencv():
    fine = _texture(400, 1, sigma_px=3.0)
    maps = _field_maps((40, 40))
    ours = warp_to_fine_grid(fine, affine_field(*maps), PHI)
    ref = _opencv_warp(fine, maps)
    inner = (slice(40, -40), slice(40, -40))
    rms = float(np.sqrt(np.mean((ours - ref)[inner] ** 2)))
    moved_by = float(np.sqrt(np.mean((fine - ref)[inner] ** 2)))
    # spline against Lanczos on content of σ 3 px; OpenCV places its taps to 1/32 px
    assert rms < 0.01 * fine.std() and rms < 0.02 * moved_by
    # a pure shift is a Fourier shift by φ·d
    shift_only = AffineField(col=(0.23, 0.0, 0.0), row=(-0.41, 0.0, 0.0))
    moved = warp_to_fine_grid(fine, shift_only, PHI)
    spec = np.fft.fft2(fine)
    fy = np.fft.fftfreq(400)[:, None]
    fx = np.fft.fftfreq(400)[None, :]
    fourier = np.real(np.fft.ifft2(spec * np.exp(-2j * np.pi * (fx * 2.3 + fy * -4.1))))
    # (the FFT wraps the image round: its edge rings, hence RMS over the inner part)
    assert float(np.sqrt(np.mean((moved - fourier)[inner] ** 2))) < 0.005 * fine.std()


@pytest.mark.parametrize("q", [0.8, 1.6])
def test_warped_simulator_renders_the_moved_scene(q):
    """Against the paper's model of the UAV image warped by OpenCV: the warp on the fine
    grid matches, and at Q 0.8 (optics passing content above the satellite Nyquist) it
    is several times closer than warping the sampled simulation."""
    fine = _texture(640, 2)
    maps = _field_maps((64, 64))
    truth = paper_model(_opencv_warp(fine, maps)[np.newaxis], q=q, phi=PHI)[0]
    sim = QSimulator(fine[np.newaxis].astype(np.float32), phi=PHI, q_min=0.6)
    warped = sim.warped(affine_field(*maps))
    assert warped is not None and sim.warped(affine_field(*maps)) is warped  # kept
    on_fine = warped(q)[0]
    on_sampled = warp_by_field(sim(q)[0], *maps)
    inner = (slice(6, -6), slice(6, -6))
    err_fine = float(np.sqrt(np.mean((on_fine - truth)[inner] ** 2)))
    err_sampled = float(np.sqrt(np.mean((on_sampled - truth)[inner] ** 2)))
    assert err_fine < 0.01 * float(truth.std())
    if q < 1.0:
        assert err_fine < err_sampled / 3.0
    # its fine-grid renders are moved too: a blur variant of it at no blur is itself
    variant = warped.variant(transfer=lambda fy, fx: np.ones_like(fy), key="none")
    assert variant is not None
    assert np.allclose(variant(q)[0], on_fine, atol=1e-3)


def test_invalid_uav_pixels_are_filled_before_the_fine_grid_renders():
    """Invalid UAV pixels (a flight's nodata rim) are filled as the paper's model fills
    them, so the fine-grid renders exist; away from the rim they are the renders of the
    complete image."""
    fine = _texture(640, 3)
    valid = np.ones(fine.shape, bool)
    valid[:, :40] = False                       # 4 satellite columns
    holed = np.where(valid, fine, 0.0)[np.newaxis].astype(np.float32)
    sim = QSimulator(holed, phi=PHI, valid=valid, q_min=0.6)
    whole = QSimulator(fine[np.newaxis].astype(np.float32), phi=PHI, q_min=0.6)
    field = affine_field(*_field_maps((64, 64)))
    smear = {"transfer": lambda fy, fx: np.sinc(1.5 * fx), "key": "smear 1.5 px"}
    far = (slice(8, -8), slice(16, -8))          # ≥ 12 satellite px from the rim
    for a, b in ((sim.warped(field), whole.warped(field)),
                 (sim.variant(**smear), whole.variant(**smear)),
                 (sim.variant(shift_px=(0.3, -0.2)), whole.variant(shift_px=(0.3, -0.2)))):
        assert a is not None
        assert np.abs(a(1.2)[0] - b(1.2)[0])[far].max() < 1e-3 * fine.std()
    native = sim.native(1.2, 1.4)
    assert native is not None
    assert np.abs(native[0] - whole.native(1.2, 1.4)[0])[far].max() < 1e-3 * fine.std()


def test_coregister_moves_a_rotated_scene_on_the_fine_grid():
    """A scene rotated by 0.6° (corners ≈ 0.5 px): the registration finds the field, moves
    the UAV image before the optics, and its render fits the scene better than the
    sampled simulation warped by the same field."""
    q = 0.9
    fine = _texture(1280, 4)
    maps = _field_maps((128, 128))
    real = np.rint(paper_model(_opencv_warp(fine, maps)[np.newaxis], q=q, phi=PHI))
    sim = QSimulator(fine[np.newaxis].astype(np.float32), phi=PHI, q_min=0.6)
    inp = make_inputs(real, sim, q, None, None, None, 0.5)
    reg = coregister(inp)
    assert reg.field_px is not None and reg.before_sampling
    assert isinstance(reg.presampled, QSimulator)
    model = ForwardModel(q=q, blur={}, registration=reg)
    inner = (slice(8, -8), slice(8, -8))
    on_fine = model.sim_at(sim)[0]
    on_sampled = reg.move(sim(q))[0]
    rms_fine = float(np.sqrt(np.mean((on_fine - real[0])[inner] ** 2)))
    rms_sampled = float(np.sqrt(np.mean((on_sampled - real[0])[inner] ** 2)))
    assert rms_fine < rms_sampled
