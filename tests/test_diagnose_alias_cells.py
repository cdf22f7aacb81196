"""The alias-cell transfer model sees a blur that acts before sampling at low Q, where the
product-grid model cannot, and equals it where nothing aliases: first in the prototype
(benchmarks/diagnose_alias_cells.py), then in the diagnosis (geosim.diagnose.alias_cells,
its fits and its exact model), against blurs applied on the fine grid with scipy."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import diagnose_alias_cells as alias  # noqa: E402

from geosim.diagnose.alias_cells import alias_pieces, cell_parts  # noqa: E402
from geosim.diagnose.exact import ExactSimulations  # noqa: E402
from geosim.diagnose.fit import (  # noqa: E402
    alias_unexplained_share,
    build_spectral_data,
    fit_transfer,
)
from geosim.diagnose.simulate import QSimulator  # noqa: E402
from geosim.diagnose.spectra import apply_taper, unexplained_power  # noqa: E402
from geosim.diagnose.stage_blur import change_taper, taper_pieces  # noqa: E402
from geosim.physics.radiometry import luma  # noqa: E402


def test_a_low_q_box_is_recovered_by_the_alias_cell_model_only():
    # synthetic ground (no sources): the generator's own pasture texture
    r = alias.run_case(3, 0.9, "detector_integration", 1.4, [])
    a, o = r["alias_cells"], r["product_grid"]
    assert r["gain_alias_cells"] > 5 * max(r["gain_product_grid"], 5.0)
    assert a["q"] == pytest.approx(0.9, rel=0.05)
    assert a["param"] == pytest.approx(1.4, rel=0.08)
    # the product-grid model of the box is further from the data than the box is from Q
    assert a["chi2"] < 0.5 * o["chi2"]


def test_the_models_agree_where_nothing_aliases():
    r = alias.run_case(3, 2.3, "detector_integration", 1.4, [])
    assert r["gain_alias_cells"] == pytest.approx(r["gain_product_grid"], rel=0.01)
    assert r["alias_cells"]["q"] == pytest.approx(r["product_grid"]["q"], rel=0.01)


# ---------------------------------------------------------------- in the diagnosis
# geosim.diagnose.alias_cells: the same model inside the transfer fits and the exact model.

def _texture(n_fine: int, seed: int) -> np.ndarray:
    """A 1/f texture on the fine grid, three equal bands (grey = the texture)."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(n_fine)[:, None]
    fx = np.fft.fftfreq(n_fine)[None, :]
    spec = np.fft.fft2(rng.normal(size=(n_fine, n_fine))) / np.maximum(np.hypot(fy, fx),
                                                                        2.0 / n_fine)
    img = np.real(np.fft.ifft2(spec))
    img = 120.0 + 40.0 * img / img.std()
    return np.repeat(img[np.newaxis], 3, axis=0)


def test_cell_parts_split_a_cosine_by_its_alias_cell():
    # 1.2 cycles per product pixel along the columns (phi 10): cells (0, +1) and (0, -1)
    phi, n = 10, 400
    x = np.arange(n)
    cosine = np.cos(2 * np.pi * 1.2 / phi * x)[np.newaxis, :].repeat(n, axis=0)
    parts = cell_parts(cosine, phi)
    both = np.real(parts[(0, 1)] + parts[(0, -1)])
    # away from the reflect padding's seams (their leakage: ~2 % of the amplitude)
    inner = (slice(40, -40), slice(40, -40))
    assert np.abs(both[inner] - cosine[inner]).max() < 0.05
    for cell, part in parts.items():
        if cell not in ((0, 1), (0, -1)):
            assert np.abs(part[inner]).max() < 0.05, cell


