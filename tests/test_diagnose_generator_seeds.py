"""The independent benchmark's seeds → cases mapping does not move: cases drawn now
equal the stored development rows of benchmarks/results/diagnose_independent.json."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402


@pytest.mark.parametrize("index", [2, 16, 24, 54])
def test_development_cases_are_the_stored_ones(realdata, samples_dir, index):
    stored = json.loads((ROOT / "benchmarks" / "results" / "diagnose_independent.json")
                        .read_text())
    row = next(r for r in stored["cases"]
               if r["split"] == "development" and r["case"] == f"c{index:02d}")
    case = gen.make_case(index, gen.pick_sources(gen.list_sources(realdata, samples_dir)))
    assert case.q == pytest.approx(row["q_true"], rel=1e-12)
    assert case.source == row["source"]
    assert set(case.truth) == set(row["truth"])
    for name, params in row["truth"].items():
        for k, v in params.items():
            assert case.truth[name][k] == pytest.approx(v, rel=1e-9), (name, k)


def test_forced_effects_draw_the_named_effects_only(realdata, samples_dir):
    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(3, sources, base_seed=6000, force=("motion_smear",))
    assert set(case.truth) == {"motion_smear"}
    lo, hi = gen.RANGES["motion_smear"]["length_px"]
    assert lo <= case.truth["motion_smear"]["length_px"] <= hi


def _results(path: Path, rows: list[dict], sat_px: int = 128) -> Path:
    path.write_text(json.dumps({"cases": rows, "setup": {"sat_px": sat_px}}))
    return path


def _row(case: str, seed: int, **kw) -> dict:
    return {"case": case, "seed": seed, "split": "validation", "source": "s", "q_true": 2.0,
            "q_base": 2.0, "q_refined": 3.0, "truth": {}, "claimed": {},
            "se_base": 0.1, "se_refined": 0.05, "seconds_total": 1.5, **kw}


def test_merge_takes_rows_by_case_recomputes_splits_and_states_limits(tmp_path):
    """``diagnose_independent.py --merge``: later files win; each row's split comes from
    its seed (a past validation half joins development); rows without the diagnosis's
    detection limits get the ones it states at their delivered Q; a file of other-sized
    scenes is refused and nothing is written."""
    import diagnose_independent as bench

    from geosim.diagnose.detection_limits import detection_limits_json

    lim = {"detector_integration": {"param": "pitch_px", "limit": 9.0,
                                    "absorbed_side": "below", "q": 3.0}}
    # a seed of the current validation half (rows keep their seed when a new half is drawn)
    v_seed = gen.VALIDATION_FIRST_SEED + 6
    vc = f"c{v_seed - 1000}"
    a = _results(tmp_path / "a.json", [_row("c00", 1000), _row(vc, v_seed)])
    b = _results(tmp_path / "b.json", [_row("c00", 1000, claimed={"haze": {}},
                                            detection_limits=lim)])
    out = tmp_path / "merged.json"
    bench.merge([a, b], str(out))
    doc = json.loads(out.read_text())
    rows = {r["case"]: r for r in doc["cases"]}
    assert [r["case"] for r in doc["cases"]] == ["c00", vc]
    assert rows["c00"]["claimed"] == {"haze": {}} and rows["c00"]["detection_limits"] == lim
    assert rows["c00"]["split"] == "development" and rows[vc]["split"] == "validation"
    assert rows[vc]["detection_limits"] == detection_limits_json(3.0)
    assert rows[vc]["detection_limits_restated"] is True
    assert doc["halves"]["development"]["n_cases"] == 1
    assert doc["seconds_total"] == pytest.approx(3.0, abs=0.5)
    big = _results(tmp_path / "big.json", [_row("c01", 1001)], sat_px=384)
    with pytest.raises(SystemExit, match="384 px"):
        bench.merge([a, big], str(tmp_path / "refused.json"))
    assert not (tmp_path / "refused.json").exists()
    other = _results(tmp_path / "variants.json",
                     [_row("c02", 1002, variant=gen.draw_variant(1002))])
    with pytest.raises(SystemExit, match="implementation variants"):
        bench.merge([a, other], str(tmp_path / "refused.json"))
    assert not (tmp_path / "refused.json").exists()


def test_stated_untestable_reads_the_rows_limits():
    lim = {"detector_integration": {"param": "pitch_px", "limit": 1.5, "absorbed_side": "below"},
           "atmospheric_blur": {"param": "f0_cyc_per_px", "limit": None,
                                "absorbed_side": "above"}}
    row = {"truth": {"detector_integration": {"pitch_px": 1.2}}, "claimed": {},
           "detection_limits": lim, "se_base": 0.1, "se_refined": 0.05}
    assert gen.stated_untestable(row) == {"detector_integration"}
    row["truth"]["detector_integration"]["pitch_px"] = 1.6
    assert gen.stated_untestable(row) == set()
    row["truth"]["atmospheric_blur"] = {"f0_cyc_per_px": 0.3}   # limit None: never testable
    assert gen.stated_untestable(row) == {"atmospheric_blur"}
    s = gen.score([row])
    assert (s["recall_testable"], s["stated_untestable"], s["rows_with_limits"]) == (0.0, 1, 1)
    assert s["recall"] == 0.0 and s["stated_untestable_found"] == 0
    # the 1.6 px detector lies beyond its limit: stated testable, and missed
    assert (s["stated_testable"], s["stated_testable_found"]) == (1, 0)
    row["claimed"] = {"atmospheric_blur": {}}   # claimed: the report states no limit for it
    assert gen.stated_untestable(row) == set()
    s = gen.score([row])
    assert (s["stated_testable"], s["stated_testable_found"]) == (2, 1)
    assert s["stated_testable_by_effect"] == {"atmospheric_blur": [1, 1],
                                              "detector_integration": [1, 0]}
    # an effect without a limit (no entry) is not counted
    row["truth"]["haze"] = {}
    assert gen.score([row])["stated_testable"] == 2
    # resampling's limit (a native pitch, measured on the spectrum) reads the same way
    row["detection_limits"]["resampling"] = {"param": "native_pitch_px", "limit": 1.4,
                                             "absorbed_side": "below"}
    row["truth"]["resampling"] = {"native_pitch_px": 1.3}
    assert gen.stated_untestable(row) == {"resampling"}
    row["truth"]["resampling"]["native_pitch_px"] = 1.5
    assert gen.score([row])["stated_testable_by_effect"]["resampling"] == [1, 0]
    # a blur whose family was claimed by another name is not excused by its limit (the
    # data showed the family: a swap, not an untestable effect)
    row["truth"]["detector_integration"]["pitch_px"] = 1.2
    assert "detector_integration" not in gen.stated_untestable(row)
    swap = {"truth": {"motion_smear": {"length_px": 1.4}},
            "claimed": {"off_nadir_anisotropy": {}},
            "detection_limits": {"motion_smear": {"param": "length_px", "limit": 2.0,
                                                  "absorbed_side": "below"}},
            "se_base": 0.1, "se_refined": 0.05}
    assert gen.stated_untestable(swap) == set()
    swap["claimed"] = {}
    assert gen.stated_untestable(swap) == {"motion_smear"}


# ------------------------------------------------------------------ implementation variants
def test_variants_keep_each_cases_effects_and_default_render():
    """``--variants`` renders the same case (seed, Q, effects, parameters, UAV image) with
    other implementation choices; the default choices are the halves' own render."""
    truth = {"atmospheric_blur": {"f0_cyc_per_px": 0.3},
             "resampling": {"native_pitch_px": 1.5}, "compression": {"quality": 40}}
    for seed in (1003, 1210):
        plain = gen.make_case(seed - 1000, [])
        varied = gen.make_case(seed - 1000, [], variants=True)
        assert varied.variant == gen.draw_variant(seed) and plain.variant is None
        assert (varied.q, varied.truth) == (plain.q, plain.truth)
        np.testing.assert_array_equal(varied.uav, plain.uav)
    ground = gen.synthetic_ground(np.random.default_rng(5), 40 * gen.PHI)
    a = gen.render(ground, 2.0, truth, np.random.default_rng(1), margin_px=6)
    b = gen.render(ground, 2.0, truth, np.random.default_rng(1), margin_px=6,
                   variant=dict(gen.DEFAULT_VARIANT))
    np.testing.assert_array_equal(a[1], b[1])
    other = {"atmosphere_exponent": 1.0, "interpolation": "pillow_keys",
             "jpeg": "pillow_444", "shift": "fourier"}
    c = gen.render(ground, 2.0, truth, np.random.default_rng(1), margin_px=6, variant=other)
    assert np.abs(c[1] - a[1]).mean() > 0.5


