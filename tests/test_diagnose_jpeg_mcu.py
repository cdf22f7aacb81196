"""The JPEG's 16 px minimum coded units (4:2:0 chroma) and the radiometric fit under JPEG.

Truth from outside geosim: the scenes are encoded by Pillow (libjpeg's 4:2:0 and 4:4:4),
cut at known offsets, so where the MCU edges lie is known by construction; the haze is
applied by hand before the encoding.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geosim.diagnose.effects import get_effect
from geosim.diagnose.model import CompressionFit, ForwardModel
from geosim.diagnose.select import MIN_DELTA_BIC
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.diagnose.stage_jpeg import mcu_grid
from geosim.diagnose.stage_radiometry import fit_scene_radiometry
from tests.helpers import area_averaged_rgb, no_registration, pillow_jpeg

SIDE_PX = 128
#: the scene is cut from a larger encoded image at these (row, col) offsets
CUTS = [(0, 0), (3, 11), (8, 8), (12, 4), (5, 14)]


@pytest.fixture(scope="module")
def pasture(realdata) -> np.ndarray:
    """A real colour scene, 160 px (0.1 m imagery area-averaged 8x), bands first, DN."""
    return area_averaged_rgb(realdata / "brazil_pasture_10cm_epsg3395.tif", start_px=800,
                             size_px=1280, side_px=160)


def _patches(seed: int = 4) -> np.ndarray:
    """A synthetic colour scene: 40 fields of random colour with texture, 160 px."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:160, 0:160]
    centres = rng.uniform(0, 160, (40, 2))
    label = np.argmin((yy[..., None] - centres[:, 0]) ** 2
                      + (xx[..., None] - centres[:, 1]) ** 2, axis=-1)
    colours = rng.uniform(40, 200, (40, 3))
    img = np.moveaxis(colours[label], -1, 0) + rng.normal(0, 6, (3, 160, 160))
    return np.stack([cv2.GaussianBlur(b, (0, 0), 1.0) for b in img])


@pytest.mark.parametrize("cut", CUTS)
def test_mcu_phase_of_apillow_jpeg(pasture, cut):
    """The phase mod 16 where the encoder's MCUs start, for real and synthetic colour,
    from the 8x8 grid alone (which leaves two candidates per axis)."""
    r, c = cut
    want = ((-r) % 16, (-c) % 16)
    for scene in (pasture, _patches()):
        real = pillow_jpeg(scene, 40)[:, r:r + SIDE_PX, c:c + SIDE_PX]
        mask = np.ones(real.shape[-2:], bool)
        phase, ratio = mcu_grid(real, mask, (want[0] % 8, want[1] % 8))
        assert phase == want
        assert min(ratio) > 2.0
        # the 8x8 grid given off by 8 px changes nothing: the chroma decides
        assert mcu_grid(real, mask, ((want[0] + 8) % 8, want[1] % 8))[0] == want


def test_mcu_phase_without_subsampling_has_no_preference(pasture):
    """4:4:4 chroma is coded in 8x8 blocks: both candidates step alike."""
    real = pillow_jpeg(pasture, 40, subsampling=0)[:, 3:3 + SIDE_PX, 11:11 + SIDE_PX]
    _, ratio = mcu_grid(real, np.ones(real.shape[-2:], bool), (5, 5))
    assert max(ratio) < 1.5


def test_compression_effect_on_the_mcu_grid_reproduces_pillow(pasture):
    """geosim's JPEG (OpenCV) at the right MCU phase gives Pillow's pixels away from the
    padded first units (mean |difference| 0.34 DN: the two libraries' decoders differ a
    little); at the phase 8 px off it mixes the colours of neighbouring MCUs (0.94 DN)."""
    r, c = 5, 14
    full = np.clip(np.rint(pasture), 0, 255)
    want = pillow_jpeg(full, 30)[:, r:r + SIDE_PX, c:c + SIDE_PX]
    cut = full[:, r:r + SIDE_PX, c:c + SIDE_PX]
    phase = ((-r) % 16, (-c) % 16)
    comp = get_effect("compression")
    right = comp.apply(cut, quality=30, block_offset_px=phase)
    wrong = comp.apply(cut, quality=30, block_offset_px=((phase[0] + 8) % 16, phase[1]))
    inner = (slice(None), slice(16 + phase[0], None), slice(16 + phase[1], None))
    err_right = np.mean(np.abs(right - want)[inner])
    err_wrong = np.mean(np.abs(wrong - want)[inner])
    assert err_right < 0.5
    assert err_wrong > 2 * err_right


