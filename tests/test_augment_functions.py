"""The twelve functions: pair consistency, identities, parameter distributions, config checks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import stats

from geosim.augment import functions as fn
from geosim.augment.geometry import Boxes
from geosim.augment.pipeline import AugImage, Pipeline
from geosim.errors import ConfigError

SHAPE = (48, 56)


def _sample(seed: int = 0) -> AugImage:
    rng = np.random.default_rng(seed)
    img = rng.integers(20, 235, (3, *SHAPE), dtype=np.uint8)
    mask = np.ones(SHAPE, bool)
    mask[:6, :9] = False
    img[:, ~mask] = 0
    boxes = Boxes(np.array([0, 0, 1]), np.array([[10.0, 12.0, 20.0, 18.0], [30, 30, 41, 44],
                                                 [40, 5, 50, 15]]))
    return AugImage(img, mask, boxes)


def _pipeline(name: str, **params) -> Pipeline:
    return Pipeline.from_dict({"pipeline": {"min_visible_fraction": 0.0},
                               "functions": [{"name": name, **params}]})


def _same(x: AugImage, y: AugImage) -> bool:
    return (np.array_equal(x.image, y.image) and np.array_equal(x.mask, y.mask)
            and np.array_equal(x.boxes.xyxy_px, y.boxes.xyxy_px)
            and np.array_equal(x.boxes.class_id, y.boxes.class_id))


ACTIVE = {
    "rotate": {"min_deg": 5.0, "max_deg": 25.0},
    "shift": {"sigma_px": 3.0},
    "colour": {"sigma_dn": 20.0},
    "hue": {"sigma_deg": 30.0},
    "saturation": {"sigma_dn": 30.0},
    "value": {"sigma_dn": 30.0},
    "mirror": {"p_ud": 1.0, "p_lr": 0.5},
    "scale": {"sigma": 0.1},
    "noise": {"sigma_dn": 5.0},
    "shear": {"sigma_x": 0.1, "sigma_y": 0.1},
    "local_warp": {"max_px": 2.0, "filter_sigma_px": 8.0, "mode": "together"},
}

ZERO = {
    "rotate": {"min_deg": 0.0, "max_deg": 0.0},
    "alignment": {"sigma_px": 0.0},
    "shift": {"sigma_px": 0.0},
    "colour": {"sigma_dn": 0.0},
    "hue": {"sigma_deg": 0.0},
    "saturation": {"sigma_dn": 0.0},
    "value": {"sigma_dn": 0.0},
    "mirror": {"p_ud": 0.0, "p_lr": 0.0},
    "scale": {"sigma": 0.0},
    "noise": {"sigma_dn": 0.0},
    "shear": {"sigma_x": 0.0, "sigma_y": 0.0},
    "local_warp": {"max_px": 0.0, "filter_sigma_px": 8.0},
}


def test_the_twelve_functions_are_all_covered() -> None:
    assert set(fn.FUNCTIONS) == set(ZERO) and len(fn.FUNCTIONS) == 12
    assert set(ACTIVE) | {"alignment"} == set(fn.FUNCTIONS)


@pytest.mark.parametrize("name", sorted(ACTIVE))
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1))
def test_identical_pair_stays_identical(name: str, seed: int) -> None:
    src = _sample()
    res = _pipeline(name, **ACTIVE[name]).apply(src, src, np.random.default_rng(seed))
    assert _same(res.a, res.b)
    assert res.chain_a == res.chain_b
    assert res.chain_a, "the function did nothing"  # (a tiny draw may still round away)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_alignment_moves_exactly_one_image(seed: int) -> None:
    src = _sample()
    res = _pipeline("alignment", sigma_px=3.0).apply(src, src, np.random.default_rng(seed))
    moved = res.records[0]["params"]["image"]
    still, shifted = (res.b, res.a) if moved == "a" else (res.a, res.b)
    assert _same(still, src)
    assert not _same(shifted, src)
    assert res.on_map_grid == ((moved != "a"), (moved != "b"))


@pytest.mark.parametrize("name, params", [
    ("local_warp", {"max_px": 2.0, "filter_sigma_px": 8.0, "mode": "independent"}),
    ("noise", {"sigma_dn": 5.0, "independent": True}),
    ("colour", {"sigma_dn": 20.0, "independent": True}),
    ("hue", {"sigma_deg": 20.0, "independent": True}),
])
def test_independent_modes_treat_the_images_differently(name: str, params: dict) -> None:
    src = _sample()
    res = _pipeline(name, **params).apply(src, src, np.random.default_rng(1))
    assert not _same(res.a, res.b)


@pytest.mark.parametrize("name", sorted(ZERO))
def test_zero_parameters_are_the_identity(name: str) -> None:
    src = _sample()
    for seed in range(3):
        res = _pipeline(name, **ZERO[name]).apply(src, src, np.random.default_rng(seed))
        assert _same(res.a, src) and _same(res.b, src)
        assert res.chain_a == [] and res.on_map_grid == (True, True)
        assert res.a.image is not src.image  # a copy, never the caller's array


def test_probability_zero_is_the_identity() -> None:
    src = _sample()
    res = _pipeline("rotate", probability=0.0, **ACTIVE["rotate"]).apply(
        src, src, np.random.default_rng(0))
    assert _same(res.a, src) and res.records[0]["applied"] is False


def test_mirror_twice_is_the_identity() -> None:
    src = _sample()
    both = {"name": "mirror", "p_ud": 1.0, "p_lr": 1.0}
    twice = Pipeline.from_dict({"functions": [both, both]})
    res = twice.apply(src, src, np.random.default_rng(0))
    assert _same(res.a, src)
    once = Pipeline.from_dict({"functions": [both]})
    first = once.apply(src, src, np.random.default_rng(0))
    second = once.apply(first.a, first.b, np.random.default_rng(0))
    assert _same(second.a, src) and not _same(first.a, src)


# ------------------------------------------------------------------ parameter distributions

N_DRAWS = 3000


def _draws(f: fn.AugmentFunction, key, *, seed: int = 0, length_scale: float = 1.0):
    rng = np.random.default_rng(seed)
    recs = [f.draw(rng, length_scale=length_scale) for _ in range(N_DRAWS)]
    return np.array([key(r) for r in recs])


def test_rotation_is_uniform_on_min_max() -> None:
    x = _draws(fn.Rotate(min_deg=-7.0, max_deg=13.0), lambda r: r["rotation_deg"])
    assert x.min() >= -7.0 and x.max() <= 13.0
    assert stats.kstest(x, "uniform", args=(-7.0, 20.0)).pvalue > 0.01
    # the test has power: a wrong interval is rejected
    assert stats.kstest(x, "uniform", args=(-6.0, 20.0)).pvalue < 0.01


@pytest.mark.parametrize("f, key, sigma", [
    (fn.Shift(sigma_px=4.0), lambda r: r["dx_px"], 4.0 * 0.1),
    (fn.Shift(sigma_px=4.0), lambda r: r["dy_px"], 4.0 * 0.1),
    (fn.Alignment(sigma_px=30.0), lambda r: r["dx_px"], 30.0 * 0.1),
    (fn.Colour(sigma_dn=12.0), lambda r: r["shift_g_dn"], 12.0),
    (fn.Hue(sigma_deg=6.0), lambda r: r["hue_deg"], 6.0),
    (fn.Saturation(sigma_dn=9.0), lambda r: r["saturation_dn"], 9.0),
    (fn.Value(sigma_dn=15.0), lambda r: r["value_dn"], 15.0),
    (fn.Scale(sigma=0.08), lambda r: r["ratio"], 0.08),
    (fn.Shear(sigma_x=0.05, sigma_y=0.02), lambda r: r["shear_x"], 0.05),
    (fn.Shear(sigma_x=0.05, sigma_y=0.02), lambda r: r["shear_y"], 0.02),
])
def test_gaussian_parameters_follow_their_distribution(f, key, sigma) -> None:
    x = _draws(f, key, length_scale=0.1)  # lengths scale with the GSD; others do not
    assert stats.kstest(x, "norm", args=(0.0, sigma)).pvalue > 0.01
    assert stats.kstest(x, "norm", args=(0.0, 1.2 * sigma)).pvalue < 0.01


def test_colour_channels_are_independent() -> None:
    x = _draws(fn.Colour(sigma_dn=10.0), lambda r: (r["shift_r_dn"], r["shift_b_dn"]))
    assert abs(np.corrcoef(x[:, 0], x[:, 1])[0, 1]) < 0.06


def test_mirror_flips_are_independent_bernoullis() -> None:
    x = _draws(fn.Mirror(p_ud=0.3, p_lr=0.7), lambda r: (r["flip_ud"], r["flip_lr"]))
    ud, lr = x[:, 0].astype(bool), x[:, 1].astype(bool)
    assert stats.binomtest(int(ud.sum()), N_DRAWS, 0.3).pvalue > 0.01
    assert stats.binomtest(int(lr.sum()), N_DRAWS, 0.7).pvalue > 0.01
    assert stats.binomtest(int((ud & lr).sum()), N_DRAWS, 0.21).pvalue > 0.01
    assert stats.binomtest(int(ud.sum()), N_DRAWS, 0.35).pvalue < 0.01


def test_alignment_picks_each_image_half_the_time() -> None:
    x = _draws(fn.Alignment(sigma_px=1.0), lambda r: r["image"] == "a")
    assert stats.binomtest(int(x.sum()), N_DRAWS, 0.5).pvalue > 0.01
    fixed = _draws(fn.Alignment(sigma_px=1.0, image="b"), lambda r: r["image"])
    assert set(fixed) == {"b"}


def test_step_probability_is_a_bernoulli() -> None:
    p = Pipeline.from_dict({"functions": [{"name": "rotate", "probability": 0.25}]})
    rng = np.random.default_rng(0)
    applied = sum(p.draw(rng)[0]["applied"] for _ in range(N_DRAWS))
    assert stats.binomtest(applied, N_DRAWS, 0.25).pvalue > 0.01


def test_noise_seed_draws_reproduce_the_noise() -> None:
    f = fn.Noise(sigma_dn=4.0)
    rec = f.draw(np.random.default_rng(0))
    op_a, op_b = f.ops(rec, SHAPE)
    assert op_a.seed == op_b.seed == rec["seed"]
    w = np.full((*SHAPE, 3), 100.0, np.float32)  # kernels take (rows, cols, bands)
    out_a = op_a.func(w, 255.0, np.random.default_rng(op_a.seed))
    assert np.array_equal(out_a, op_b.func(w, 255.0, np.random.default_rng(op_b.seed)))
    d = (out_a - w).ravel()
    assert stats.kstest(d, "norm", args=(0.0, 4.0)).pvalue > 0.01


# ------------------------------------------------------------------ configuration checks


@pytest.mark.parametrize("entry, match", [
    ({"name": "spin"}, "unknown function 'spin'"),
    ({"name": "rotate", "min_deg": 5.0, "max_deg": -5.0}, "min_deg"),
    ({"name": "rotate", "angle": 3}, "unknown parameter"),
    ({"name": "shift", "sigma_px": "big"}, "not a number"),
    ({"name": "shift", "sigma_px": -1.0}, "must be >= 0"),
    ({"name": "mirror", "p_ud": 1.5}, "probability"),
    ({"name": "alignment", "image": "c"}, "use one of"),
    ({"name": "noise", "independent": 1}, "true or false"),
    ({"name": "local_warp", "max_px": 50.0, "filter_sigma_px": 10.0}, "fold"),
    ({"name": "rotate", "probability": 2.0}, "probability"),
])
def test_bad_config_names_the_entry_and_the_fix(entry: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match) as exc:
        Pipeline.from_dict({"functions": [{"name": "mirror"}, entry]}, source="aug.toml")
    assert "aug.toml: functions[1]" in str(exc.value)
