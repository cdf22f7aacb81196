"""End-to-end diagnosis on satellite scenes made without any geosim code.

The scenes come from ``benchmarks/diagnose_generator.py``, an independent implementation of
the physics (numpy / scipy / OpenCV / Pillow, blur applied on the 0.05 m grid before
sampling); the test checks that it imports nothing from geosim, then runs the diagnosis
blind and scores it with the generator's own spectral error.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.combine import combine_flights  # noqa: E402
from geosim.diagnose.engine import diagnose_arrays  # noqa: E402
from geosim.diagnose.grids import calibrate_q_lv  # noqa: E402
from geosim.diagnose.report_markdown import diagnosis_markdown  # noqa: E402
from geosim.diagnose.resampling_limit import PITCHES  # noqa: E402
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.physics.radiometry import luma  # noqa: E402
from tests.generator_cases import diagnose_scene as _run  # noqa: E402


def test_generator_is_independent_of_geosim():
    tree = ast.parse((ROOT / "benchmarks" / "diagnose_generator.py").read_text())
    mods = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            mods |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            mods.add(node.module or "")
    assert mods, "no imports found"
    assert not [m for m in mods if m.split(".")[0] == "geosim"], mods


def test_control_from_independent_generator_claims_nothing():
    claimed, se_base, se_ref, _ = _run({}, q=1.6, seed=11)
    assert claimed == {}
    assert se_ref <= se_base + 1e-9


def test_presampling_motion_smear_found_and_fit_improves():
    truth = {"motion_smear": {"length_px": 2.5, "direction_deg": 60.0}}
    claimed, se_base, se_ref, d = _run(truth, q=1.3, seed=12)
    assert set(claimed) == {"motion_smear"}, list(claimed)
    p = claimed["motion_smear"]["params"]
    assert abs((p["direction_deg"] - 60.0 + 90) % 180 - 90) < 10
    assert abs(p["length_px"] - 2.5) < 0.5
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)
    # the uncertainty holds 1-σ values: of the smear's parameters and of Q fitted with it
    # (Q's σ, not Q itself, which an earlier version reported under "q")
    unc = claimed["motion_smear"]["uncertainty"]
    assert 0 < unc["length_px"] < 0.5 and 0 < unc["direction_deg"] < 20, unc
    assert 0 < unc["q"] < 0.2 * d.summary["refined"]["q"], unc
    # the claimed smear lies beyond the limit the scene states for it, and the report
    # lists neither anisotropic blur under "cannot test" (the data showed the family)
    lim = d.summary["detection_limits"]["motion_smear"]
    assert lim["limit"] is not None and lim["limit"] < 2.5, lim
    report = diagnosis_markdown(d.summary)
    assert "motion smear (motion_smear) shorter" not in report
    assert "off-nadir blur (off_nadir_anisotropy) with σ below" not in report


def test_short_smear_under_a_wide_psf_is_stated_untestable_in_any_direction():
    """A 0.9 px smear under Q 4 optics: its anisotropy lies where the optics pass almost
    nothing. It is not claimed, and diagnosis.json and the report say that a smear this
    short is not testable here in any direction (not that there is none)."""
    truth = {"motion_smear": {"length_px": 0.9, "direction_deg": 35.0}}
    claimed, se_base, se_ref, d = _run(truth, q=4.0, seed=21)
    assert not {"motion_smear", "off_nadir_anisotropy"} & set(claimed), list(claimed)
    lim = d.summary["detection_limits"]["motion_smear"]
    assert (lim["param"], lim["absorbed_side"]) == ("length_px", "below")
    assert lim["limit"] is not None and lim["limit"] > 0.9, lim
    assert "off_nadir_anisotropy" in d.summary["detection_limits"]
    assert se_ref <= se_base + 1e-9
    assert (f"shorter than {lim['limit']:.2f} px, in any direction, is not testable"
            in diagnosis_markdown(d.summary))


def test_noise_and_haze_from_independent_generator():
    truth = {"sensor_noise": {"gain_dn": 0.2, "read_var_dn2": 6.0},
             "haze": {"transmission": [0.92, 0.88, 0.8], "path_radiance_dn": [5.0, 9.0, 15.0]}}
    claimed, se_base, se_ref, d = _run(truth, q=1.8, seed=13)
    assert set(claimed) == {"sensor_noise", "haze"}, list(claimed)
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)
    # white variance near the truth at the mean brightness (a·s + b)
    s_mean = float(d.real.mean())
    true_var = 0.2 * s_mean + 6.0
    got = d.summary["noise"]["white_variance_dn2"]
    assert 0.6 * true_var < got < 1.5 * true_var, (got, true_var)


def test_detector_under_a_wide_psf_is_stated_untestable_not_absent():
    """A 1.2 px detector box under Q 4 optics changes the in-band transfer as a ~3 % larger
    Q would (< 1 % apart): the diagnosis cannot claim it, and diagnosis.json says so (its
    detection limit at the delivered Q lies above 1.2 px), as does the report."""
    truth = {"detector_integration": {"pitch_px": 1.2}}
    claimed, se_base, se_ref, d = _run(truth, q=4.0, seed=17)
    assert "detector_integration" not in claimed, list(claimed)
    lim = d.summary["detection_limits"]["detector_integration"]
    assert lim["q"] == d.summary["refined"]["q"] and lim["absorbed_side"] == "below"
    assert lim["limit"] > 1.2, lim
    assert se_ref <= se_base + 1e-9
    assert f"narrower than {lim['limit']:.2f} px" in diagnosis_markdown(d.summary)
    # resampling's limit, measured on the scene's spectrum at the same Q
    res = d.summary["detection_limits"]["resampling"]
    assert (res["param"], res["basis"], res["q"]) == ("native_pitch_px", "measured_spectrum",
                                                      lim["q"])
    assert [p for p, _ in res["predicted_spectral_gain"]] == list(PITCHES)
    assert res["limit"] is None or PITCHES[0] <= res["limit"] <= PITCHES[-1]


def test_benchmark_scoring_counts_exact_names():
    rows = [{"truth": {"haze": {}}, "claimed": {"haze": {}, "sensor_noise": {}},
             "se_base": 0.4, "se_refined": 0.1},
            {"truth": {}, "claimed": {}, "se_base": 0.05, "se_refined": 0.06}]
    s = gen.score(rows)
    assert (s["tp"], s["fp"], s["fn"]) == (1, 1, 0)
    assert s["precision"] == pytest.approx(0.5) and s["recall"] == 1.0
    assert s["controls_clean"] == 1 and s["refined_le_half_baseline"] == 1
    assert s["refined_above_baseline"] == 1


@pytest.mark.parametrize("index", [10, 19])
def test_fixed_benchmark_subset_on_real_imagery(realdata, samples_dir, index):
    """Two fixed cases of benchmarks/diagnose_independent.py (a control on an SJER 2018
    tile at Q 1.15; haze on the Australian woodland at Q 2.27): exact names, and the refined
    spectral error (the benchmark's own measure) at most half the baseline's with effects,
    never above it."""
    import diagnose_independent as bench

    # the benchmark's own source list (its cases are numbered over it)
    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(index, sources)
    row = bench.diagnose_case(case)
    assert set(row["claimed"]) == set(case.truth), (case.truth, row["claimed"])
    assert row["se_refined"] <= row["se_base"] + 1e-9
    if case.truth:
        assert row["se_refined"] <= 0.5 * row["se_base"]


def test_presampling_resampling_with_atmosphere_both_named():
    """Resampling (native render, cubic back) with an atmospheric roll-off: a wide detector
    sinc imitates both, but a detector wider than two product pixels is implausible, and
    resampling's aliased power (which the transfer fit cannot see) decides it."""
    truth = {"resampling": {"native_pitch_px": 1.5},
             "atmospheric_blur": {"f0_cyc_per_px": 0.4}}
    claimed, se_base, se_ref, d = _run(truth, q=2.0, seed=14)
    assert "resampling" in claimed, list(claimed)
    assert "detector_integration" not in claimed, list(claimed)
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - 1.5) < 0.3
    # better than the baseline (here 0.29 -> 0.15: just short of the benchmark's ½ target)
    assert se_ref < 0.75 * se_base, (se_base, se_ref)



