"""The exact (window-aware) duel inside a blur family, on scenes made with numpy alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from geosim.diagnose.exact_family import exact_duel
from geosim.diagnose.fit import build_spectral_data
from geosim.diagnose.select import BLUR_FAMILY, select_blur


def _airy_sims(scene: np.ndarray, q_grid: np.ndarray) -> list[np.ndarray]:
    """Scene filtered by the analytic circular-aperture OTF (cut-off 1/Q cycles/px)."""
    fy = np.fft.fftfreq(scene.shape[0])[:, None]
    fx = np.fft.fftfreq(scene.shape[1])[None, :]
    f = np.hypot(fy, fx)
    spec = np.fft.fft2(scene)
    out = []
    for q in q_grid:
        v = np.clip(f * q, 0, 1)
        otf = (2 / np.pi) * (np.arccos(v) - v * np.sqrt(1 - v * v))
        out.append(np.real(np.fft.ifft2(spec * otf)))
    return out


def _select_and_duel(real, sims, q_grid, family, q_start, block=32):
    """Forward selection among ``family``'s members on 32 px Welch blocks of a square
    scene with its four quadrants as folds, then the exact duel."""
    n = real.shape[0]
    origins = [(r, c) for r in range(0, n - block + 1, block)
               for c in range(0, n - block + 1, block)]
    groups = [[o for o in origins if (o[0] >= n / 2) == (i // 2 == 1)
               and (o[1] >= n / 2) == (i % 2 == 1)] for i in range(4)]
    full = build_spectral_data(sims, q_grid, real, origins=origins, block_px=block)
    folds = []
    for j, g in enumerate(groups):
        train = [o for i, gg in enumerate(groups) if i != j for o in gg]
        folds.append((build_spectral_data(sims, q_grid, real, origins=train, block_px=block),
                      build_spectral_data(sims, q_grid, real, origins=g, block_px=block)))
    members = tuple(m for m, fam in BLUR_FAMILY.items() if fam == family)
    sel = select_blur(full, folds, candidates=members, q_starts=(q_start,))
    assert sel.steps, f"no {family} blur selected at all"
    return exact_duel(real, sims, q_grid, full, origins, groups, block, sel, family, q_start)


@pytest.mark.parametrize("truth", ["detector_integration", "atmospheric_blur"])
def test_exact_duel_names_the_isotropic_member(truth):
    """A 1/f scene at Q 2.2 blurred by a 1.6 px square pixel aperture or by an atmosphere
    exp(-(f/0.35)^(5/3)) (analytic transfers, in numpy): the exact duel names the member
    that made it and keeps its parameter and Q near the truth."""
    rng = np.random.default_rng(3)
    n = 160
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.fftfreq(n)[None, :]
    f = np.hypot(fy, fx)
    white = np.fft.fft2(rng.normal(size=(n, n)))
    scene = np.real(np.fft.ifft2(white / np.maximum(f, 1 / n))) * 3 + 128
    q_grid = np.exp(np.linspace(np.log(0.7), np.log(3.5), 16))
    sims = _airy_sims(scene, q_grid)
    truth_sim = _airy_sims(scene, [2.2])[0]
    if truth == "detector_integration":
        # a 1.6 px square aperture: its analytic transfer sinc(1.6 fx) sinc(1.6 fy)
        h = np.sinc(1.6 * fx) * np.sinc(1.6 * fy)
    else:
        h = np.exp(-(f / 0.35) ** (5 / 3))
    real = np.real(np.fft.ifft2(np.fft.fft2(truth_sim) * h))
    real = real + rng.normal(0, 0.05, real.shape)
    out = _select_and_duel(real, sims, q_grid, "isotropic", 2.0)
    assert [s.name for s in out.steps] == [truth]
    p = out.final.effects[truth]
    if truth == "detector_integration":
        assert abs(p["pitch_px"] - 1.6) < 0.2, p
    else:
        assert abs(p["f0_cyc_per_px"] - 0.35) < 0.07, p
    assert abs(out.final.q - 2.2) < 0.2, out.final.q


@pytest.mark.parametrize("truth", ["motion_smear", "off_nadir_anisotropy"])
def test_exact_duel_names_the_anisotropic_member(truth):
    """A 1/f scene at Q 1.3 blurred along the columns (east, 90° from north) by a 2.6 px
    box (sinc, with its sign flip at 0.38 cycles/px) or by a Gaussian of σ 0.75 px (the
    same second moment; analytic transfers, in numpy): the exact duel names the member
    that made it, along its direction."""
    rng = np.random.default_rng(5)
    n = 160
    fy = np.fft.fftfreq(n)[:, None]
    fx = np.fft.fftfreq(n)[None, :]
    white = np.fft.fft2(rng.normal(size=(n, n)))
    scene = np.real(np.fft.ifft2(white / np.maximum(np.hypot(fy, fx), 1 / n))) * 3 + 128
    q_grid = np.exp(np.linspace(np.log(0.7), np.log(3.5), 16))
    sims = _airy_sims(scene, q_grid)
    truth_sim = _airy_sims(scene, [1.3])[0]
    if truth == "motion_smear":
        h = np.sinc(2.6 * fx) * np.ones_like(fy)
    else:
        h = np.exp(-2 * np.pi**2 * 0.75**2 * fx**2) * np.ones_like(fy)
    real = np.real(np.fft.ifft2(np.fft.fft2(truth_sim) * h)) + rng.normal(0, 0.05, (n, n))
    out = _select_and_duel(real, sims, q_grid, "anisotropic", 1.5)
    assert [s.name for s in out.steps] == [truth]
    direction = next(v for k, v in out.final.effects[truth].items() if k.endswith("_deg"))
    assert abs(direction - 90.0) < 5.0, out.final.effects
    # the other member predicts held-out blocks within 25 % and is listed, but at Q 1.3 the
    # sinc's sign flip lies inside the optical band: on all blocks the evidence against it
    # is very strong (ΔBIC > 10), which the report states
    (alt,) = out.steps[0].alternatives
    assert alt.delta_bic is not None and alt.delta_bic > 10.0, alt


def test_exact_duel_leaves_a_selection_without_the_family_alone():
    rng = np.random.default_rng(4)
    n = 96
    scene = ndimage.gaussian_filter(rng.normal(size=(n, n)), 1.0) * 20 + 128
    q_grid = np.exp(np.linspace(np.log(0.7), np.log(3.0), 12))
    sims = _airy_sims(scene, q_grid)
    real = sims[6] + rng.normal(0, 0.05, (n, n))
    origins = [(r, c) for r in range(0, n - 31, 32) for c in range(0, n - 31, 32)]
    full = build_spectral_data(sims, q_grid, real, origins=origins, block_px=32)
    sel = select_blur(full, None, candidates=(), q_starts=(1.5,))
    assert exact_duel(real, sims, q_grid, full, origins, [origins], 32, sel, "isotropic",
                      1.5) is sel
