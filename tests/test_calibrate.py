"""Calibration of Q by Laplacian variance: known answers, monotonicity, blocks, the step."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
import scipy.signal
from affine import Affine
from click.testing import CliRunner

from geosim.cli.main import cli
from geosim.config import FlightConfig, Parameters, SatelliteConfig, SiteConfig
from geosim.degrade import calibrate as cal
from geosim.degrade.blur import laplacian_moments, laplacian_variance, to_grey
from geosim.degrade.core import degrade_array, to_dtype
from geosim.degrade.steps import run_calibrate
from geosim.errors import CalibrationError, InputFileError, RasterError
from geosim.io.raster import RasterData
from geosim.physics import psf
from tests.helpers import textured_rgb, write_raster

UAV_TF = Affine(0.05, 0.0, 250000.0, 0.0, -0.05, 6190000.0)
SAT_TF = UAV_TF @ Affine.scale(10)


def _sjer(realdata: Path) -> np.ndarray:
    with rasterio.open(realdata / "sjer_2017" / "SJER_002.tif") as ds:
        return ds.read([1, 2, 3])


def _satellite_lv(image: np.ndarray, q: float) -> float:
    """LV of a simulated 'satellite': the reference path, delivered as uint8 RGB."""
    sat, _ = degrade_array(image, q=q, method="reference")
    return laplacian_variance(to_grey(to_dtype(sat, np.uint8)))


# --------------------------------------------------------------------------- pure kernels

@pytest.mark.parametrize("q_true", [1.0, 2.0, 3.0, 4.34, 6.0])
def test_known_q_is_recovered_synthetic(q_true: float) -> None:
    image = textured_rgb(400, 400, seed=21)
    q = cal.calibrate_q(image, None, _satellite_lv(image, q_true), phi=10, name="synthetic")
    assert q == pytest.approx(q_true, rel=0.02)


@pytest.mark.parametrize("q_true", [1.0, 2.0, 4.34, 6.0])
def test_known_q_is_recovered_real_sjer_tile(realdata: Path, q_true: float) -> None:
    image = _sjer(realdata)  # real rangeland texture (0.1 m, used as if on the UAV grid)
    q = cal.calibrate_q(image, None, _satellite_lv(image, q_true), phi=10, name="SJER_002")
    assert q == pytest.approx(q_true, rel=0.02)


def test_known_q_from_a_literal_spatial_convolution() -> None:
    """A 'satellite' made independently: convolution with the paper's |FFT(pupil)|² kernel
    (holding 99.5 % of the energy, symmetric padding), then cv2.resize INTER_CUBIC."""
    q_true, phi = 1.0, 10
    grey = to_dtype(to_grey(textured_rgb(400, 400, seed=22)), np.uint8)  # one grey band
    kernel = psf.pupil_psf(q_true, phi=phi)
    h = kernel.shape[0] // 2
    padded = np.pad(grey.astype(np.float64), h, mode="symmetric")
    blurred = scipy.signal.fftconvolve(padded, kernel, mode="valid").astype(np.float32)
    sat = cv2.resize(blurred, (40, 40), interpolation=cv2.INTER_CUBIC)
    lv_sat = laplacian_variance(to_dtype(sat, np.uint8).astype(np.float64))
    assert cal.calibrate_q(grey, None, lv_sat, phi=phi) == pytest.approx(q_true, rel=0.02)


def test_lv_falls_monotonically_with_q(realdata: Path) -> None:
    qs = np.linspace(0.5, 8.0, 16)
    for image in (textured_rgb(400, 400, seed=23), _sjer(realdata)):
        curve = cal.lv_curve(image, None, qs, phi=10, quantized=False)
        assert np.all(np.diff(curve) < 0), curve


def test_grey_path_equals_rgb_degrade_then_grey() -> None:
    image = textured_rgb(400, 400, seed=24)
    valid = np.ones((400, 400), bool)
    valid[:55, 300:] = False
    for q in (0.7, 2.0, 5.0):
        fast = cal.lv_of_degraded(image, valid, q, phi=10, quantized=False)
        rgb, vout = degrade_array(image, q=q, valid=valid, method="reference")
        assert fast == pytest.approx(laplacian_variance(to_grey(rgb), vout), rel=1e-6)


def test_rounding_to_uint8_adds_the_modelled_lv() -> None:
    """Delivered uint8 bands carry rounding noise: LV + 13 × Σc²/12 ≈ +0.483 grey levels²."""
    assert cal.quantization_lv(1.0) == pytest.approx(13 * (0.299**2 + 0.587**2 + 0.114**2) / 12)
    image = textured_rgb(800, 800, seed=25)
    for q in (3.0, 5.0):
        rgb, _ = degrade_array(image, q=q)
        delivered = laplacian_variance(to_grey(to_dtype(rgb, np.uint8)))
        unrounded = cal.lv_of_degraded(image, None, q, quantized=False)
        modelled = cal.lv_of_degraded(image, None, q)
        assert modelled == pytest.approx(delivered, rel=0.03)
        assert abs(unrounded - delivered) > 0.8 * cal.quantization_lv(1.0)
    floats = image.astype(np.float32)  # float images are delivered unrounded
    assert cal.lv_of_degraded(floats, None, 3.0) == pytest.approx(
        cal.lv_of_degraded(image, None, 3.0, quantized=False), rel=1e-9)


def test_unbracketed_target_names_the_input_and_values() -> None:
    image = textured_rgb(300, 300, seed=26)
    with pytest.raises(CalibrationError, match=r"flight PA2.*above.*q_min = 0\.5"):
        cal.calibrate_q(image, None, 1e6, name="flight PA2")
    with pytest.raises(CalibrationError, match=r"flight PA2.*below.*q_max = 8"):
        cal.calibrate_q(image, None, 1e-6, name="flight PA2")
    with pytest.raises(CalibrationError, match="flat or empty"):
        cal.calibrate_q(image, None, 0.0, name="flight PA2")
    with pytest.raises(ValueError):
        cal.lv_of_degraded(image, None, -1.0)


def _reader(grey: np.ndarray, row0: int, col0: int,
            data: tuple[int, int, int, int] | None = None):
    """Reader of windows relative to (row0, col0) of ``grey``; data only inside ``data``
    = (first row, end row, first col, end col) in ``grey`` (default: all of it)."""
    lo_r, hi_r, lo_c, hi_c = data or (0, grey.shape[0], 0, grey.shape[1])

    def read(r: int, c: int, h: int, w: int) -> RasterData:
        g = np.zeros((h, w), np.float32)
        v = np.zeros((h, w), bool)
        a0, b0 = max(row0 + r, lo_r), max(col0 + c, lo_c)
        a1, b1 = min(row0 + r + h, hi_r), min(col0 + c + w, hi_c)
        if a1 > a0 and b1 > b0:
            sl = (slice(a0 - row0 - r, a1 - row0 - r), slice(b0 - col0 - c, b1 - col0 - c))
            g[sl] = grey[a0:a1, b0:b1]
            v[sl] = True
        # pixel (row, col) of grey is map (col, -row): only the arrays matter here
        return RasterData(array=g[np.newaxis], valid=v,
                          transform=Affine(1, 0, col0 + c, 0, -1, -(row0 + r)), crs=None,
                          band_names=("grey",))
    return read


def test_blocks_pool_to_the_whole_image_lv() -> None:
    """Blocks with 16-px margins give the LV of one big image to < 1e-3 (relative)."""
    grey = to_grey(textured_rgb(900, 900, seed=27))
    inner = np.zeros((90, 90), bool)  # the calibrated area: satellite pixels 20..70
    inner[20:70, 20:70] = True
    whole = cal.DegradedLV.from_image(grey, None, q_min=0.5, out_mask=inner)
    blocked = cal.build_blocked_lv(_reader(grey, 200, 200), (50, 50), q_min=0.5,
                                   block_sat_px=16, margin_sat_px=16)
    assert len(blocked.blocks) == 16
    np.testing.assert_array_equal(blocked.lv_mask, whole.lv_mask[20:70, 20:70])
    assert blocked.n_pixels == 48 * 48
    for q in (0.5, 2.0, 8.0):
        assert blocked(q) == pytest.approx(whole(q), rel=1e-3)


def test_interior_window_is_unbiased_with_the_guard_band() -> None:
    """A flight inside a larger satellite scene (textured ground beyond its edge)."""
    scene = textured_rgb(1400, 1400, seed=28)
    grey = to_grey(scene)
    for q_true in (1.5, 4.0):
        sat = to_grey(to_dtype(degrade_array(scene, q=q_true)[0], np.uint8))
        read = _reader(grey, 400, 400, (400, 1000, 400, 1000))  # flight: 600 × 600 UAV px
        model = cal.build_blocked_lv(read, (60, 60), q_min=0.5, guard_sat_px=6,
                                     offset_lv=cal.quantization_lv(1.0))
        assert model.n_pixels == 46 * 46  # 6-px guard + the Laplacian reach
        lv_sat = laplacian_moments(sat[40:100, 40:100], model.lv_mask).variance
        q = cal.solve_q(model, lv_sat, name="inner flight").q
        assert q == pytest.approx(q_true, rel=0.005)


# --------------------------------------------------------------------------- the step

def _site(flights: dict[str, Path], sat: Path) -> SiteConfig:
    now = dt.datetime(2021, 7, 15, 13, 10)
    return SiteConfig(path=None, name="synthetic", crs="EPSG:28356",
                      reference_flight=next(iter(flights)),
                      flights=tuple(FlightConfig(id=k, image=v, acquired=now)
                                    for k, v in flights.items()),
                      satellite=SatelliteConfig(image=sat, acquired=now), paddocks=None,
                      parameters=Parameters(tile_px=500))


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run folder as the grid and align steps leave it, with a satellite at Q = 3."""
    out = tmp_path_factory.mktemp("calib") / "run"
    scene = textured_rgb(1000, 1400, seed=30)
    sat = to_dtype(degrade_array(scene, q=3.0)[0], np.uint8)
    sat[:, :4, :] = 0  # a nodata strip in the satellite scene
    (out / "grid").mkdir(parents=True)
    (out / "aligned").mkdir()
    write_raster(out / "grid" / "satellite.tif", sat, transform=SAT_TF, nodata=0)
    write_raster(out / "aligned" / "A.tif", scene, transform=UAV_TF)
    write_raster(out / "aligned" / "B.tif", scene[:, 200:900, 300:1200].copy(),
                 transform=UAV_TF @ Affine.translation(300, 200))
    far = UAV_TF @ Affine.translation(100_000, 0)  # nested in the grid, but elsewhere
    write_raster(out / "aligned" / "C.tif", scene[:, :300, :300].copy(), transform=far)
    return out