def _inputs(real: np.ndarray, model_img: np.ndarray) -> Inputs:
    return Inputs(real=real, grey=grey(real), valid=np.ones(real.shape[-2:], bool),
                  simulate=lambda q: model_img, base=model_img, q_base=1.0, block_px=32,
                  quantized=True, gsd_m=0.5)


def _model(compression: CompressionFit | None) -> ForwardModel:
    reg = no_registration()
    return ForwardModel(q=1.0, blur={}, registration=reg, compression=compression)


@pytest.mark.parametrize("make_scene", ["pasture", "patches"])
def test_jpeg_chroma_loss_is_not_haze(pasture, make_scene):
    """A JPEG 20 alone (Pillow, cut at (5, 14)): fitted against the model re-encoded at
    the found quality and MCU phase, no radiometric evidence at all (ΔBIC over the
    identity ≤ 0); against the model without the JPEG, on the real pasture, the lost
    colour contrast is evidence for a radiometric effect (ΔBIC 63-77 measured at
    blurs of 0-3 px; not claimed here only because its size stays under 1 DN)."""
    scene = pasture if make_scene == "pasture" else _patches()
    r, c = 5, 14
    full = np.clip(np.rint(scene), 0, 255)
    real = pillow_jpeg(full, 20)[:, r:r + SIDE_PX, c:c + SIDE_PX]
    model_img = full[:, r:r + SIDE_PX, c:c + SIDE_PX]
    mask = np.ones(real.shape[-2:], bool)
    phase, _ = mcu_grid(real, mask, ((-r) % 8, (-c) % 8))
    inp = _inputs(real, model_img)
    with_jpeg = fit_scene_radiometry(inp, _model(CompressionFit(20, phase, {})), mask)
    assert with_jpeg.radiometry is not None and with_jpeg.radiometry.name is None
    assert with_jpeg.radiometry.delta_bic <= 0.0
    if make_scene == "pasture":
        without = fit_scene_radiometry(inp, _model(None), mask).radiometry
        assert without is not None and without.delta_bic > MIN_DELTA_BIC


def test_haze_under_jpeg_recovered(pasture):
    """Haze applied before a JPEG 30 (transmission rising and path radiance falling
    from blue to red, as scattering has them) is named and its parameters recovered."""
    t_true = np.array([0.90, 0.86, 0.80])
    p_true = np.array([6.0, 10.0, 16.0])
    r, c = 3, 11
    full = np.clip(np.rint(pasture), 0, 255)
    hazy = t_true[:, None, None] * full + p_true[:, None, None]
    real = pillow_jpeg(hazy, 30)[:, r:r + SIDE_PX, c:c + SIDE_PX]
    model_img = full[:, r:r + SIDE_PX, c:c + SIDE_PX]
    mask = np.ones(real.shape[-2:], bool)
    phase, _ = mcu_grid(real, mask, ((-r) % 8, (-c) % 8))
    fit = fit_scene_radiometry(_inputs(real, model_img),
                               _model(CompressionFit(30, phase, {})), mask).radiometry
    assert fit is not None and fit.name == "haze"
    # over one scene's brightness range transmission and path radiance trade against
    # each other (T·x + P): the transmission within 0.03 and each band's mean level
    # within 1 DN (the path radiance alone came out 10.0 / 10.6 / 12.2 for 6 / 10 / 16)
    t_fit = np.asarray(fit.params["transmission"])
    p_fit = np.asarray(fit.params["path_radiance_dn"])
    assert np.allclose(t_fit, t_true, atol=0.03)
    mean_dn = model_img.mean(axis=(1, 2))
    assert np.allclose(t_fit * mean_dn + p_fit, t_true * mean_dn + p_true, atol=1.0)