@pytest.mark.parametrize("effect,params,fine_blur", [
    ("detector_integration", {"pitch_px": 1.5},
     lambda img: ndimage.uniform_filter(img, size=(1, 15, 15), mode="wrap")),
    ("motion_smear", {"length_px": 2.1, "direction_deg": 90.0},   # along the columns
     lambda img: ndimage.uniform_filter(img, size=(1, 1, 21), mode="wrap")),
])
def test_exact_render_with_alias_pieces_matches_a_blur_before_sampling(effect, params,
                                                                       fine_blur):
    # truth: the blur applied on the 0.05 m grid with scipy (a box of 15 or 21 fine
    # pixels), then the paper model at Q 0.85 -- what a real sensor does. The exact model
    # with the alias pieces renders that; the product-grid model (the blur on the sampled
    # simulation) does not
    phi, q = 10, 0.85
    uav = _texture(640, 5)
    q_grid = [0.75, q, 1.0, 2.5]
    sim = QSimulator(uav, phi=phi, q_min=0.6)
    truth = luma(QSimulator(fine_blur(uav), phi=phi, q_min=0.6)(q))
    sims = [luma(sim(g)) for g in q_grid]
    pieces = alias_pieces(sim.alias_simulators(), q_grid, q_min=0.6)
    assert pieces[-1] is None and all(p is not None for p in pieces[:-1])
    with_cells = ExactSimulations(sims, q_grid, pieces=pieces).image(q, {effect: params})
    product = ExactSimulations(sims, q_grid).image(q, {effect: params})
    inner = (slice(6, -6), slice(6, -6))
    err_cells = np.sqrt(np.mean((with_cells - truth)[inner] ** 2))
    err_product = np.sqrt(np.mean((product - truth)[inner] ** 2))
    assert err_cells < 0.25 * err_product
    assert err_cells < 0.05 * truth.std()


def _changed_taper(n: int) -> np.ndarray:
    """A change taper over scattered discs (moved cattle) on an n × n product grid."""
    yy, xx = np.mgrid[:n, :n]
    mask = np.ones((n, n), bool)
    for r, c in ((20, 30), (70, 90), (100, 25), (45, 110), (95, 60)):
        mask &= np.hypot(yy - r, xx - c) > 7
    return change_taper(mask, np.ones((n, n), bool))


@pytest.mark.parametrize("tapered", [False, True])
def test_transfer_fit_with_alias_pieces_finds_a_low_q_box(tapered):
    # the real scene: a 1.5 px box on the fine grid at Q 0.85 (scipy, as above); the fit
    # with the pieces recovers pitch and Q, the product-grid fit lets Q absorb the box.
    # Tapered: changed regions tapered out of the scene and the simulations alike (as
    # spectral_setup does), the pieces with them (taper_pieces)
    phi, q = 10, 0.85
    uav = _texture(1280, 7)
    sim = QSimulator(uav, phi=phi, q_min=0.6)
    real = luma(QSimulator(ndimage.uniform_filter(uav, size=(1, 15, 15), mode="wrap"),
                           phi=phi, q_min=0.6)(q))
    q_grid = list(np.exp(np.linspace(np.log(0.7), np.log(2.6), 8)))
    sims = [luma(sim(g)) for g in q_grid]
    pieces = alias_pieces(sim.alias_simulators(), q_grid, q_min=0.6)
    if tapered:
        taper = _changed_taper(128)
        real, sims = apply_taper(real, taper), [apply_taper(s, taper) for s in sims]
        tapered_pieces = taper_pieces(pieces, taper)
        # the taper is linear: the tapered pieces sum to the tapered sum of the pieces,
        # so with the tapered k = 0 part they still make the tapered simulation
        both = sum(pieces[1].values())
        assert np.allclose(sum(tapered_pieces[1].values()),
                           apply_taper(both.real, taper) + 1j * apply_taper(both.imag, taper))
        pieces = tapered_pieces
    origins = [(r, c) for r in range(0, 128 - 32 + 1, 16) for c in range(0, 128 - 32 + 1, 16)]
    fits = {}
    for name, pc in (("cells", pieces), ("product", None)):
        data = build_spectral_data(sims, q_grid, real, origins=origins, block_px=32, pieces=pc)
        fits[name] = (fit_transfer(data, ["detector_integration"], q_starts=(1.2,)),
                      fit_transfer(data, [], q_starts=(1.2,)))
    box, null = fits["cells"]
    assert box.effects["detector_integration"]["pitch_px"] == pytest.approx(1.5, rel=0.1)
    assert box.q == pytest.approx(q, rel=0.08)
    assert null.chi2 - box.chi2 > 10 * max(fits["product"][1].chi2 - fits["product"][0].chi2,
                                           1.0)