def test_variant_draws_cover_every_choice():
    draws = [gen.draw_variant(1000 + i) for i in range(64)]
    lo, hi = gen.VARIANT_CHOICES["atmosphere_exponent"]
    assert all(lo <= d["atmosphere_exponent"] <= hi for d in draws)
    for key in ("interpolation", "jpeg", "shift"):
        assert {d[key] for d in draws} == set(gen.VARIANT_CHOICES[key])


def test_atmosphere_exponent_is_the_mtf_shape():
    """exp(-(f/f0)^n): 1/e at f0 whatever n; exp(-2^n) at 2 f0."""
    n_fine, f0 = 200, 0.25
    for exponent in (1.0, 5.0 / 3.0, 2.0):
        mtf = gen.atmosphere_mtf(n_fine, f0, exponent=exponent)
        # fine-grid frequency index k is k/n_fine cycles per fine px = k*PHI/n_fine per px
        k0 = int(round(f0 * n_fine / gen.PHI))
        assert mtf[0, k0] == pytest.approx(np.exp(-1.0), rel=1e-9)
        assert mtf[0, 2 * k0] == pytest.approx(np.exp(-2.0 ** exponent), rel=1e-9)


def test_pillow_keys_interpolation_reproduces_quadratics():
    """Keys' cubic convolution (a = -0.5, Pillow's bicubic) reproduces quadratics exactly
    away from the edges; OpenCV's a = -0.75 does not: the two variants are different
    kernels, as stated."""
    import cv2
    from PIL import Image

    n_nat, n = 40, 64
    # native pixel centres in output pixel units: (j + 0.5) * n / n_nat
    x_nat = (np.arange(n_nat) + 0.5) * n / n_nat
    x_out = np.arange(n) + 0.5
    row_nat = (0.01 * x_nat ** 2).astype(np.float32)
    nat = np.repeat(row_nat[np.newaxis], 8, axis=0)
    keys = np.asarray(Image.fromarray(nat, "F").resize((n, 8), Image.BICUBIC))[4]
    ocv = cv2.resize(nat, (n, 8), interpolation=cv2.INTER_CUBIC)[4]
    inner = slice(6, n - 6)
    truth = 0.01 * x_out ** 2
    assert np.max(np.abs(keys[inner] - truth[inner])) < 1e-3
    assert np.max(np.abs(ocv[inner] - truth[inner])) > 5e-3


