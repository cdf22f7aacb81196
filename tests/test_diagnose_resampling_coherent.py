"""Resampling under noise found by its coherent trace in the pixels.

The scenes come from the independent generator (``benchmarks/diagnose_generator.py``: the
native grid rendered on the 0.05 m grid, area-averaged, OpenCV's bicubic back onto the
product grid, Poisson-Gaussian noise), run blind through the whole diagnosis; the held-out
measure is checked on hand-made residual sums.
"""

from __future__ import annotations

import numpy as np
import pytest

import geosim.diagnose.stage_resampling_coherent as coherent
from geosim.diagnose.stage_resampling_coherent import CoherentScan
from tests.test_diagnose_independent import _run

NOISE = {"gain_dn": 0.18, "read_var_dn2": 3.6}


def test_heldout_dchi2_chooses_on_one_half_and_scores_the_other():
    left = np.zeros((2, 4), bool)
    left[:, :2] = True
    right = ~left   # 4 pixels each
    base = [[40.0, 80.0], [36.0, 88.0]]   # two Q factors
    resampled = [("r1", [30.0, 60.0]), ("r2", [20.0, 76.0])]
    scan = CoherentScan(halves=[left, right], base=base, resampled=resampled)  # type: ignore[arg-type]
    # chosen on the left: base Q 2 (36), resampled r2 (20); scored on the right: 88 → 76
    # in units of 88 / 4 per pixel; chosen on the right: Q 1 (80), r1 (60); on the left
    # 40 → 30 in units of 40 / 4
    assert scan.heldout_dchi2() == pytest.approx([(88 - 76) / 22, (40 - 30) / 10])
    assert scan.best() == "r1"   # lowest over both halves (90 against 96)


def test_resampling_under_noise_found_in_the_pixels():
    truth = {"resampling": {"native_pitch_px": 1.4}, "sensor_noise": NOISE}
    claimed, se_base, se_ref, _ = _run(truth, q=2.0, seed=27, sat_px=160)
    assert set(claimed) == {"resampling", "sensor_noise"}, list(claimed)
    # the generator's grid: 184 product px (160 + two 12 px margins) onto 131 native pixels
    assert abs(claimed["resampling"]["params"]["native_pitch_px"] - 184 / 131) <= 0.01
    assert se_ref <= 0.5 * se_base, (se_base, se_ref)


def test_without_the_coherent_test_that_resampling_is_missed(monkeypatch):
    """The same scene with the coherent test switched off: the spectrum alone misses it
    (so the test above is this stage's)."""
    monkeypatch.setattr(coherent, "COHERENT_MIN_DCHI2", np.inf)
    truth = {"resampling": {"native_pitch_px": 1.4}, "sensor_noise": NOISE}
    claimed, _, _, _ = _run(truth, q=2.0, seed=27, sat_px=160)
    assert "resampling" not in claimed and "sensor_noise" in claimed, list(claimed)


def test_noise_alone_claims_no_resampling():
    claimed, se_base, se_ref, _ = _run({"sensor_noise": NOISE}, q=2.0, seed=28, sat_px=160)
    assert set(claimed) == {"sensor_noise"}, list(claimed)
    assert se_ref <= se_base


def test_models_refined_on_one_half_are_never_scored_on_it():
    """A model refined on half 0 may fit half 1 best too; it is still only a candidate
    when choosing on half 0 (and so scored on half 1, where it was not fitted)."""
    left = np.zeros((2, 4), bool)
    left[:, :2] = True
    right = ~left
    scan = CoherentScan(halves=[left, right], base=[[40.0, 80.0]],
                        resampled=[("grid", [39.0, 79.0])],  # type: ignore[list-item]
                        base_refined=[[[38.0, 81.0]], [[41.0, 78.0]]],
                        resampled_refined=[[("fit0", [10.0, 30.0])],  # type: ignore[list-item]
                                           [("fit1", [30.0, 20.0])]])
    # chosen on the left: base refined on the left (38 → 81 on the right), fit0 (10 → 30);
    # chosen on the right: base refined on the right (78 → 41 on the left), fit1 (20 → 30)
    assert scan.heldout_dchi2() == pytest.approx([(81 - 30) / (81 / 4), (41 - 30) / (41 / 4)])
    assert scan.best() == "fit0"   # 40 over both halves against fit1's 50


def test_refinement_places_the_generators_native_grid():
    """The native grid as the independent generator lays it (OpenCV's area resize of the
    whole rendered window, 120 product px, onto round(120 / pitch) native pixels, both
    grids' outer edges together, then a 12 px margin cropped): the refinement, started
    half a step of the scan's pitches off (the farthest the scan's nearest pitch can be)
    and a third of a native pixel off in phase, finds its pitch and phase from the noisy
    pixels."""
    from geosim.diagnose.model import ForwardModel
    from tests.generator_cases import no_registration, scene_inputs

    truth = {"resampling": {"native_pitch_px": 1.45}, "sensor_noise": NOISE}
    inp, real = scene_inputs(truth, q=3.0, seed=31, sat_px=96)
    n_window = 96 + 2 * 12
    pitch = n_window / round(n_window / 1.45)          # 120 / 83
    phase = (-12.0) % pitch                           # a native edge at the window's
    start = ForwardModel(q=3.15, blur={"resampling": {"native_pitch_px": pitch + 0.005,
                                                      "cubic_a": -0.75},
                                       "detector_integration": {"pitch_px": 0.2}},
                         registration=no_registration(),
                         native_phase_px=((phase + pitch / 3) % pitch,) * 2)
    mask = np.zeros(real.shape[-2:], bool)
    mask[6:-6, 6:-6] = True
    m = coherent.refine_resampled(inp, start, mask)
    got = m.blur["resampling"]["native_pitch_px"]
    assert abs(got - pitch) < 0.004, (got, pitch)
    for p in m.native_phase_px:
        d = (p - phase + pitch / 2) % pitch - pitch / 2
        assert abs(d) < 0.1, (m.native_phase_px, phase)
    assert abs(m.q - 3.0) < 0.15
    assert m.blur["detector_integration"] == {"pitch_px": 0.2}   # the model's other blurs kept


