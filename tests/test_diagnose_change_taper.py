"""Changed regions tapered out of the transfer fit (``stage_blur.change_taper``).

Truth from outside the code under test: the real scene is the simulation at the true
Q blurred once more by a Gaussian of known σ, whose transfer is exp(−2π²σ²f²), with
bright "moved cattle" pasted only into it; the transfer the fit's Welch data measure
(real over the simulation at the true Q) must be that Gaussian's.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.context import FitWindow
from geosim.diagnose.exact import ExactBlocks, ExactSimulations, exact_fit
from geosim.diagnose.fit import TransferFit
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.spectra import apply_taper, block_origins
from geosim.diagnose.stage_blur import MIN_BLOCKS, change_taper, extent_block_px, spectral_setup
from geosim.diagnose.stage_inputs import make_inputs
from geosim.diagnose.stage_register import coregister

N_PX = 128
SIGMA_EXTRA_PX = 0.9
Q_TRUE = 1.5


def _scene(rng: np.random.Generator) -> np.ndarray:
    """A textured ground (1/f-like), (rows, cols), DN."""
    white = rng.normal(size=(N_PX, N_PX))
    fy = np.fft.fftfreq(N_PX)[:, None]
    fx = np.fft.fftfreq(N_PX)[None]
    amp = 1.0 / np.maximum(np.hypot(fy, fx), 1.0 / N_PX)
    g = np.real(np.fft.ifft2(np.fft.fft2(white) * amp))
    return 100.0 + 25.0 * g / g.std()


def _simulate(ground: np.ndarray):
    def simulate(q: float) -> np.ndarray:
        return ndimage.gaussian_filter(ground, 0.45 * q, mode="wrap")[np.newaxis]
    return simulate


def _case(seed: int = 3):
    rng = np.random.default_rng(seed)
    ground = _scene(rng)
    simulate = _simulate(ground)
    real = ndimage.gaussian_filter(simulate(Q_TRUE)[0], SIGMA_EXTRA_PX, mode="wrap")
    # 25 bright cattle-sized discs spread over the scene (a jittered 5 × 5 grid): in the
    # real scene only
    rr, cc = np.mgrid[:N_PX, :N_PX]
    hot = np.zeros((N_PX, N_PX), bool)
    grid = (np.arange(5) + 0.5) * N_PX / 5
    centres = np.stack(np.meshgrid(grid, grid), -1).reshape(-1, 2)
    for r0, c0 in centres + rng.uniform(-3, 3, size=centres.shape):
        disc = np.hypot(rr - r0, cc - c0) <= 3.0
        real[disc] += 60.0
        hot |= disc
    # the first pass's mask: the discs with a margin (its regions are the residual energy,
    # smoothed over 1.5 px, above a threshold, then dilated by 2 px)
    fit_mask = ~ndimage.binary_dilation(hot, np.ones((13, 13)))
    return simulate, real[np.newaxis], fit_mask


def _transfer_error(setup) -> float:
    """RMS of ln(measured / true) of the extra blur's transfer over 0.04-0.2 cycles/px: the
    measured one is |real / simulation at Q_TRUE| on the fit's bins."""
    d = setup.full
    measured = np.abs(d.t_real / d.g_at(Q_TRUE))
    fr = np.hypot(d.fy, d.fx)
    band = (fr > 0.04) & (fr < 0.2)
    truth = np.exp(-2.0 * np.pi**2 * SIGMA_EXTRA_PX**2 * fr[band] ** 2)
    return float(np.sqrt(np.mean(np.log(measured[band] / truth) ** 2)))


def test_taper_weights_vanish_in_regions_and_reach_one_away_from_them() -> None:
    mask = np.ones((64, 64), bool)
    mask[15:35, 15:35] = False
    valid = np.ones_like(mask)
    valid[:, :4] = False
    w = change_taper(mask, valid)
    assert w.min() >= 0.0 and w.max() <= 1.0
    # ≥ 6 px (2σ) inside the region (regions_mask has dilated the regions by 2 px already)
    assert np.all(w[21:29, 21:29] < 0.03)
    assert np.all(w[47:, 47:] > 0.999)
    assert np.all(w[:, :4] == 0.0)               # outside the valid area


def test_scattered_changes_are_tapered_and_the_transfer_is_the_true_one() -> None:
    simulate, real, fit_mask = _case()
    # the case is the one the taper is for: too few whole blocks outside the changes
    assert len(block_origins(fit_mask.shape, block_px=16, valid=fit_mask)) < MIN_BLOCKS
    inp = make_inputs(real, simulate, Q_TRUE, None, None, False, 0.5)
    model = ForwardModel(q=Q_TRUE, blur={}, registration=coregister(inp))
    window = FitWindow(mask=fit_mask, q_lo=0.7, q_hi=3.0, candidates=(),
                       q_starts=(Q_TRUE, 1.5))
    setup = spectral_setup(inp, model, window)
    assert setup.taper is not None and setup.block_px == 32
    assert len(setup.origins) >= MIN_BLOCKS
    # the taper's edge biases the transfer towards 1 by a few per cent (TAPER_SIGMA_PX)
    err_tapered = _transfer_error(setup)
    assert err_tapered < 0.05, err_tapered

    # the same blocks with the changes left in (what the fit used before the taper):
    # the discs' power, which the simulation does not share, biases the transfer
    everything = FitWindow(mask=np.ones_like(fit_mask), q_lo=0.7, q_hi=3.0, candidates=(),
                           q_starts=(Q_TRUE, 1.5))
    untapered = spectral_setup(inp, model, everything)
    assert untapered.taper is None
    err_untapered = _transfer_error(untapered)
    assert err_untapered > 2.0 * err_tapered, (err_untapered, err_tapered)


