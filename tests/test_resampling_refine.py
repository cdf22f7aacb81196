"""The resampling's pitch, Q and native phase searched on a score of known minimum
(``geosim.diagnose.resampling_refine``)."""

from __future__ import annotations

import numpy as np

from geosim.diagnose.resampling_refine import minimise_bounded, refine_resampling


def _bowl(p0: float, q0: float, phase0: tuple[float, float]):
    calls = []

    def se(p: float, q: float, ph: tuple[float, float]) -> float:
        calls.append((p, q, ph))
        # narrow in pitch, wider in ln Q, one minimum per native cell in phase
        return float(60 * (p - p0) ** 2 + 15 * np.log(q / q0) ** 2
                     + 0.04 * (2 - np.cos(2 * np.pi * (ph[0] - phase0[0]) / p)
                               - np.cos(2 * np.pi * (ph[1] - phase0[1]) / p)))
    return se, calls


def _phase_error(a: float, b: float, p: float) -> float:
    d = (a - b) % p
    return min(d, p - d)


def test_pitch_q_and_phase_found_from_a_distant_start():
    se, calls = _bowl(1.41, 1.07, (0.3, 1.2))
    r = refine_resampling(se, 1.30, 1.35, (0.0, 0.0), pitch_bounds=(1.15, 2.0),
                          q_bounds=(0.7, 2.5))
    assert abs(r.native_pitch_px - 1.41) < 0.01, r
    assert abs(r.q / 1.07 - 1) < 0.02, r
    assert _phase_error(r.phase_px[0], 0.3, 1.41) < 0.05, r
    assert _phase_error(r.phase_px[1], 1.2, 1.41) < 0.05, r
    assert 0 <= r.phase_px[0] < r.native_pitch_px and 0 <= r.phase_px[1] < r.native_pitch_px
    assert r.spectral_error < 1e-3
    assert r.n_evals == len({(round(p, 6), round(np.log(q), 6), round(ph[0] % p, 5),
                              round(ph[1] % p, 5)) for p, q, ph in calls})
    assert r.n_evals < 300


def test_bounds_hold_and_no_phase_when_not_asked():
    se, calls = _bowl(2.4, 0.5, (0.0, 0.0))          # minimum outside both boxes
    r = refine_resampling(se, 1.6, 1.2, (0.25, 0.5), pitch_bounds=(1.15, 2.0),
                          q_bounds=(0.7, 2.5), fit_phase=False)
    assert 1.15 <= r.native_pitch_px <= 2.0 and 0.7 <= r.q <= 2.5
    assert r.native_pitch_px > 1.99 and r.q < 0.71, r
    assert all(ph == (0.25, 0.5) for _, _, ph in calls)


def test_never_worse_than_the_start():
    # a start at the minimum of a noisy score: the search may wander, the result not
    rng = np.random.default_rng(0)

    def f(x: np.ndarray) -> float:
        return float(np.sum(x**2) + (0.0 if np.allclose(x, 0) else 0.5 + 0.1 * rng.random()))

    x, fx = minimise_bounded(f, np.zeros(2), np.full(2, -1.0), np.full(2, 1.0),
                             np.full(2, 0.1))
    assert np.allclose(x, 0) and fx == 0.0
