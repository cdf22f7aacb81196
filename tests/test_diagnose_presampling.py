"""Physics where it acts: shifts and blurs on the fine grid before sampling, and the
window-aware (exact) transfer model.

Truth comes from known transforms (a whole-pixel shift is a roll), from the absence of
aliasing at high Q (blur before and after sampling then agree), and from scenes made by
the independent generator ``benchmarks/diagnose_generator.py`` (no geosim code).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_generator as gen  # noqa: E402

from geosim.diagnose.effects import get_effect  # noqa: E402
from geosim.diagnose.exact import ExactBlocks, ExactSimulations, exact_fit  # noqa: E402
from geosim.diagnose.fit import build_spectral_data, fit_transfer  # noqa: E402
from geosim.diagnose.model import (  # noqa: E402
    ForwardModel,
    NoiseEstimate,
    blur_apply,
)
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.spectra import block_origins  # noqa: E402
from geosim.physics.radiometry import luma  # noqa: E402
from tests.helpers import no_registration  # noqa: E402


def _ground(seed: int, sat_px: int) -> np.ndarray:
    return gen.synthetic_ground(np.random.default_rng(seed), sat_px * gen.PHI)


def _transfer(effects: dict[str, dict[str, float]]):
    def tr(fy, fx):
        h = np.ones(np.broadcast_shapes(fy.shape, fx.shape))
        for n, p in effects.items():
            h = h * get_effect(n).transfer(fy, fx, **p)
        return h
    return tr


def test_variant_shift_of_whole_pixels_is_a_roll():
    uav = _ground(1, 48)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    moved = sim.variant(shift_px=(2.0, -1.0))(1.5)
    rolled = np.roll(sim(1.5), (-1, 2), axis=(-2, -1))
    inner = (slice(None), slice(6, -6), slice(6, -6))
    assert np.max(np.abs(moved[inner] - rolled[inner])) < 0.5
    assert sim.shifted((2.0, -1.0)) is sim.variant(shift_px=(2.0, -1.0))   # cached


def test_variant_blur_before_sampling_equals_after_without_aliasing():
    # Q = 3: the optics cut at 1/3 cycle per satellite pixel, below its Nyquist, so a blur
    # acting before or after the sampling gives the same image
    uav = _ground(2, 48)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    eff = {"off_nadir_anisotropy": {"sigma_px": 0.9, "azimuth_deg": 30.0}}
    before = sim.variant(transfer=_transfer(eff), key="t")(3.0)
    after = blur_apply(sim(3.0), eff)
    inner = (slice(None), slice(6, -6), slice(6, -6))
    rms = np.sqrt(np.mean((before[inner] - after[inner]) ** 2))
    assert rms < 0.02 * np.std(after[inner]), rms


def test_blur_before_sampling_matches_an_independent_low_q_scene():
    # Q = 0.9 passes content above the satellite Nyquist: the generator's off-nadir blur
    # (on the fine grid) keeps it from aliasing; the same blur after sampling cannot
    truth = {"off_nadir_anisotropy": {"sigma_px": 1.1, "azimuth_deg": 60.0}}
    rng = np.random.default_rng(3)
    uav, real = gen.render(gen.synthetic_ground(rng, 96 * gen.PHI), 0.9, truth, rng,
                           margin_px=12)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    before = np.rint(sim.variant(transfer=_transfer(truth), key="t")(0.9))
    after = np.rint(blur_apply(sim(0.9), truth))
    se_before = gen.spectral_error(before, real)
    se_after = gen.spectral_error(after, real)
    assert se_before < 0.5 * se_after, (se_before, se_after)


def test_exact_transfer_model_removes_the_window_bias():
    # a 2.6 px smear at Q 3.5 on a small scene (16 px Welch blocks): the fast fit sees it
    # through the window's leakage and measures it short; the exact model does not
    truth = {"motion_smear": {"length_px": 2.6, "direction_deg": 80.0}}
    rng = np.random.default_rng(4)
    uav, real = gen.render(gen.synthetic_ground(rng, 96 * gen.PHI), 3.5, truth, rng,
                           margin_px=12)
    sim = QSimulator(uav, phi=gen.PHI, q_min=0.6)
    q_grid = np.exp(np.linspace(np.log(0.7), np.log(5.0), 18))
    sims = [luma(sim(q)) for q in q_grid]
    grey = luma(real)
    origins = block_origins(grey.shape, block_px=16)
    full = build_spectral_data(sims, q_grid, grey, origins=origins, block_px=16)
    fast = fit_transfer(full, ["motion_smear"], q_starts=(3.0,))
    ex_sims = ExactSimulations(sims, q_grid)
    exact = exact_fit(ex_sims, ExactBlocks.build(ex_sims, grey, origins, 16), fast)
    err_fast = abs(fast.effects["motion_smear"]["length_px"] - 2.6)
    err_exact = abs(exact.effects["motion_smear"]["length_px"] - 2.6)
    assert err_exact < 0.15 * 2.6, exact.effects
    assert err_exact < err_fast, (fast.effects, exact.effects)


def _columns_cosine(n_sat: int, phi: int, cycles: int) -> np.ndarray:
    """A fine-grid image varying along columns only: a cosine of ``cycles`` whole cycles
    over the window (bands, rows, cols), DN."""
    x = np.arange(n_sat * phi)
    row = 100.0 + 50.0 * np.cos(2 * np.pi * cycles * x / (n_sat * phi))
    return np.repeat(row[None, None, :], n_sat * phi, axis=1).astype(np.float32)


def test_native_resampling_aliases_as_the_native_sampling_does():
    """A sinusoid above the product Nyquist (0.60 cycles per product pixel) seen by a
    native sampling of pitch ≈ 1.5 px folds to |0.60·p − 1| / p cycles per product pixel
    (analytic aliasing of the native grid), not where resampling the already sampled
    product would put it (0.60 → 0.40 on the product grid, then folded again by the
    native grid). QSimulator.native renders from the fine grid, so the peak is at the
    native alias."""
    n_sat, phi = 128, gen.PHI
    cycles = 77                                   # whole cycles over the fine window
    sim = QSimulator(_columns_cosine(n_sat, phi, cycles), phi=phi, q_min=0.5)
    out = sim.native(0.6, 1.5)
    n_nat = int(round(n_sat / 1.5))
    pitch = n_sat / n_nat                         # native pitch actually rendered, px
    f = cycles / n_sat                            # cycles per product pixel (0.60)
    f_native = f * pitch                          # cycles per native sample (≈ 0.90)
    alias = abs(f_native - round(f_native)) / pitch
    w = np.hanning(n_sat)
    spec = np.abs(np.fft.rfft((out[0].mean(axis=0) - out[0].mean()) * w))
    peak = int(np.argmax(spec[1:])) + 1
    assert abs(peak - alias * n_sat) <= 1.0, (peak, alias * n_sat)
    # resampling the sampled product puts it elsewhere (a different fold)
    f_prod = 1.0 - f                              # 0.40 after the product sampling
    f2 = f_prod * pitch
    wrong = abs(f2 - round(f2)) / pitch
    assert abs(wrong - alias) * n_sat > 5
    assert spec[peak] > 10 * np.median(spec[1:])


def test_native_phase_shift_flips_the_alias_not_the_passband():
    """Moving the native grid half a cell against the scene
    (``ForwardModel.native_phase_px``) leaves content below the native Nyquist where
    it was and turns content the native grid aliases by π (analytic: a sample at
    (k + ½)·pitch of frequency f, reconstructed at f − 1/pitch): what a native grid of
    unknown phase changes, and nothing else."""
    n_sat, phi = 128, gen.PHI
    reg = no_registration()
    w = np.hanning(n_sat - 32)

    def spectra(cycles: int) -> tuple[np.ndarray, np.ndarray, int]:
        sim = QSimulator(_columns_cosine(n_sat, phi, cycles), phi=phi, q_min=0.5)
        model = ForwardModel(q=0.6, blur={"resampling": {"native_pitch_px": 1.5}},
                             registration=reg)
        half = 0.75                                 # half a native cell

        def spec(m: ForwardModel) -> np.ndarray:
            prof = m.deterministic(sim)[0, 16:-16, 16:-16].mean(axis=0)  # off the edges
            return np.fft.rfft((prof - prof.mean()) * w)

        s0 = spec(model)
        s1 = spec(model.without(native_phase_px=(0.0, half)))   # along the columns
        k = int(np.argmax(np.abs(s0[1:]))) + 1
        return s0, s1, k

    s0, s1, k = spectra(16)                         # 0.125 cycles/px: below the native Nyquist
    assert abs(s1[k] - s0[k]) < 0.02 * abs(s0[k]), (s0[k], s1[k])
    s0, s1, k = spectra(77)                         # 0.60 cycles/px: aliased to ≈ 0.064
    assert abs(k / (n_sat - 32) - 0.064) < 0.015, k
    assert abs(s1[k] + s0[k]) < 0.1 * abs(s0[k]), (s0[k], s1[k])   # sign flipped


def test_native_sampling_reused_across_kernels_gives_the_fresh_render():
    """QSimulator.native keeps a pitch's native sampling for the next call (the kernel
    scans render each pitch with both kernels): every render equals that of a simulator
    that never rendered before, whatever came before it."""
    img = _ground(5, 48)
    sim = QSimulator(img, phi=gen.PHI, q_min=0.5)
    calls = [(1.4, -0.75), (1.4, -0.5), (1.45, -0.5), (1.6, -0.75), (1.4, -0.75), (1.6, -0.5)]
    for q in (1.2, 2.0):
        for pitch, a in calls:
            got = sim.native(q, pitch, cubic_a=a)
            fresh = QSimulator(img, phi=gen.PHI, q_min=0.5).native(q, pitch, cubic_a=a)
            assert np.array_equal(got, fresh), (q, pitch, a)


def test_native_row_step_reused_across_column_phases_gives_the_fresh_render():
    """QSimulator.native keeps the native rows' step of a row phase for the next column
    phase (the phase scans render every column phase of a row phase in turn): every
    render equals that of a simulator that never rendered before."""
    img = _ground(8, 48)
    sim = QSimulator(img, phi=gen.PHI, q_min=0.5)
    calls = [(1.4, (0.0, 0.0)), (1.4, (0.0, 0.5)), (1.4, (0.0, 0.9)), (1.4, (0.5, 0.9)),
             (1.4, (0.5, 0.0)), (1.45, (0.5, 0.0)), (1.4, (0.0, 0.5)), (1.4, (0.5, 0.5))]
    for q in (1.2, 2.0):
        for pitch, phase in calls:
            got = sim.native(q, pitch, phase_px=phase)
            fresh = QSimulator(img, phi=gen.PHI, q_min=0.5).native(q, pitch, phase_px=phase)
            assert np.array_equal(got, fresh), (q, pitch, phase)


def test_noise_realisations_render_the_model_once_with_the_same_arrays():
    """ForwardModel.delivered_realisations gives the arrays separate ``delivered`` calls
    give (the deterministic part rendered once, not modified by the noise)."""
    sim = QSimulator(_ground(6, 48), phi=gen.PHI, q_min=0.5)
    reg = no_registration()
    noise = NoiseEstimate(gain_dn=0.2, read_var_dn2=4.0, gain_sigma=0.0, read_sigma=0.0,
                          white_var_dn2=20.0, whiteness=1.0, claimed=True, quantization_dn2=0.0)
    model = ForwardModel(q=1.5, blur={"resampling": {"native_pitch_px": 1.4}},
                         registration=reg, noise=noise)
    rngs = [np.random.default_rng(7 + k) for k in range(3)]
    many = model.delivered_realisations(sim, rngs, quantized=True)
    one = [model.delivered(sim, np.random.default_rng(7 + k), quantized=True) for k in range(3)]
    assert all(np.array_equal(a, b) for a, b in zip(many, one, strict=True))
    assert not np.array_equal(many[0], many[1])      # distinct realisations