@pytest.mark.parametrize("shape,expected", [((128, 128), 32), ((80, 128), 32),
                                            ((40, 60), 16), ((64, 64), 16), ((20, 20), 16)])
def test_the_block_size_follows_the_valid_extent(shape, expected) -> None:
    """32 px blocks where the extent holds 16 half-overlapping ones (128 px: 49; 80 × 128:
    28), 16 px where it does not (64 px: 9 of 32 px), never smaller than 16 px."""
    assert extent_block_px(np.ones(shape, bool), 32) == expected


def test_a_turned_footprint_is_counted_by_its_valid_pixels() -> None:
    """A footprint turned 30° in a 96 px window: its valid pixels, not the window, decide."""
    rr, cc = np.mgrid[:96, :96] - 47.5
    t = np.radians(30.0)
    valid = (np.abs(rr * np.cos(t) + cc * np.sin(t)) < 30) & (
        np.abs(-rr * np.sin(t) + cc * np.cos(t)) < 30)
    n32 = len(block_origins(valid.shape, block_px=32, valid=valid))
    assert n32 < MIN_BLOCKS
    assert extent_block_px(valid, 32) == 16
    assert len(block_origins(valid.shape, block_px=16, valid=valid)) >= MIN_BLOCKS


def test_no_taper_where_whole_blocks_remain() -> None:
    simulate, real, _ = _case()
    inp = make_inputs(real, simulate, Q_TRUE, None, None, False, 0.5)
    model = ForwardModel(q=Q_TRUE, blur={}, registration=coregister(inp))
    mask = np.ones((N_PX, N_PX), bool)
    mask[:40, :40] = False      # one corner changed: plenty of whole blocks elsewhere
    window = FitWindow(mask=mask, q_lo=0.7, q_hi=3.0, candidates=(), q_starts=(Q_TRUE, 1.5))
    setup = spectral_setup(inp, model, window)
    assert setup.taper is None
    assert setup.tapered(inp.grey) is inp.grey


def _atmosphere(img: np.ndarray, f0_cyc_per_px: float) -> np.ndarray:
    """``img`` through exp(−(f/f0)^(5/3)), written here from the formula (periodic)."""
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None]
    mtf = np.exp(-(np.hypot(fy, fx) / f0_cyc_per_px) ** (5.0 / 3.0))
    return np.real(np.fft.ifft2(np.fft.fft2(img) * mtf))


def test_exact_model_tapers_its_renders_and_finds_the_atmosphere() -> None:
    """The exact model renders the blurred simulation and tapers it as the real scene was
    tapered after its blur: an atmosphere of known f0 behind scattered moved objects is
    refitted close to the truth, and closer than without the taper's order kept (the
    tapered simulations filtered afterwards)."""
    f0_true = 0.25
    simulate, _, fit_mask = _case()
    clean = _atmosphere(simulate(Q_TRUE)[0], f0_true)
    # objects inside the changed regions (their cores: the regions eroded back), in the
    # real scene only
    core = ~ndimage.binary_dilation(fit_mask, np.ones((13, 13)))
    real = np.where(core, clean + 60.0, clean)
    q_grid = np.exp(np.linspace(np.log(0.7), np.log(3.0), 14))
    sims = [simulate(q)[0] for q in q_grid]
    taper = change_taper(fit_mask, np.ones_like(fit_mask))
    origins = block_origins(fit_mask.shape, block_px=32, valid=np.ones_like(fit_mask))
    start = TransferFit(effects={"atmospheric_blur": {"f0_cyc_per_px": 0.4}}, sigmas={},
                        q=1.3, gain=1.0, chi2=0.0, n_params=3, n_eff=0.0)

    def fitted(ex: ExactSimulations) -> tuple[float, float]:
        blocks = ExactBlocks.build(ex, apply_taper(real, taper), origins, 32)
        fit = exact_fit(ex, blocks, start)
        return fit.effects["atmospheric_blur"]["f0_cyc_per_px"], fit.q

    # (seeds 1, 3, 5 when written: f0 0.251-0.252, Q 1.51-1.52 tapered after the blur;
    # 0.262-0.269, Q 1.58-1.62 with the simulations tapered before it)
    f0, q = fitted(ExactSimulations(sims, q_grid, taper=taper))
    f0_pre, _ = fitted(ExactSimulations([apply_taper(s, taper) for s in sims], q_grid))
    assert abs(f0 / f0_true - 1.0) < 0.03, f0
    assert abs(q / Q_TRUE - 1.0) < 0.03, q
    assert abs(f0 - f0_true) < abs(f0_pre - f0_true), (f0, f0_pre)