def test_phase_harmonics_give_the_renders_at_any_phase():
    """Three native phases per axis nearly determine the product at every phase (the
    first-harmonic part of the native sampling's aliases; what the cubic kernel images
    beyond the native Nyquist and the product grid folds back is left out): the RSS
    interpolated between them at the phase it picks is within 5 % of the RSS's spread
    over the phase of the renderer's own product there, and that phase within 5 % of
    the renders' best (Q 3, pitch 1.4458 px: 120 / 83, as the generator lays it)."""
    from geosim.diagnose.simulate import QSimulator
    from geosim.physics.radiometry import luma
    from tests.generator_cases import gen, render_scene

    truth = {"resampling": {"native_pitch_px": 1.45}, "sensor_noise": NOISE}
    uav, real = render_scene(truth, q=3.0, seed=31, sat_px=96)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    g = luma(real)[6:-6, 6:-6].ravel()
    pitch = 120 / 83

    def residual(pr: float, pc: float) -> np.ndarray:
        return g - luma(sim.native(3.0, pitch, phase_px=(pr, pc)))[6:-6, 6:-6].ravel()

    steps = np.arange(coherent.PHASE_STEPS) * pitch / coherent.PHASE_STEPS
    res = np.stack([np.stack([residual(a, b) for b in steps]) for a in steps])
    rss, (pr, pc) = coherent.phase_harmonics(res, pitch)
    fine = np.arange(coherent.PHASE_FINE) * pitch / coherent.PHASE_FINE
    direct = {(a, b): float(np.sum(residual(a, b) ** 2)) for a in fine for b in fine}
    at = direct[min(direct, key=lambda k: abs(k[0] - pr) + abs(k[1] - pc))]
    spread = max(direct.values()) - min(direct.values())
    assert spread > 0.005 * at                  # the phase matters here
    assert abs(rss - at) < 0.05 * spread, (rss, at, spread)
    assert at - min(direct.values()) < 0.05 * spread


def test_phase_harmonics_rss_is_that_of_the_interpolated_residuals():
    """The RSS phase_harmonics reports is the sum of squares of the residual images that
    first-harmonic trigonometric interpolation makes at its phase (each pixel's nine
    Fourier coefficients over the scanned phases evaluated there, written out here), and
    no other of the PHASE_FINE² phases gives a lower one."""
    rng = np.random.default_rng(3)
    n, steps, fine_n, pitch = 500, coherent.PHASE_STEPS, coherent.PHASE_FINE, 1.37
    res = rng.normal(size=(steps, steps, n)) + 4.0 * rng.normal(size=n)
    rss, (pr, pc) = coherent.phase_harmonics(res, pitch)
    c = np.fft.fft2(res, axes=(0, 1)) / steps ** 2
    harmonics = (0, 1, -1)                     # np.fft order for three steps

    def at(phase_r: float, phase_c: float) -> float:
        img = np.zeros(n, dtype=complex)
        for a, ha in enumerate(harmonics):
            for b, hb in enumerate(harmonics):
                img += c[a, b] * np.exp(2j * np.pi * (ha * phase_r + hb * phase_c) / pitch)
        return float(np.sum(img.real ** 2))

    grid = np.arange(fine_n) * pitch / fine_n
    every = {(a, b): at(a, b) for a in grid for b in grid}
    assert rss == pytest.approx(at(pr, pc), rel=1e-10)
    assert rss <= min(every.values()) * (1 + 1e-10)


@pytest.mark.parametrize("truth,q,seed,start_pitch,start_a,passes", [
    # a true resampling (the generator's pitch 120 / 83 px)
    ({"resampling": {"native_pitch_px": 1.45}, "sensor_noise": NOISE}, 3.0, 31, 1.4458,
     -0.75, True),
    # an atmosphere the model lacks, and a short resampling standing in for its roll-off
    # (development c319: 1.16 px, Keys, at Q 3.2)
    ({"atmospheric_blur": {"f0_cyc_per_px": 0.22}, "sensor_noise": NOISE}, 3.2, 41, 1.16,
     -0.5, False),
])
def test_aliases_placed_must_help_beyond_the_roll_off(truth, q, seed, start_pitch, start_a,
                                                      passes):
    """The resampled model refined on each colour of the checkerboard, scored on the other
    against its own mean over the native phase (the roll-off without the aliases)."""
    from geosim.diagnose.context import EvalContext
    from geosim.diagnose.model import ForwardModel
    from tests.generator_cases import no_registration, scene_inputs

    inp, real = scene_inputs(truth, q=q, seed=seed, sat_px=96)
    ev = EvalContext(mask=np.ones(real.shape[-2:], bool), origins=[], block_px=32,
                     real_grey=inp.grey, noise_seed=0)
    halves = coherent.checker_halves(ev)
    start = ForwardModel(q=q, blur={"resampling": {"native_pitch_px": start_pitch,
                                                   "cubic_a": start_a}},
                         registration=no_registration())
    scan = CoherentScan(halves=halves, base=[], resampled=[])
    for k, h in enumerate(halves):
        m = coherent.refine_resampled(inp, start, h)
        scan.resampled_refined[k].append((m, coherent.rss_on_halves(inp, halves, m)))
    gain = coherent.aliasing_dchi2(inp, scan)
    assert (min(gain) >= coherent.ALIAS_MIN_DCHI2) == passes, gain
