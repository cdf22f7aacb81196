"""The one-band grey render (:func:`geosim.diagnose.grey_render.grey_expected`) against the
luma of the full three-band render, on a generator scene, with every per-band and per-pixel
part of the forward model set: haze, a seam, moved objects, a global shift moved before
sampling or a local warp, a resampling's native grid and an LSI blur; and the simulator's
native cache against rendering from scratch."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from geosim.diagnose.grey_render import grey_expected
from geosim.diagnose.model import CompressionFit, ForwardModel, RadiometryChoice
from geosim.diagnose.seam import GainStep
from geosim.diagnose.simulate import QSimulator
from geosim.diagnose.stage_inputs import grey
from geosim.diagnose.stage_objects import SceneObjects
from geosim.physics.radiometry import luma, luma_weights
from tests.generator_cases import no_registration, scene_inputs

SAT_PX = 48


@pytest.fixture(scope="module")
def scene():
    inp, _ = scene_inputs({"haze": {"transmission": [0.9, 0.85, 0.8],
                                    "path_radiance_dn": [6.0, 8.0, 12.0]}}, 1.6, 5, SAT_PX)
    return inp


def _models(inp) -> dict[str, ForwardModel]:
    rows, cols = inp.grey.shape
    rng = np.random.default_rng(3)
    rr, cc = np.mgrid[0:rows, 0:cols]
    haze = RadiometryChoice("haze", {"transmission": [0.93, 0.9, 0.8],
                                     "path_radiance_dn": [7.0, 9.5, 14.0]}, {}, 5.0, {})
    colour = RadiometryChoice("colour_response", {"gain": [1.1, 0.95, 0.9],
                                                  "offset_dn": [1.0, -2.0, 3.0]}, {}, 5.0, {})
    seam = GainStep(normal_deg=30.0, offset_px=3.0, factor=1.07, fraction=0.5,
                    delta_bic=9.0, explained=0.5, side=(rr + 0.5 * cc) > rows * 0.6)
    objects = SceneObjects(objects=[], layer=rng.normal(0, 5, (3, rows, cols)))
    shift = no_registration()
    shift = replace(shift, applied=True, shift_px=(0.37, -0.61),
                    presampled=inp.simulate.shifted((0.37, -0.61)))
    warp = replace(no_registration(), applied=True,
                   field_px=(0.3 + 0.004 * (rr - rows / 2), -0.2 + 0.003 * (cc - cols / 2)))
    resampling = {"resampling": {"native_pitch_px": 1.37, "cubic_a": -0.5}}
    blur = {"atmospheric_blur": {"f0_cyc_per_px": 0.45}}
    base = ForwardModel(q=1.5, blur={}, registration=no_registration())
    return {
        "plain": base,
        "haze, seam, objects": base.without(radiometry=haze, seam=seam, objects=objects),
        "colour, shift, resampling": base.without(radiometry=colour, registration=shift,
                                                  blur=resampling, native_phase_px=(0.4, 1.1)),
        "warp, blur, resampling, haze": base.without(registration=warp, radiometry=haze,
                                                     blur={**blur, **resampling},
                                                     native_phase_px=(0.9, 0.2)),
        "below q_min, warp": base.without(q=0.55, registration=warp, seam=seam),
    }


@pytest.mark.parametrize("name", ["plain", "haze, seam, objects", "colour, shift, resampling",
                                  "warp, blur, resampling, haze", "below q_min, warp"])
def test_grey_render_equals_luma_of_the_full_render(scene, name: str) -> None:
    m = _models(scene)[name]
    full = grey(m.deterministic(scene.simulate))
    one = grey_expected(scene, m)
    spread = float(np.ptp(full))
    assert spread > 20.0
    assert np.max(np.abs(one - full)) < 1e-6 * spread


def test_grey_render_with_invalid_pixels_and_under_jpeg(scene) -> None:
    """Invalid UAV pixels: filled as the paper's model fills them (linear, so the one-band
    render still equals the three-band luma); JPEG is not linear: the full render's luma,
    exactly."""
    uav = np.asarray(scene.simulate.uav)
    valid = np.ones(uav.shape[-2:], bool)       # on the UAV's fine grid
    valid[:60, :90] = False
    sim = QSimulator(uav, phi=scene.simulate.phi, q_min=0.6, valid=valid)
    inp = replace(scene, simulate=sim)
    m = _models(inp)["haze, seam, objects"]
    full = grey(m.deterministic(sim))
    assert np.max(np.abs(grey_expected(inp, m) - full)) < 1e-6 * float(np.ptp(full))
    jpeg = m.without(compression=CompressionFit(quality=70, offset_px=(0, 0), test={}))
    assert np.array_equal(grey_expected(inp, jpeg), grey(jpeg.deterministic(sim)))


def test_luma_weights_match_luma() -> None:
    img = np.random.default_rng(0).uniform(0, 255, (4, 5, 6))
    assert np.allclose(np.tensordot(luma_weights(4), img, axes=1), luma(img))
    assert np.allclose(np.tensordot(luma_weights(1), img[:1], axes=1), luma(img[:1]))
    with pytest.raises(ValueError, match="1 or ≥3 bands"):
        luma_weights(2)


def test_native_cache_renders_at_the_key_q(scene) -> None:
    """Two Q that round to the same cache key render the same image in either order (the
    optics' image was once cached at whichever Q came first)."""
    sim = scene.simulate
    a, b = 1.50004, 1.49996
    first = sim.native(a, 1.4, phase_px=(0.2, 0.3))
    then = sim.native(b, 1.4, phase_px=(0.2, 0.3))
    fresh = QSimulator(np.asarray(sim.uav), phi=sim.phi, q_min=0.6)
    other_order = fresh.native(b, 1.4, phase_px=(0.2, 0.3))
    assert np.array_equal(first, then)
    assert np.array_equal(first, other_order)
    assert np.array_equal(first, fresh.native(1.5, 1.4, phase_px=(0.2, 0.3)))
