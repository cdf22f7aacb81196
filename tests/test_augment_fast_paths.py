"""The augmentation's skipped passes give the values of the passes they skip, bit for bit.

Truth: every photometric kernel run in full on float32 blocks (convert, op after op, each
clipping, round once, zero the invalid pixels), as the stage did before it skipped
anything; OpenCV's own nearest-neighbour remap of the mask; and a process's page-fault
count for the allocator setting.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

from geosim.augment import photometric as ph
from geosim.augment.functions import Colour, Hue, Noise, Saturation, Value
from geosim.augment.pipeline import BLOCK_ROWS, _merge_hsv, _photometric_stage
from geosim.augment.resample import _nearest_inside_bounds, remap_resample_hwc

DTYPES = {np.uint8: 255.0, np.uint16: 65535.0, np.int16: 32767.0, np.float32: 255.0}


def _reference_stage(hwc, mask, ops, dn_max):
    """Every kernel in full, block by block (the stage without any skipped pass)."""
    ops = _merge_hsv(ops)
    rngs = [np.random.default_rng(op.seed) if op.seed is not None else None for op in ops]
    out = np.empty(hwc.shape, hwc.dtype)
    for r0 in range(0, hwc.shape[0], BLOCK_ROWS):
        block = slice(r0, min(hwc.shape[0], r0 + BLOCK_ROWS))
        work = ph.to_work(hwc[block])
        for op, rng in zip(ops, rngs, strict=True):
            work = op.func(work, dn_max, rng)
        ph.from_work(work, hwc.dtype, out=out[block])
    out[~mask] = 0
    return out


def _ops(names, seed):
    """PixelOps of the named functions with drawn parameters (large sigmas: clipping)."""
    rng = np.random.default_rng(seed)
    make = {"colour": Colour(sigma_dn=40.0), "hue": Hue(sigma_deg=40.0),
            "saturation": Saturation(sigma_dn=60.0), "value": Value(sigma_dn=60.0),
            "noise": Noise(sigma_dn=5.0), "big_noise": Noise(sigma_dn=40.0)}
    ops = []
    for n in names:
        op_a, _ = make[n].ops(make[n].draw(rng), (1, 1))
        ops.append(op_a)
    return ops


def _image(dtype, bands, rows=300, cols=37, seed=0):
    rng = np.random.default_rng(seed)
    dn_max = DTYPES[dtype]
    low = -0.02 * dn_max if dtype in (np.int16, np.float32) else 0  # a few out of range
    img = rng.uniform(low, dn_max * 1.01 if dtype == np.float32 else dn_max,
                      (rows, cols, bands))
    img[:3] = dn_max if dtype != np.int16 else dn_max  # saturated rows
    img[3:6] = 0
    img = img.astype(dtype) if dtype == np.float32 else np.rint(img).astype(dtype)
    mask = rng.random((rows, cols)) > 0.1
    mask[:, :4] = False
    img[~mask] = rng.integers(1, 200, int((~mask).sum()))[:, None]  # under the mask: not 0
    return img, mask


COMBOS = [("colour",), ("hue",), ("noise",), ("big_noise",), ("colour", "noise"),
          ("colour", "hue", "saturation", "value", "noise"), ("saturation", "value"),
          ("hue", "noise"), ("colour", "value"), ("value", "colour", "big_noise"),
          ("noise", "colour")]


@pytest.mark.parametrize(("dtype", "bands"), [(np.uint8, 3), (np.uint8, 4), (np.uint8, 1),
                                              (np.uint8, 5), (np.uint16, 3), (np.int16, 3),
                                              (np.float32, 3)])
def test_photometric_stage_equals_every_kernel_in_full(dtype, bands) -> None:
    dn_max = DTYPES[dtype]
    for i, names in enumerate(COMBOS):
        if bands < 3 and any(n in ("hue", "saturation") for n in names):
            continue
        img, mask = _image(dtype, bands, seed=i)
        for seed in range(3):
            ops = [op for op in _ops(names, seed) if op is not None]
            if not ops:
                continue
            got = _photometric_stage(img, mask, ops, dn_max)
            want = _reference_stage(img, mask, ops, dn_max)
            assert got.dtype == img.dtype
            assert np.array_equal(got, want), (dtype, bands, names, seed)
            assert not got[~mask].any()


def test_reference_is_not_trivially_equal() -> None:
    """The comparison can fail: rounding twice (a uint8 table before HSV) is caught."""
    img, mask = _image(np.uint8, 3, seed=1)
    colour, hue = _ops(("colour", "hue"), 4)
    want = _reference_stage(img, mask, [colour, hue], 255.0)
    twice = _photometric_stage(_photometric_stage(img, mask, [colour], 255.0), mask, [hue],
                               255.0)
    assert not np.array_equal(twice, want)


def test_colour_lut_is_the_kernel() -> None:
    shifts = np.array([-30.4, 0.5, 201.7])
    lut = ph.colour_lut(shifts, 3)
    ramp = np.repeat(np.arange(256, dtype=np.float32)[:, None], 3, axis=1)[None]
    assert lut.dtype == np.float32 and lut.shape == (1, 256, 3)
    assert np.array_equal(lut, ph.colour_shift(ramp, shifts))
    assert lut[0, 0, 0] == 0 and lut[0, 255, 2] == 255 and lut[0, 10, 1] == np.float32(10.5)


def test_noise_into_output_equals_add_clip_round() -> None:
    work = np.random.default_rng(2).uniform(-3, 258, (64, 50, 3)).astype(np.float32)
    for dtype, dn_max in ((np.uint8, 255.0), (np.uint16, 65535.0)):
        w = work * np.float32(dn_max / 255.0)
        for sigma in (2.0, 40.0):
            want = ph.from_work(ph.add_noise(w, sigma_dn=sigma, rng=np.random.default_rng(7),
                                             dn_max=dn_max), dtype)
            out = np.full(w.shape, 9, dtype)
            got = ph.add_noise(w, sigma_dn=sigma, rng=np.random.default_rng(7), dn_max=dn_max,
                               out=out)
            assert got is out and np.array_equal(out, want)
    with pytest.raises(ValueError, match="uint8 or uint16"):
        ph.add_noise(work, sigma_dn=2.0, rng=np.random.default_rng(0),
                     out=np.zeros(work.shape, np.int16))


@pytest.mark.parametrize(("s", "v"), [(30.0, 0.0), (-30.0, 0.0), (0.0, 40.0), (0.0, -40.0),
                                      (30.0, -40.0), (-30.0, 40.0), (0.0, 0.0)])
def test_hsv_one_sided_clip_equals_both_sides(s, v) -> None:
    rgb = np.random.default_rng(3).uniform(0, 255, (40, 40, 3)).astype(np.float32)
    rgb[0, :3] = [[0, 0, 0], [255, 255, 255], [255, 0, 0]]
    got = ph.hsv_shift(rgb, hue_deg=17.0, saturation_dn=s, value_dn=v)
    # both clips, explicitly
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    cv2.add(hsv, (17.0, s / 255.0, v, 0.0), dst=hsv)
    cv2.min(hsv, (720.0, 1.0, 255.0, 0.0), dst=hsv)
    cv2.max(hsv, (0.0, 0.0, 0.0, 0.0), dst=hsv)
    want = np.clip(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB), 0, 255)
    assert np.array_equal(got, want)


@pytest.mark.parametrize(("rows", "cols"), [(7, 10), (10, 7), (9, 9), (8, 12)])
def test_all_valid_mask_range_test_equals_nearest_remap(rows, cols) -> None:
    """OpenCV's rounding at the edges, ties included, is what the range test reproduces."""
    rng = np.random.default_rng(rows * cols)
    edges = np.array([-1.5, -0.5000001, -0.5, -0.4999999, 0.0, 0.5, 1.5, 2.5], np.float32)
    xs = np.concatenate([edges, cols - 1 + edges + 1, rng.uniform(-3, cols + 2, 400)])
    ys = np.concatenate([edges, rows - 1 + edges + 1, rng.uniform(-3, rows + 2, 400)])
    xy = np.stack(np.meshgrid(xs.astype(np.float32), ys.astype(np.float32)), axis=-1)
    ones = np.ones((rows, cols), np.uint8)
    want = cv2.remap(ones, xy, None, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=0)
    got = (cv2.inRange(xy, *_nearest_inside_bounds(rows, cols)) > 0).astype(np.uint8)
    assert 0 < want.sum() < want.size
    assert np.array_equal(got, want)