@pytest.mark.parametrize("shift_px", [(0.0, 0.0), (0.4, -0.3)])
def test_alias_pieces_of_a_flight_with_a_nodata_rim(shift_px):
    """A flight's UAV image with a nodata rim (real flights have one): the pieces are made
    (round 36 made none), from the filled image; away from the rim they are the pieces of
    the whole image (the ground's own aliasing, to the reach of the cells' sharp frequency
    masks), and on the rim each takes its nearest
    valid pixel's value, as the registration fills the simulations they add to."""
    from geosim.diagnose.model import ForwardModel
    from geosim.diagnose.stage_blur import split_alias_cells
    from geosim.diagnose.stage_inputs import make_inputs
    from geosim.diagnose.stage_register import coregister
    from geosim.physics.geometry import fourier_shift

    phi, q, n = 10, 0.9, 96
    uav = _texture(n * phi, 11)
    uav_valid = np.ones(uav.shape[-2:], bool)
    uav_valid[:, :130] = False        # a 13 px rim on the product grid, and 7 px
    uav_valid[-70:, :] = False
    valid = uav_valid.reshape(n, phi, n, phi).all(axis=(1, 3))
    full = QSimulator(uav.astype(np.float32), phi=phi, q_min=0.6)
    real = fourier_shift(full(q), shift_px)
    q_grid = np.array([0.75, q, 1.1])

    def pieces_of(sim: QSimulator, valid: np.ndarray | None):
        inp = make_inputs(real, sim, q, valid, None, False, 0.5)
        model = ForwardModel(q=q, blur={}, registration=coregister(inp))
        return model.registration, split_alias_cells(inp, model, q_grid)

    sim = QSimulator(np.where(uav_valid, uav, 0.0).astype(np.float32), phi=phi,
                     valid=uav_valid, q_min=0.6)
    reg, pieces = pieces_of(sim, valid)
    _, whole = pieces_of(full, None)
    assert reg.fill_idx is not None and pieces is not None and whole is not None
    # away from the rim by more than the optics' and the fill's reach
    inner = ndimage.binary_erosion(valid, iterations=12)
    nearest = (reg.fill_idx[0][~valid], reg.fill_idx[1][~valid])
    for pc, pw in zip(pieces, whole, strict=True):
        for cell, piece in pc.items():
            # the cells' sharp frequency masks reach far: 5-15 % RMS here (none: 100 %)
            rms = np.sqrt(np.mean(np.abs(pw[cell][inner]) ** 2))
            assert np.sqrt(np.mean(np.abs(piece - pw[cell])[inner] ** 2)) < 0.2 * rms, cell
            np.testing.assert_array_equal(piece[~valid], piece[nearest])


def test_unexplained_power_is_what_no_combination_explains():
    # per bin, target = a·x0 + b·x1 + white noise over n blocks: the residual power over
    # its degrees of freedom (n − regressors holding power) estimates the noise's; a
    # regressor with no power at all is not counted and does not break the solve
    rng = np.random.default_rng(3)
    n, shape = 40, (12, 12)

    def cn(*s):
        return rng.normal(size=s) + 1j * rng.normal(size=s)

    x0, x1 = cn(n, *shape), cn(n, *shape)
    a, b = cn(*shape), cn(*shape)
    exact = a * x0 + b * x1
    rss, held = unexplained_power([x0, x1, np.zeros_like(x0)], exact)
    assert np.all(held == 2)
    assert np.all(rss < 1e-6 * np.sum(np.abs(exact) ** 2, axis=0))
    sigma2 = 0.3**2 * 2  # complex: 0.3 per part
    rss, held = unexplained_power([x0, x1], exact + 0.3 * cn(n, *shape))
    assert np.mean(rss / (n - held)) == pytest.approx(sigma2, rel=0.05)
    # one regressor: the residual of the plain coherence, S_rr (1 − γ²)
    t = exact + 0.3 * cn(n, *shape)
    rss1, _ = unexplained_power([x0], t)
    srr, s00 = np.sum(np.abs(t) ** 2, 0), np.sum(np.abs(x0) ** 2, 0)
    coh = np.abs(np.sum(t * np.conj(x0), 0)) ** 2 / (srr * s00)
    assert np.allclose(rss1, srr * (1 - coh))