@pytest.mark.parametrize("interpolation, true_a", [("opencv_cubic", -0.75),
                                                   ("pillow_keys", -0.5)])
def test_resampling_with_either_cubic_kernel_is_named_alone(interpolation, true_a):
    """A product resampled with Keys' a = -0.5 (GDAL's and Pillow's cubic; the generator's
    Pillow variant) is softer than with OpenCV's -0.75. With the kernel fitted, the extra
    roll-off is resampling's own and the kernel is recovered; with OpenCV's kernel alone
    the diagnosis claimed a 1.55 px detector box beside it here (and in 6 of 33 such
    development cases, round 10)."""
    truth = {"resampling": {"native_pitch_px": 1.5}}
    claimed, se_base, se_ref, _ = _run(truth, q=2.5, seed=24,
                                       variant={"interpolation": interpolation})
    assert set(claimed) == {"resampling"}, list(claimed)
    params = claimed["resampling"]["params"]
    assert abs(params["cubic_a"] - true_a) < 0.1, params
    assert abs(params["native_pitch_px"] - 1.5) < 0.15, params
    assert se_ref < se_base, (se_base, se_ref)


def test_low_q_resampling_pitch_q_and_phase_from_the_power_spectrum():
    """Round 22. At Q 1.0 the optics pass content far above a 1.45 px native grid's
    Nyquist; the grid's aliasing makes the transfer incoherent (its Q and pitch were far
    off: development c09, c629) and, against a native grid placed elsewhere, the power
    spectrum too (the generator's grid starts at its margin's edge, 12 px: a phase of
    0.4 px here). Pitch, Q and phase refined together on the power spectrum recover the
    grid, and the refined simulation fits."""
    truth = {"resampling": {"native_pitch_px": 1.45}}
    claimed, se_base, se_ref, d = _run(truth, q=1.0, seed=31)
    assert set(claimed) == {"resampling"}, list(claimed)
    # the generator's pitch: whole native pixels over the rendered extent (120 px)
    n = 96 + 24
    pitch = n / round(n / 1.45)
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - pitch) < 0.03
    assert abs(d.summary["refined"]["q"] - 1.0) < 0.05
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_jpeg_alone_is_not_called_an_isotropic_blur():
    """A JPEG'd product (Pillow, after sampling) loses high frequencies, and JPEG lowers the
    Laplacian variance, so the LV baseline's Q (and the top of the Q grid derived from it)
    can lie below the true Q. Before, Q was pinned at that top (2.5) and
    ``atmospheric_blur`` (f0 0.66) stood in for the missing optics and the JPEG's loss. Now
    the Q grid is extended when Q is pinned, and the JPEG quality and the blur are fitted
    to a common fixed point: no isotropic blur, Q and the quality near the truth."""
    truth = {"compression": {"quality": 30}}
    claimed, se_base, se_ref, d = _run(truth, q=2.9, seed=16)
    assert "compression" in claimed, list(claimed)
    assert not {"atmospheric_blur", "detector_integration"} & set(claimed), list(claimed)
    assert abs(d.summary["refined"]["q"] - 2.9) < 0.25, d.summary["refined"]["q"]
    assert abs(claimed["compression"]["params"]["quality"] - 30) <= 6
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_jpeg_at_high_q_is_not_called_resampling():
    """At Q 4 the optics cut the band below the product Nyquist; resampling's pitch scanned
    on the power spectrum then ran to the end of its scan (2.0 px) to absorb the JPEG
    model's high-frequency misfit. A pitch pinned at an end of the scan is not claimed."""
    claimed, se_base, se_ref, d = _run({"compression": {"quality": 50}}, q=4.0, seed=15)
    assert set(claimed) == {"compression"}, list(claimed)
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)
    # the compression entry follows the schema of the others (found by a test, not a fit:
    # no σ, twice the lattice's log-likelihood gain as its evidence, the test itself under
    # "test"), so a combined verdict over flights can take medians of it (it raised
    # TypeError on the dict before)
    c = claimed["compression"]
    assert abs(c["params"]["quality"] - 50) <= 1   # 49 and 50: steps ≤ 1 apart
    assert c["uncertainty"] == {} and isinstance(c["delta_bic"], float)
    assert c["delta_bic"] == pytest.approx(2 * c["test"]["lattice_log_lik_gain"])
    out = combine_flights({"A": d.summary, "B": d.summary}, reference="A")
    (comb,) = [e for e in out["effects"] if e["name"] == "compression"]
    assert comb["votes"] == "2/2" and comb["delta_bic"] == pytest.approx(c["delta_bic"])
    # the combined verdict states its detection limits at its own (median) Q
    assert out["detection_limits"]["detector_integration"]["q"] == out["refined"]["q"]
    own = d.summary["detection_limits"]["resampling"]["limit"]
    assert out["detection_limits"]["resampling"]["limit_by_flight"] == [own, own]
    assert (f"quantisation lattice, 2 Δ log-likelihood = {c['delta_bic']:.3g}"
            in diagnosis_markdown(d.summary))