def test_remap_of_an_all_valid_mask_matches_a_mask_that_is_not() -> None:
    """The fast path (all valid) and the remap (one invalid pixel far from the footprint)."""
    rng = np.random.default_rng(5)
    rows, cols = 64, 80
    img = rng.integers(0, 255, (rows, cols, 3), dtype=np.uint8)
    u = rng.uniform(-6, 6, (rows, cols)).astype(np.float32)
    v = rng.uniform(-6, 6, (rows, cols)).astype(np.float32)
    u[10, 10], v[10, 10] = 0.5, 0.0  # ties
    full = np.ones((rows, cols), bool)
    almost = full.copy()
    almost[32, 40] = False
    m_full = remap_resample_hwc(img, full, u, v)[1]
    m_almost = remap_resample_hwc(img, almost, u, v)[1]
    sampled = (np.rint(np.arange(cols) + u) == 40) & (np.rint(
        np.arange(rows)[:, None] + v) == 32)
    assert not m_full.all() and m_full.any()
    assert np.array_equal(m_full & ~sampled, m_almost)


_FAULTS = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from geosim.heap import keep_large_arrays
    if sys.argv[1] == "keep":
        assert keep_large_arrays() and keep_large_arrays()
    def faults():
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    np.ones(64 * 2**20, np.uint8)  # 64 MB, freed
    f0 = faults()
    for _ in range(4):
        a = np.ones(64 * 2**20, np.uint8)  # touched whole
        del a
    print((faults() - f0) / 4)
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc mallopt only")
def test_keep_large_arrays_reuses_large_arrays_without_page_faults() -> None:
    def per_alloc(mode: str) -> float:
        done = subprocess.run([sys.executable, "-c", _FAULTS, mode], check=True,
                              capture_output=True, text=True)
        return float(done.stdout.strip())

    pages = 64 * 2**20 / 4096
    fresh, kept = per_alloc("fresh"), per_alloc("keep")
    assert fresh > 0.2 * pages / 512  # fresh mappings fault (at least per 2 MB huge page)
    assert kept < 0.05 * fresh, (fresh, kept)


