"""The TOML pipeline: parsing, reproducibility, replay, fusion of affine steps, metadata."""

from __future__ import annotations

import numpy as np
import pytest

from geosim.augment import Boxes, Pipeline, default_config_path, load_pipeline
from geosim.augment.pipeline import AugImage, AugmentResult
from geosim.errors import ConfigError, InputFileError

SHAPE = (64, 72)


def _pair(dtype=np.uint8, bands: int = 3) -> tuple[AugImage, AugImage]:
    rng = np.random.default_rng(5)
    hi = 255 if dtype != np.uint16 else 65535
    imgs = []
    for _ in range(2):
        img = rng.integers(0, hi, (bands, *SHAPE)).astype(dtype)
        imgs.append(AugImage(img, np.ones(SHAPE, bool),
                             Boxes(np.array([0]), np.array([[20.0, 20.0, 40.0, 34.0]]))))
    return imgs[0], imgs[1]


def test_shipped_example_config_loads_with_all_twelve_functions() -> None:
    p = load_pipeline()
    assert default_config_path().is_file()
    assert {s.function.name for s in p.steps} == {
        "rotate", "alignment", "shift", "colour", "hue", "saturation", "value", "mirror",
        "scale", "noise", "shear", "local_warp"}
    assert p.reference_gsd_m == 0.05
    assert Pipeline.from_dict(p.to_dict()) == p


def test_toml_file_round_trip_and_errors(tmp_path) -> None:
    f = tmp_path / "aug.toml"
    f.write_text('[pipeline]\nmin_visible_fraction = 0.3\n\n[[functions]]\nname = "rotate"\n'
                 'probability = 0.5\nmin_deg = -3\nmax_deg = 3\n')
    p = Pipeline.from_toml(f)
    assert p.min_visible_fraction == 0.3 and p.steps[0].probability == 0.5
    assert p.steps[0].function.min_deg == -3.0
    f.write_text("[pipeline\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        Pipeline.from_toml(f)
    f.write_text("[pipeline]\nspeed = 3\n")
    with pytest.raises(ConfigError, match="unknown \\[pipeline\\] key"):
        Pipeline.from_toml(f)
    with pytest.raises(InputFileError, match="does not exist"):
        Pipeline.from_toml(tmp_path / "missing.toml")


def test_same_seed_same_output_and_records_different_seed_differs() -> None:
    p = load_pipeline()
    a, b = _pair()
    r1 = p.apply(a, b, np.random.default_rng(42))
    r2 = p.apply(a, b, np.random.default_rng(42))
    r3 = p.apply(a, b, np.random.default_rng(43))
    assert r1.records == r2.records
    for x, y in ((r1.a, r2.a), (r1.b, r2.b)):
        assert np.array_equal(x.image, y.image) and np.array_equal(x.mask, y.mask)
        assert np.array_equal(x.boxes.xyxy_px, y.boxes.xyxy_px)
    assert r1.records != r3.records


def test_replay_of_records_reproduces_the_output() -> None:
    p = load_pipeline()
    a, b = _pair()
    for seed in range(4):
        r = p.apply(a, b, np.random.default_rng(seed), length_scale=0.1)
        again = p.replay(a, b, r.records)
        assert np.array_equal(r.a.image, again.a.image)
        assert np.array_equal(r.b.image, again.b.image)


def test_affine_steps_are_fused_so_rotating_there_and_back_loses_nothing() -> None:
    p = Pipeline.from_dict({"functions": [{"name": "rotate", "min_deg": 30, "max_deg": 30},
                                          {"name": "rotate", "min_deg": -30, "max_deg": -30}]})
    a, b = _pair()
    r = p.apply(a, b, np.random.default_rng(0))
    assert np.array_equal(r.a.image, a.image) and r.a.mask.all()
    assert r.chain_a == [] and r.on_map_grid == (True, True)


def test_photometric_only_stays_on_the_grid_and_geometric_does_not() -> None:
    a, b = _pair()
    photo = Pipeline.from_dict({"functions": [{"name": "colour"}, {"name": "noise"}]})
    r = photo.apply(a, b, np.random.default_rng(0))
    assert r.on_map_grid == (True, True)
    assert [s["kind"] for s in r.chain_a] == ["photometric"]
    assert np.array_equal(r.a.boxes.xyxy_px, a.boxes.xyxy_px)  # boxes untouched
    geo = Pipeline.from_dict({"functions": [{"name": "shear", "sigma_x": 0.1},
                                            {"name": "colour"}]})
    r = geo.apply(a, b, np.random.default_rng(0))
    assert r.on_map_grid == (False, False)
    assert [s["kind"] for s in r.chain_a] == ["affine", "photometric"]


def test_pixel_to_source_matrix_maps_output_pixels_back() -> None:
    p = Pipeline.from_dict({"functions": [{"name": "rotate"}, {"name": "scale"}]})
    a, b = _pair()
    r = p.apply(a, b, np.random.default_rng(3))
    back = AugmentResult.pixel_to_source(r.chain_a)
    # the box centre in the output, mapped back, is the box centre in the source
    x0, y0, x1, y1 = r.a.boxes.xyxy_px[0]
    src = back @ [(x0 + x1) / 2, (y0 + y1) / 2, 1.0]
    assert np.allclose(src[:2], [30.0, 27.0], atol=1e-9)
    warp = Pipeline.from_dict({"functions": [{"name": "local_warp", "max_px": 2.0,
                                              "filter_sigma_px": 10.0}]})
    assert AugmentResult.pixel_to_source(warp.apply(a, b, np.random.default_rng(0)).chain_a) \
        is None


def test_lengths_follow_the_gsd() -> None:
    p = Pipeline.from_dict({"pipeline": {"reference_gsd_m": 0.05},
                            "functions": [{"name": "local_warp", "max_px": 10.0,
                                           "filter_sigma_px": 100.0}]})
    assert p.length_scale(0.5) == pytest.approx(0.1) and p.length_scale(None) == 1.0
    rec = p.draw(np.random.default_rng(0), length_scale=p.length_scale(0.5))[0]["params"]
    assert rec["max_px"] == pytest.approx(1.0) and rec["filter_sigma_px"] == pytest.approx(10.0)


@pytest.mark.parametrize("dtype", [np.uint16, np.float32])
def test_other_dtypes_keep_their_dtype(dtype) -> None:
    a, b = _pair(dtype)
    r = load_pipeline().apply(a, b, np.random.default_rng(1), length_scale=0.1)
    assert r.a.image.dtype == dtype and r.b.image.dtype == dtype


def test_hue_leaves_extra_bands_alone() -> None:
    a, b = _pair(bands=4)
    p = Pipeline.from_dict({"functions": [{"name": "hue", "sigma_deg": 40.0}]})
    r = p.apply(a, b, np.random.default_rng(0))
    assert np.array_equal(r.a.image[3], a.image[3]) and not np.array_equal(r.a.image[:3],
                                                                           a.image[:3])


def test_pair_of_different_shapes_is_refused() -> None:
    a, _ = _pair()
    small = AugImage(a.image[:, :10, :10], a.mask[:10, :10])
    with pytest.raises(ValueError, match="same shape"):
        load_pipeline().apply(a, small, np.random.default_rng(0))