def test_jpeg_quality_exact_and_q_from_the_delivered_spectrum():
    """JPEG 30 at Q 2.0 (Pillow, no other effect): the quality is read exactly from the
    scene's lattice, and Q is chosen on the delivered spectrum (JPEG last): the transfer
    fit through the linearised JPEG put it at 2.47 once the quality was exact."""
    claimed, se_base, se_ref, d = _run({"compression": {"quality": 30}}, q=2.0, seed=7)
    assert claimed["compression"]["params"]["quality"] == 30
    assert abs(d.summary["refined"]["q"] - 2.0) < 0.1, d.summary["refined"]["q"]
    assert se_ref <= 0.25 * se_base, (se_base, se_ref)


def test_jpeg_under_very_sharp_optics(realdata, samples_dir):
    """Development c259 (SJER tile, Q 0.82, JPEG 40 and haze; independent generator): the
    earlier block-edge match gave quality 38 at a Q pinned near its floor (0.71); now the
    lattice gives 40 and the delivered spectrum Q ≈ 0.8 (the linearised transfer fit alone:
    1.08, and a refined spectral error 0.93 of the baseline's)."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    row = bench.diagnose_case(gen.make_case(259, sources))
    assert set(row["truth"]) == {"compression", "haze"}
    assert row["claimed"]["compression"]["quality"] == 40
    assert abs(row["q_refined"] - row["q_true"]) < 0.1, (row["q_refined"], row["q_true"])
    assert row["se_refined"] <= 0.5 * row["se_base"], (row["se_base"], row["se_refined"])


def test_shift_measured_again_against_the_refined_model(realdata, samples_dir):
    """Round 16's fresh c512 (noise only at Q 3.88; the LV baseline, sharpened by the
    noise, at Q 0.81) claimed a 0.18 px misregistration: the baseline's aliasing biased
    the shift. Measured again against the refined model it is not clear, and not claimed;
    development c29's true shift is still found."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    false = bench.diagnose_case(gen.make_case(512, sources))
    assert set(false["truth"]) == {"sensor_noise"}
    assert "misregistration" not in false["claimed"], false["claimed"]
    true = bench.diagnose_case(gen.make_case(29, sources))
    assert "misregistration" in true["claimed"], true["claimed"]
    got, want = true["claimed"]["misregistration"]["shift_px"], true["truth"][
        "misregistration"]["shift_px"]
    assert np.hypot(got[0] - want[0], got[1] - want[1]) < 0.1, (got, want)