def test_combos_cover_every_fast_path() -> None:
    """Leading colour (alone and not), HSV first and last, noise last and not last."""
    firsts = {c[0] for c in COMBOS}
    lasts = {c[-1] for c in COMBOS}
    assert {"colour", "hue", "noise"} <= firsts and {"noise", "hue", "value"} <= lasts
    assert any(len(c) > 1 and "noise" in c[:-1] for c in COMBOS)


@pytest.mark.parametrize("independent", [False, True])
def test_pair_noise_is_drawn_once_when_shared_and_equals_each_image_alone(
        monkeypatch: pytest.MonkeyPatch, independent: bool) -> None:
    """Truth: each image's photometric stage run on its own (no cache), OpenCV draws counted."""
    from geosim.augment import AugImage
    from geosim.augment.pipeline import AugmentStep, Pipeline

    rng = np.random.default_rng(7)
    rows, cols = 3 * BLOCK_ROWS + 17, 90
    a = rng.integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    b = rng.integers(0, 256, (rows, cols, 3), dtype=np.uint8)
    mask = np.ones((rows, cols), bool)
    steps = (AugmentStep(Hue(sigma_deg=5.0), 1.0),
             AugmentStep(Noise(sigma_dn=4.0, independent=independent), 1.0))
    pipe = Pipeline(steps, reference_gsd_m=None)
    records = pipe.draw(np.random.default_rng(3))
    draws: list[int] = []
    real = ph._draw_noise
    monkeypatch.setattr(ph, "_draw_noise", lambda *args: draws.append(1) or real(*args))
    res = pipe.replay(AugImage(np.moveaxis(a, -1, 0), mask), AugImage(np.moveaxis(b, -1, 0),
                                                                        mask), records)
    blocks = -(-rows // BLOCK_ROWS)
    assert len(draws) == (2 * blocks if independent else blocks)
    for img, src, side in ((res.a, a, 0), (res.b, b, 1)):
        ops = []
        for step, rec in zip(steps, records, strict=True):
            op = step.function.ops(rec["params"], (rows, cols))[side]
            if op is not None:
                ops.append(op)
        alone = _photometric_stage(src, mask, ops, 255.0)
        assert np.array_equal(np.moveaxis(img.image, 0, -1), alone)


def test_noise_cache_gives_the_block_only_for_the_same_draw() -> None:
    cache = ph.NoiseBlockCache()
    work = np.full((8, 10, 3), 100.0, np.float32)
    first = ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(1), cache=cache)
    again = ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(1), cache=cache)
    other = ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(2), cache=cache)
    bigger = ph.add_noise(work, sigma_dn=4.0, rng=np.random.default_rng(2), cache=cache)
    assert cache.hits == 1
    assert np.array_equal(first, again) and not np.array_equal(first, other)
    assert np.array_equal(first, ph.add_noise(work, sigma_dn=3.0, rng=np.random.default_rng(1)))
    assert not np.array_equal(other, bigger)