def _box_scene(noise_dn: float) -> tuple[np.ndarray, list[np.ndarray], list[float],
                                          list, list[tuple[int, int]]]:
    """(real scene, grid simulations, their Q, alias pieces, Welch origins) of a 1.5 px box
    on the fine grid at Q 1.15 (scipy), 128 px, white noise of ``noise_dn``."""
    phi, q = 10, 1.15
    uav = _texture(1280, 11)
    sim = QSimulator(uav, phi=phi, q_min=0.6)
    real = luma(QSimulator(ndimage.uniform_filter(uav, size=(1, 15, 15), mode="wrap"),
                           phi=phi, q_min=0.6)(q))
    real = real + noise_dn * np.random.default_rng(5).normal(size=real.shape)
    q_grid = list(np.exp(np.linspace(np.log(0.7), np.log(2.6), 8)))
    sims = [luma(sim(g)) for g in q_grid]
    pieces = alias_pieces(sim.alias_simulators(), q_grid, q_min=0.6)
    origins = [(r, c) for r in range(0, 128 - 32 + 1, 16) for c in range(0, 128 - 32 + 1, 16)]
    return real, sims, q_grid, pieces, origins


def test_alias_share_lets_the_cells_folding_count_as_signal():
    # a box before sampling at Q 1.15 folds a different mix of each alias cell than the
    # sharpest simulation: not a linear function of it, so its coherence counts that as
    # noise. The cells explain it (share well below 1 where they hold power), the box's
    # evidence grows, and the fit still finds the box and Q
    real, sims, q_grid, pieces, origins = _box_scene(0.0)
    share = alias_unexplained_share(sims[0], pieces[0], real, origins, 32)
    assert share is not None and share.shape == (32, 32)
    assert float(np.median(share)) < 0.5, np.median(share)
    evidence = {}
    for name, sh in (("share", share), ("coherence", None)):
        data = build_spectral_data(sims, q_grid, real, origins=origins, block_px=32,
                                   pieces=pieces, share=sh)
        box = fit_transfer(data, ["detector_integration"], q_starts=(1.5,))
        null = fit_transfer(data, [], q_starts=(1.5,))
        evidence[name] = null.chi2 - box.chi2
        assert box.effects["detector_integration"]["pitch_px"] == pytest.approx(1.5, rel=0.1)
        assert box.q == pytest.approx(1.15, rel=0.08)
    assert evidence["share"] > 2 * evidence["coherence"], evidence
    # too few blocks for nine coefficients a bin: no share
    assert alias_unexplained_share(sims[0], pieces[0], real, origins[:17], 32) is None


def test_alias_share_keeps_white_noise_as_noise():
    # a scene that differs from the sharpest simulation only by white noise: no cell
    # explains any of it, and the share stays near 1 (the ratio of two unbiased estimates
    # of the same noise, pooled over 3 x 3 bins, clipped at 1)
    _, sims, _, pieces, origins = _box_scene(0.0)
    noisy = sims[0] + 2.0 * np.random.default_rng(9).normal(size=sims[0].shape)
    share = alias_unexplained_share(sims[0], pieces[0], noisy, origins, 32)
    assert float(np.median(share)) > 0.85, np.median(share)