def test_fourier_shift_moves_a_sinusoid_exactly():
    n = 64
    x = np.arange(n)
    img = np.sin(2 * np.pi * 3 * x / n)[np.newaxis, np.newaxis, :].repeat(n, axis=1)
    out = gen.fourier_shift_fine(img, 0.0, 1.3)
    np.testing.assert_allclose(out[0, 5], np.sin(2 * np.pi * 3 * (x - 1.3) / n), atol=1e-9)


def test_jpeg_variants_keep_channel_order_and_differ_in_chroma():
    rng = np.random.default_rng(0)
    img = np.stack([np.full((64, 64), 200.0), np.full((64, 64), 60.0),
                    np.full((64, 64), 30.0)]) + rng.normal(0, 8, (3, 64, 64))
    img[:, :, 32:] = img[::-1, :, 32:]    # a colour edge, so chroma subsampling matters
    outs = {"420": gen.jpeg_pillow(img, 60), "444": gen.jpeg_pillow(img, 60, subsampling=0),
            "422": gen.jpeg_opencv_422(img, 60)}
    for out in outs.values():
        np.testing.assert_allclose(out[:, :, :24].mean(axis=(1, 2)),
                                   img[:, :, :24].mean(axis=(1, 2)), atol=3.0)
    assert np.abs(outs["420"] - outs["444"]).mean() > 0.1
    assert np.abs(outs["422"] - outs["444"]).mean() > 0.1
    assert np.abs(outs["422"] - outs["420"]).mean() > 0.05