def test_run_calibrate_recovers_q_and_writes_json_and_figure(run_dir: Path) -> None:
    site = _site({k: run_dir / "aligned" / f"{k}.tif" for k in "ABC"},
                 run_dir / "grid" / "satellite.tif")
    result = run_calibrate(site, run_dir)
    summary = result.record
    assert summary["q"]["A"] == pytest.approx(3.0, rel=0.02)
    assert summary["q"]["B"] == pytest.approx(3.0, rel=0.02)
    assert summary["not_calibrated"] == ["C"]
    assert summary["mean_q"] == pytest.approx((summary["q"]["A"] + summary["q"]["B"]) / 2)
    assert "geosim diagnose" in result.warnings[0]  # Q = 3 is above real cameras' 0.5–2
    doc = json.loads((run_dir / "calibration.json").read_text())
    assert doc["mean_q"] == pytest.approx(summary["mean_q"])
    by_id = {f["flight"]: f for f in doc["flights"]}
    assert by_id["C"]["status"] == "no_overlap"
    for fid in "AB":
        f = by_id[fid]
        assert f["status"] == "ok"
        assert f["lv_at_q"] == pytest.approx(f["lv_satellite"], rel=1e-3)
        assert len(f["curve"]["q"]) == 16 and np.all(np.diff(f["curve"]["lv"]) < 0)
        assert f["curve"]["q"][0] == 0.5 and f["curve"]["q"][-1] == 8.0
        assert f["quantization_lv"] == pytest.approx(cal.quantization_lv(1.0))
    assert by_id["B"]["window_sat_px"] == [30, 20, 90, 70]
    assert by_id["A"]["n_pixels"] < 140 * 100 - 4 * 140  # satellite nodata strip left out
    png = (run_dir / "calibration.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    import matplotlib.image

    assert matplotlib.image.imread(run_dir / "calibration.png").shape[2] in (3, 4)


def test_plausibility_warning() -> None:
    from geosim.degrade.steps import plausibility_warning

    assert plausibility_warning(1.5) is None
    assert "above" in plausibility_warning(4.34) and "geosim diagnose" in plausibility_warning(4.34)
    assert "below" in plausibility_warning(0.3)


def test_run_calibrate_errors(run_dir: Path, tmp_path: Path) -> None:
    sat = run_dir / "grid" / "satellite.tif"
    with pytest.raises(InputFileError, match="geosim grid"):
        run_calibrate(_site({"A": sat}, sat), tmp_path / "empty")
    with pytest.raises(InputFileError, match="geosim align"):
        run_calibrate(_site({"Z": sat}, sat), run_dir)
    _copy_run(run_dir, tmp_path / "c", ["C"])
    with pytest.raises(CalibrationError, match="no flight could be calibrated"):
        run_calibrate(_site({"C": run_dir / "aligned" / "C.tif"}, sat), tmp_path / "c")
    assert json.loads((tmp_path / "c" / "calibration.json").read_text())["mean_q"] is None
    off = tmp_path / "off"
    _copy_run(run_dir, off, [])
    write_raster(off / "aligned" / "A.tif", textured_rgb(200, 200),
                 transform=UAV_TF @ Affine.translation(5, 0))  # half a satellite pixel off
    with pytest.raises(RasterError, match="not on the shared nested grid"):
        run_calibrate(_site({"A": off / "aligned" / "A.tif"}, sat), off)


def _copy_run(src: Path, dst: Path, flights: list[str]) -> None:
    import shutil

    (dst / "grid").mkdir(parents=True)
    (dst / "aligned").mkdir()
    shutil.copy(src / "grid" / "satellite.tif", dst / "grid" / "satellite.tif")
    for f in flights:
        shutil.copy(src / "aligned" / f"{f}.tif", dst / "aligned" / f"{f}.tif")


def test_cli_calibrate(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    _copy_run(run_dir, out, ["B"])
    # the site's inputs live outside the run folder (--out may not contain inputs)
    _copy_run(run_dir, tmp_path / "inputs", ["B"])
    inputs = tmp_path / "inputs"
    toml = tmp_path / "site.toml"
    toml.write_text(f'[[flights]]\nid = "B"\nimage = "{inputs / "aligned" / "B.tif"}"\n'
                    'acquired = 2021-07-15T13:10:00+10:00\n\n'
                    f'[satellite]\nimage = "{inputs / "grid" / "satellite.tif"}"\n')
    result = CliRunner().invoke(cli, ["calibrate", str(toml), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "mean Q = 3.0" in result.output and "geosim diagnose" in result.output
    assert (out / "calibration.json").is_file() and (out / "calibration.png").is_file()