def test_jpeg_transfer_unmeasured_bins_do_not_make_a_resampling(realdata, samples_dir):
    """Round 18. Development c487 (SJER tile, JPEG 35 and noise at Q 3.60): the JPEG's
    linearised transfer beyond the reference's optical cut-off was a ratio of noises
    (≈ 0.5 where the true pass is ≈ 0), and the fit claimed a 1.70 px resampling with
    Q 3.25 to take out the high frequencies it passed. With those bins left out it claims
    the JPEG and the noise only; c508 (JPEG 28 alone at Q 1.52) no longer claims a
    resampling either, and c229's true resampling under JPEG 45 (pitch 1.38 px) is still
    found (a 3 σ mask lost it)."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    for index, truth in ((487, {"compression", "sensor_noise"}), (508, {"compression"}),
                         (229, {"compression", "resampling"})):
        row = bench.diagnose_case(gen.make_case(index, sources))
        assert set(row["truth"]) == truth, (index, row["truth"])
        assert set(row["claimed"]) == truth, (index, row["claimed"])


def test_resampling_under_jpeg_beyond_the_optics_is_withdrawn(realdata, samples_dir):
    """Development cases of benchmarks/diagnose_independent.py (made by the independent
    generator, none with resampling in its truth beside JPEG at high Q): c157 (off-nadir,
    JPEG 37 and moved objects at Q 3.46 on an SJER tile) claimed ``resampling`` at a
    fitted Q of 3.63 with a native pitch of 1.22 px: the optics stop short of that grid's
    Nyquist (Q ≥ 2 × pitch), where resampling leaves no trace JPEG cannot leave, so it is
    withdrawn. c132 (resampling 1.32 px and JPEG 42 at Q 1.08 on the Brazil pasture),
    where the optics pass the native Nyquist, keeps it."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    false = bench.diagnose_case(gen.make_case(157, sources))
    assert "compression" in false["truth"] and "resampling" not in false["truth"]
    assert "resampling" not in false["claimed"], false["claimed"]
    assert false["se_refined"] <= false["se_base"] + 1e-9
    true = bench.diagnose_case(gen.make_case(132, sources))
    assert set(true["truth"]) == {"resampling", "compression"}
    assert set(true["claimed"]) == {"resampling", "compression"}, true["claimed"]
    assert abs(true["claimed"]["resampling"]["native_pitch_px"]
               - true["truth"]["resampling"]["native_pitch_px"]) < 0.2