@pytest.mark.parametrize("pitch_px", [0.9, 1.0, 1.04, 1.29, 1.436, 1.51, 1.6])
def test_detector_box_is_centred_and_as_wide_as_stated(pitch_px):
    """The detector box moves nothing (a point's centroid stays, for odd and even
    floor(10 pitch): an even-length kernel once moved the image by half a fine pixel) and
    its transfer is sinc(pitch f) (checked against the analytic formula, not the code)."""
    n = 401
    img = np.zeros((1, n, n))
    img[0, n // 2, n // 2] = 1.0
    out = gen.detector_box(img, pitch_px)[0]
    idx = np.arange(n) - n // 2
    assert abs(float((out.sum(axis=0) * idx).sum())) < 1e-6
    assert abs(float((out.sum(axis=1) * idx).sum())) < 1e-6
    assert out.sum() == pytest.approx(1.0, abs=1e-6)
    f = np.fft.fftfreq(n)                                   # cycles per fine pixel
    mtf = np.abs(np.fft.fft(np.fft.ifftshift(out.sum(axis=0))))
    band = np.abs(f) * gen.PHI <= 0.5                       # the product band
    # a fine-grid box (edges split over one fine pixel) is sinc(w f) to < 1 % in the band
    np.testing.assert_allclose(mtf[band], np.abs(np.sinc(pitch_px * gen.PHI * f[band])),
                               atol=0.01)


def test_noise_free_render_is_the_delivered_scene_before_noise():
    """``render(..., noise_free=True)`` is the product the noise, whole DN and JPEG act
    on: without those effects the delivered scene is it rounded; with them it differs by
    about the noise's variance; the moved objects are drawn alike."""
    ground = gen.synthetic_ground(np.random.default_rng(3), 40 * gen.PHI)
    truth = {"detector_integration": {"pitch_px": 1.3}, "scene_change": {"n_objects": 6}}
    uav_a, clean = gen.render(ground, 1.6, truth, np.random.default_rng(2), margin_px=6,
                              noise_free=True)
    uav_b, real = gen.render(ground, 1.6, truth, np.random.default_rng(2), margin_px=6)
    np.testing.assert_array_equal(uav_a, uav_b)
    np.testing.assert_array_equal(real, np.clip(np.rint(clean), 0, 255))
    noisy = {**truth, "sensor_noise": {"gain_dn": 0.2, "read_var_dn2": 4.0}}
    _, clean_n = gen.render(ground, 1.6, noisy, np.random.default_rng(2), margin_px=6,
                            noise_free=True)
    _, real_n = gen.render(ground, 1.6, noisy, np.random.default_rng(2), margin_px=6)
    np.testing.assert_array_equal(clean_n, clean)
    expected = 4.0 + 0.2 * float(np.clip(clean, 0, None).mean()) + 1.0 / 12.0
    assert np.var(real_n - clean_n) == pytest.approx(expected, rel=0.1)


# ------------------------------------------------------------------ the real-flight form
def test_flight_form_keeps_each_cases_effects_and_scene():
    """``--flight`` renders the same case (seed, Q, effects, parameters) as a surveyed
    flight: the UAV image is the whole-window one inside its footprint and 0 outside; the
    satellite scene is the same where no misregistration moves it; a misregistration's
    truth gains the drawn rotation and scale."""
    for i in range(12):
        plain = gen.make_case(i, [])
        flown = gen.make_case(i, [], flight=True)
        assert flown.flight == gen.draw_flight(1000 + i) and plain.flight is None
        assert flown.q == plain.q and set(flown.truth) == set(plain.truth)
        mask = flown.uav_valid
        assert mask is not None and 0.6 < mask.mean() <= 1.0
        np.testing.assert_array_equal(flown.uav[:, mask], plain.uav[:, mask])
        assert not flown.uav[:, ~mask].any()
        if "misregistration" in plain.truth:
            mis = flown.truth["misregistration"]
            assert mis["shift_px"] == plain.truth["misregistration"]["shift_px"]
            assert (mis["rotation_deg"], mis["scale"]) == (flown.flight["rotation_deg"],
                                                           flown.flight["scale"])
        else:
            np.testing.assert_array_equal(flown.real, plain.real)


def test_flight_draws_stay_in_their_ranges():
    draws = [gen.draw_flight(1000 + i) for i in range(64)]
    r = gen.FLIGHT_RANGES
    assert all(r["footprint_deg"][0] <= d["footprint_deg"] <= r["footprint_deg"][1]
               for d in draws)
    rot = np.array([d["rotation_deg"] for d in draws])
    assert np.all((np.abs(rot) >= r["rotation_deg"][0]) & (np.abs(rot) <= r["rotation_deg"][1]))
    assert (rot > 0).any() and (rot < 0).any()
    assert all(abs(d["scale"] - 1.0) <= r["scale_dev"][1] for d in draws)


def test_footprint_mask_is_the_turned_square_in_its_bounding_box():
    """Unturned: the whole window. Turned by a: a square of side n / (cos a + sin |a|)
    (area to 1 %), touching all four sides of the window (its bounding box), with the
    window's corners nodata and its centre imaged; either sign the mirror image."""
    n = 400
    assert gen.footprint_mask(n, {"footprint_deg": 0.0}).all()
    for deg in (10.0, -14.0):
        m = gen.footprint_mask(n, {"footprint_deg": deg})
        a = np.radians(deg)
        assert m.sum() == pytest.approx((n / (np.cos(a) + abs(np.sin(a)))) ** 2, rel=0.01)
        assert m[0].any() and m[-1].any() and m[:, 0].any() and m[:, -1].any()
        assert not (m[0, 0] or m[0, -1] or m[-1, 0] or m[-1, -1]) and m[n // 2, n // 2]
    # mirrored (to the pixel rounding): fillPoly's pixel centres are on whole coordinates
    mirror = gen.footprint_mask(n, {"footprint_deg": -10.0})[:, ::-1]
    assert np.mean(gen.footprint_mask(n, {"footprint_deg": 10.0}) != mirror) < 0.005


def test_warp_fine_turns_clockwise_scales_and_shifts_in_product_pixels():
    """A bright spot east of the centre moves to the analytic place: turned clockwise on
    the image (rows down), scaled about the centre, then shifted by (col, row) product
    pixels (x PHI fine pixels)."""
    n = 301
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    c = (n - 1) / 2.0
    spot = np.exp(-((xx - (c + 100.0)) ** 2 + (yy - c) ** 2) / (2 * 3.0 ** 2))[np.newaxis]
    rot_deg, scale, shift = 20.0, 1.05, (0.4, -0.7)
    out = gen.warp_fine(spot, shift, rot_deg, scale)[0]
    a = np.radians(rot_deg)
    want_x = c + scale * 100.0 * np.cos(a) + shift[0] * gen.PHI
    want_y = c + scale * 100.0 * np.sin(a) + shift[1] * gen.PHI
    w = np.clip(out, 0, None)
    assert (w * xx).sum() / w.sum() == pytest.approx(want_x, abs=0.05)
    assert (w * yy).sum() / w.sum() == pytest.approx(want_y, abs=0.05)


def test_spectral_error_over_the_imaged_blocks():
    """All valid: the same number as without a mask; with an invalid band the blocks that
    touch it are left out (a scene that differs only there scores as equal)."""
    rng = np.random.default_rng(3)
    a = rng.normal(100, 10, (3, 128, 128))
    b = a + rng.normal(0, 2, a.shape)
    assert gen.spectral_error(a, b, valid=np.ones((128, 128), bool)) == \
        gen.spectral_error(a, b)
    c = a.copy()
    c[:, :, :20] = 0.0
    valid = np.ones((128, 128), bool)
    valid[:, :20] = False
    assert gen.spectral_error(c, a, valid=valid) == 0.0
    assert gen.spectral_error(c, a) > 0.1
