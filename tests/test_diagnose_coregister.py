"""diagnose's co-registration adapts the shared registration kernel (issue 11).

Truth: known shifts applied to real imagery (Fourier shift, exact for band-limited
content); the kernel's own cross-check with scikit-image is in tests/test_align_local.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import rasterio
from scipy import ndimage

from geosim.align import phase_correlate
from geosim.diagnose.coregister import _block_shift, estimate_shift, integer_shift
from geosim.physics.geometry import fourier_shift


def _bali_grey(realdata) -> np.ndarray:
    """A fully valid 576 px square of the Bali farmland, averaged to 192 px (about 1 m)."""
    with rasterio.open(realdata / "bali_farmland_35cm_rgba_epsg32750.tif") as ds:
        rgb = ds.read([1, 2, 3], window=rasterio.windows.Window(29, 78, 576, 576),
                      out_shape=(3, 192, 192), resampling=rasterio.enums.Resampling.average)
        alpha = ds.read(4, window=rasterio.windows.Window(29, 78, 576, 576))
    assert (alpha > 0).all()
    return rgb.astype(np.float64).mean(axis=0)


def _shadowed_pair(grey: np.ndarray, shift_px: tuple[float, float], seed: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """sim and a 'real' scene: the ground moved by ``shift_px`` and blurred, large dark
    patches (shadows) moved by (-7, -8) px instead, plus noise."""
    rng = np.random.default_rng(seed)
    blobs = np.zeros(grey.shape)
    for _ in range(8):
        r0, c0 = rng.integers(20, grey.shape[0] - 20, 2)
        blobs[r0 - 15:r0 + 15, c0 - 10:c0 + 10] = 1.0
    shadow = ndimage.gaussian_filter(blobs, 6) * 3.0 * grey.std()
    sim = grey - shadow
    real = (fourier_shift(ndimage.gaussian_filter(grey, 1.2), shift_px)
            - fourier_shift(shadow, (-7.0, -8.0)) + rng.normal(0, 0.3 * grey.std(), grey.shape))
    return sim, real


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_integer_shift_is_the_kernel_and_finds_the_ground(realdata, seed):
    grey = _bali_grey(realdata)
    sim, real = _shadowed_pair(grey, (1.6, 2.45), seed)
    whole = integer_shift(sim, real, max_shift_px=8)
    assert whole == (2, 2)                                    # nearest whole pixel
    pc = phase_correlate(sim, real, whitening=1.0, upsample_factor=1, max_shift_px=8)
    assert whole == (int(pc.shift_px[0]), int(pc.shift_px[1]))
    est = estimate_shift(sim, real)
    assert est.shift_px == pytest.approx((1.6, 2.45), abs=0.06)


@pytest.mark.parametrize("shift", [(-5.0, 6.0), (3.0, -1.0), (7.3, -4.6)])
def test_known_shifts_on_real_imagery(realdata, shift):
    grey = _bali_grey(realdata)
    real = fourier_shift(grey, shift)
    assert integer_shift(grey, real) == tuple(int(round(v)) for v in shift)
    est = estimate_shift(grey, real)
    assert est.shift_px == pytest.approx(shift, abs=0.03)
    assert est.shift_m(0.5) == pytest.approx((shift[0] * 0.5, -shift[1] * 0.5), abs=0.015)


def test_search_radius_and_uncorrelatable_input(realdata):
    grey = _bali_grey(realdata)
    far = fourier_shift(grey, (20.0, 0.0))
    dc, dr = integer_shift(grey, far, max_shift_px=8)
    assert abs(dc) <= 8 and abs(dr) <= 8                      # the search is clipped
    assert integer_shift(grey, far, max_shift_px=24) == (20, 0)
    flat = np.full(grey.shape, 7.0)
    assert integer_shift(flat, grey) == (0, 0)               # nothing to correlate
    assert integer_shift(grey[:20, :20], grey[:20, :20]) == (0, 0)   # too small


def test_featureless_block_has_zero_correlation_without_warnings():
    """A uniform block (a saturated roof, a flat object in the scene; fresh round-22 case
    c718 on the sample site raised 'invalid value in scalar divide') measures no shift:
    its correlation is 0, below any threshold, not NaN."""
    import warnings

    flat = np.full((16, 16), 200.0)
    textured = np.random.default_rng(0).normal(100.0, 10.0, (16, 16))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for s, r in ((flat, textured), (textured, flat), (flat, flat)):
            assert _block_shift(s, r, 0.2)[2] == 0.0
    assert _block_shift(textured, textured, 0.2)[2] == pytest.approx(1.0)