def test_resampling_by_its_aliasing_with_q_refitted(realdata, samples_dir):
    """Round 19. Development c192 (a 1.69 px native grid and a shift at Q 3.95 on an SJER
    tile): the optics cut the band where resampling's roll-off lies, so route 2 finds it
    on the power spectrum. Scanned at the Q fitted without it, each pitch blurred twice
    (Q had taken up the roll-off) and none passed; with Q refitted for each scanned
    resampling it is found near its pitch and the refined Q is the true one. c605 (a
    control at Q 3.93) stays clean."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    row = bench.diagnose_case(gen.make_case(192, sources))
    assert set(row["truth"]) == {"resampling", "misregistration"}
    assert set(row["claimed"]) == {"resampling", "misregistration"}, row["claimed"]
    assert abs(row["claimed"]["resampling"]["native_pitch_px"]
               - row["truth"]["resampling"]["native_pitch_px"]) < 0.1
    assert abs(row["q_refined"] / row["q_true"] - 1) < 0.03
    assert row["se_refined"] <= 0.5 * row["se_base"]
    control = bench.diagnose_case(gen.make_case(605, sources))
    assert control["truth"] == {} and control["claimed"] == {}, control["claimed"]


def test_extension_cases_leave_the_halves_unchanged(realdata, samples_dir):
    """The development extension (seeds 5000-5999, forced effect sets) is its own split;
    forcing effects outside it is refused, and the halves' seeds still give the cases
    recorded in benchmarks/results/diagnose_independent.json (truth and Q)."""
    import json

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    stored = {r["case"]: r for r in json.loads(
        (ROOT / "benchmarks" / "results" / "diagnose_independent.json").read_text())["cases"]}
    for i in (8, 13, 52):       # noise + JPEG, colour + shift + noise, colour
        case = gen.make_case(i, sources)
        assert case.split == "development"
        assert case.truth == stored[case.name]["truth"]
        assert case.q == pytest.approx(stored[case.name]["q_true"], abs=1e-12)
    ext = gen.make_case(3, sources, base_seed=gen.EXTENSION_SEEDS[0],
                        effects=("sensor_noise", "scene_change"), q_range=(0.8, 1.5))
    assert ext.split == "extension" and ext.seed == 5003 and ext.name == "x5003"
    assert set(ext.truth) == {"sensor_noise", "scene_change"} and 0.8 <= ext.q <= 1.5
    with pytest.raises(ValueError, match="extension"):
        gen.make_case(3, sources, effects=("sensor_noise",))
    with pytest.raises(ValueError, match="one per family"):
        gen.draw_named_effects(np.random.default_rng(0), ("haze", "colour_response"))


def test_blur_leaving_q_at_its_floor_is_not_claimed(realdata, samples_dir):
    """Development-extension case x5000 (JPEG + noise at Q 1.0 on an SJER tile, made by the
    independent generator): resampling fitted with Q pinned at the bottom of its range
    stood in for the optics and was claimed, and the refined simulation fitted worse than
    the baseline. A blur that leaves Q at its floor is withdrawn: no resampling, and never
    above the baseline (the benchmark's own measure)."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(0, sources, **bench.extension_kw("noise", 0))
    assert case.name == "x5000" and set(case.truth) == {"compression", "sensor_noise"}
    row = bench.diagnose_case(case)
    assert "resampling" not in row["claimed"], row["claimed"]
    assert row["se_refined"] <= row["se_base"] + 1e-9, (row["se_base"], row["se_refined"])


def test_detector_named_by_the_exact_model(realdata, samples_dir):
    """Development-extension case x5216 (a 1.57 px detector box at Q 2.33 on a real tile,
    made by the independent generator): the fast transfer fit, whose Welch-window leakage
    smooths the box's sinc towards the atmosphere's roll-off, called it
    ``atmospheric_blur`` (held-out gain 0.202 against the detector's 0.199). The isotropic
    family is now decided by the exact window-aware model: ``detector_integration``, near
    its width, and the refined fit better than half the baseline's (benchmark's measure)."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(16, sources, **bench.extension_kw("isoblur", 16))
    assert case.name == "x5216" and set(case.truth) == {"detector_integration"}
    row = bench.diagnose_case(case)
    assert set(row["claimed"]) == {"detector_integration"}, row["claimed"]
    pitch = row["claimed"]["detector_integration"]["pitch_px"]
    assert abs(pitch - case.truth["detector_integration"]["pitch_px"]) < 0.25, pitch
    assert row["se_refined"] <= 0.5 * row["se_base"], (row["se_base"], row["se_refined"])


def test_low_q_detector_box_is_not_absorbed_into_q(realdata, samples_dir):
    """Development c1214 (round 37's fresh half: a 1.50 px detector box alone at Q 1.15 on
    the Australian tile, independent generator). The box folds a different mix of each
    alias cell than the sharpest simulation; the transfer's variance counted that as noise
    and the box's evidence was ΔBIC 7: Q absorbed it (LV Q 1.62 kept, nothing claimed,
    the box stated untestable below 1.72 px). With the cells' share taken out of the
    variance: the box, its width and the true Q, and the refined fit far better than half
    the baseline's (the benchmark's measure)."""
    import diagnose_independent as bench

    sources = gen.pick_sources(gen.list_sources(realdata, samples_dir))
    case = gen.make_case(1214, sources)
    assert set(case.truth) == {"detector_integration"} and case.source == "australia"
    row = bench.diagnose_case(case)
    assert set(row["claimed"]) == {"detector_integration"}, row["claimed"]
    pitch = row["claimed"]["detector_integration"]["pitch_px"]
    assert abs(pitch - case.truth["detector_integration"]["pitch_px"]) < 0.1, pitch
    assert abs(row["q_refined"] - case.q) < 0.05 * case.q, (row["q_refined"], case.q)
    assert row["se_refined"] <= 0.2 * row["se_base"], (row["se_base"], row["se_refined"])


@pytest.mark.parametrize("gsd_m, side_px", [(0.1, 150), (0.05, 333)])
def test_source_sat_px_is_the_largest_scene_fine_window_cuts(tmp_path, gsd_m, side_px):
    import rasterio
    from rasterio.transform import from_origin

    path = tmp_path / "src.tif"
    img = np.random.default_rng(0).integers(0, 255, (3, side_px, side_px), dtype=np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=side_px, height=side_px, count=3,
                       dtype="uint8", crs="EPSG:32611",
                       transform=from_origin(0, 0, gsd_m, gsd_m)) as ds:
        ds.write(img)
    src = gen.Source(name="t", path=path, gsd_m=gsd_m)
    sat = gen.source_sat_px(src, margin_px=12)
    # side on the fine (0.05 m) grid, in whole product pixels, less both margins
    assert sat == int(side_px * max(1.0, gsd_m / 0.05)) // gen.PHI - 24
    ground = gen.fine_window(src, np.random.default_rng(1), sat_px=sat, margin_px=12)
    assert ground.shape[-1] == (sat + 24) * gen.PHI
    bigger = gen.fine_window(src, np.random.default_rng(1), sat_px=sat + 1, margin_px=12)
    assert bigger.shape[-1] < (sat + 1 + 24) * gen.PHI   # the source holds no more


@pytest.mark.parametrize("extra, message", [
    (["--sat-px", "256"], "--sat-px: give --indices and --out"),
    (["--sat-px", "256", "--indices", "4,6"], "--sat-px: give --indices and --out"),
    (["--only", "validation"], "run part of the halves: give --out"),
    (["--indices", "4,6"], "run part of the halves: give --out"),
    (["--cases", "3"], "run part of the halves: give --out"),
    (["--variants"], "--variants: give --out"),
    (["--variants", "--only", "validation"], "--variants: give --out")])
def test_partial_runs_never_write_the_halves_file(tmp_path, extra, message):
    """Only a full run of both halves writes their results file (a part of them would
    replace every other row); the others need --out, and --merge joins them."""
    import os
    import subprocess

    halves = ROOT / "benchmarks" / "results" / "diagnose_independent.json"
    before = halves.read_bytes()
    res = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "diagnose_independent.py"),
                          *extra], capture_output=True, text=True,
                         timeout=120, env={**os.environ, "GEOSIM_REALDATA": str(tmp_path)})
    assert res.returncode != 0
    assert message in res.stderr
    assert halves.read_bytes() == before


def test_moved_objects_modelled_where_they_moved():
    """Six dark objects moved (drawn by the generator in the UAV image at one place and in
    the scene at another): the refined simulation models twelve blobs, each an object of
    the generator's 2.4 m × 1.0 m that left (dark in the UAV image, not in the scene) or
    appeared (the other way round), and halves the baseline's spectral error."""
    rng = np.random.default_rng(21)
    ground = gen.synthetic_ground(rng, (96 + 24) * gen.PHI)
    uav, real = gen.render(ground, 1.2, {"scene_change": {"n_objects": 6}}, rng, margin_px=12)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    valid = np.ones(real.shape[-2:], bool)
    d = diagnose_arrays(real, sim, q_base=calibrate_q_lv(sim, luma(real), valid),
                        rng=np.random.default_rng(0), q_lo=0.7)
    claimed = {e["name"]: e for e in d.summary["effects"]}
    assert set(claimed) == {"scene_change"}
    objects = d.summary["refined"]["moved_objects"]
    assert claimed["scene_change"]["params"]["n_objects_modelled"] == len(objects) == 12
    assert sorted(o["change"] for o in objects) == ["appeared"] * 6 + ["left"] * 6
    for o in objects:
        assert o["size_m"][0] == pytest.approx(2.4, rel=0.1)
        assert o["size_m"][1] == pytest.approx(1.0, rel=0.15)
        c, r = o["centre_px"]
        dark_in_uav = float(luma(uav[:, int(r * gen.PHI), int(c * gen.PHI)]))
        dark_in_scene = float(luma(real[:, int(r), int(c)]))
        assert (dark_in_uav < dark_in_scene) == (o["change"] == "left"), o
    se_base = gen.spectral_error(np.rint(d.baseline), real)
    se_ref = gen.spectral_error(np.rint(d.refined), real)
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_flight_with_a_rim_and_a_turned_misregistration():
    """The generator's real-flight form through the user's path: a UAV image with a nodata
    rim around a turned footprint, the satellite scene turned 0.4 deg clockwise, scaled
    1.002 and shifted. The misregistration alone is claimed (the rim makes no effect of
    its own), with the rotation's sign and size (the tool's counter-clockwise positive)
    and the scale, and the refined simulation fits better over the imaged blocks."""
    from tests.generator_cases import diagnose_flight_scene

    flight = {"footprint_deg": 12.0,
              "rotation_deg": 0.4, "scale": 1.002}
    truth = {"misregistration": {"shift_px": [0.35, -0.3]}}
    claimed, se_base, se_ref, d = diagnose_flight_scene(truth, q=1.4, seed=21, flight=flight,
                                                        sat_px=128)
    assert not d.valid.all()
    assert set(claimed) == {"misregistration"}, list(claimed)
    p = claimed["misregistration"]["params"]
    assert p["rotation_deg"] == pytest.approx(-0.4, abs=0.05), p
    assert p["scale"] == pytest.approx(1.002, abs=0.001), p
    assert se_ref < se_base, (se_base, se_ref)
