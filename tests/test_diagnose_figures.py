"""Diagnosis figures: flight named in titles, map coordinates, scale bar, --dpi."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from affine import Affine  # noqa: E402
from PIL import Image  # noqa: E402
from rasterio.crs import CRS  # noqa: E402
from rasterio.transform import array_bounds  # noqa: E402

from geosim.diagnose.engine import Diagnosis  # noqa: E402
from geosim.diagnose.report_figures import (  # noqa: E402
    draw_scale_bar,
    flights_figure,
    map_extent,
    mismatch_maps_figure,
    save_png,
    scale_bar_length,
)

TRANSFORM = Affine(0.5, 0, 500123.0, 0, -0.5, 6200456.0)
CRS_UTM = CRS.from_epsg(32756)


def _diag(shape=(60, 90)) -> Diagnosis:
    rng = np.random.default_rng(0)
    maps = {k: rng.uniform(0.5, 2.0, shape) for k in
            ("residual_energy", "blur_ratio", "gain", "offset")}
    z = np.zeros((1, *shape))
    return Diagnosis(summary={}, real=z, baseline=z, refined=z, valid=np.ones(shape, bool),
                     maps=maps)


def test_map_extent_is_the_rasters_bounds():
    west, south, east, north = array_bounds(60, 90, TRANSFORM)  # rasterio, independent
    assert map_extent(TRANSFORM, (60, 90)) == pytest.approx((west, east, south, north))


def test_mismatch_maps_name_flight_and_carry_map_coordinates():
    fig = mismatch_maps_figure(_diag(), transform=TRANSFORM, crs=CRS_UTM, flight="F2")
    try:
        assert "flight F2" in fig._suptitle.get_text()
        west, south, east, north = array_bounds(60, 90, TRANSFORM)
        image_axes = [ax for ax in fig.axes if ax.images and ax.get_xlabel()]
        assert len(image_axes) == 4
        for ax in image_axes:
            assert ax.images[0].get_extent() == pytest.approx([west, east, south, north])
            assert ax.get_xlabel() == "easting (m)"
        assert "northing (m)" in image_axes[0].get_ylabel()
        assert "EPSG:32756" in image_axes[0].get_ylabel()
        # the scale bar: a line whose length in map units is the number on its label
        for ax in image_axes:
            bar = [ln for ln in ax.lines if ln.get_gid() == "scale_bar"]
            label = [t for t in ax.texts if t.get_gid() == "scale_bar_label"]
            assert len(bar) == 1 and len(label) == 1
            x = bar[0].get_xdata()
            value, unit = label[0].get_text().split()
            assert unit == "m"
            assert x[1] - x[0] == pytest.approx(float(value))
            assert float(value) == 10.0   # 45 m wide: a fifth is 9 m, the round length 10 m
    finally:
        plt.close(fig)


@pytest.mark.parametrize(("width_m", "expected"), [(45.0, 10.0), (1000.0, 200.0),
                                                   (7.0, 1.0), (2600.0, 500.0),
                                                   (30000.0, 5000.0)])
def test_scale_bar_length_is_round_and_near_a_fifth(width_m, expected):
    length = scale_bar_length(width_m)
    assert length == expected
    mantissa = length / 10 ** np.floor(np.log10(length))
    assert mantissa in (1.0, 2.0, 5.0)
    assert width_m / 10 <= length <= width_m / 2.5


def test_scale_bar_label_in_km_matches_length():
    fig, ax = plt.subplots()
    try:
        length, label = draw_scale_bar(ax, (0.0, 30000.0, 0.0, 20000.0))
        assert (length, label) == (5000.0, "5 km")
    finally:
        plt.close(fig)
    with pytest.raises(ValueError):
        scale_bar_length(0.0)


def _per(q_base, q_ref):
    return {"baseline": {"q": q_base, "rmse": 5.0}, "refined": {"q": q_ref, "rmse": 3.0}}


def test_combined_figure_says_all_flights(tmp_path):
    per = {"F1": _per(2.0, 1.5), "F2": _per(2.2, 1.6)}
    fig = flights_figure(per, {"refined": {"q": 1.55, "rmse": 3.0}})
    name = save_png(fig, tmp_path / "c.png", dpi=50)
    title = Image.open(tmp_path / name).info["Title"]   # the PNG's own text chunk
    assert "All flights (combined)" in title and "F1" in title and "F2" in title


def test_dpi_scales_png_pixels_and_title_is_in_the_file(tmp_path):
    sizes = {}
    for dpi in (50, 100):
        fig = mismatch_maps_figure(_diag(), transform=TRANSFORM, crs=CRS_UTM, flight="F7")
        save_png(fig, tmp_path / f"m{dpi}.png", dpi=dpi, tight=False)
        with Image.open(tmp_path / f"m{dpi}.png") as im:
            sizes[dpi] = im.size
            assert "flight F7" in im.info["Title"]
    # figsize 16 × 4.6 in: pixels = inches × dpi
    assert sizes[50] == (800, 230)
    assert sizes[100] == (1600, 460)


def test_diagnose_grids_figures_name_flight_and_follow_dpi(tmp_path):
    """Through the real writer: every PNG of a flight names it, at the dpi asked."""
    from geosim.diagnose.grids import FlightPixels, diagnose_grids
    from geosim.diagnose.simulate import QSimulator
    from tests.test_diagnose_effects import textured_uav

    uav = textured_uav(192, seed=3)
    real = np.round(QSimulator(uav, phi=2, q_min=0.7)(1.4))
    pixels = FlightPixels.of_arrays(uav, real, sat_transform=TRANSFORM, crs=CRS_UTM, phi=2,
                                    q_base=1.4)
    doc = diagnose_grids(pixels, tmp_path, phi=2, extra={"flight": "A1"}, dpi=40)
    assert len(doc["plots"]) == 3
    for name in doc["plots"]:
        with Image.open(tmp_path / name) as im:
            assert "flight A1" in im.info["Title"], name
            if name == "mismatch_maps.png":
                assert im.size == (640, 184)   # 16 × 4.6 in at 40 dpi
    assert "![mismatch_maps](mismatch_maps.png)" in (tmp_path / "report.md").read_text()


def test_cli_dpi_and_combined_figures(tmp_path):
    """`geosim diagnose --uav A --uav B --dpi 40`: flight titles, combined figure, embeds."""
    import json

    from click.testing import CliRunner

    from geosim.cli.main import cli
    from geosim.diagnose.simulate import QSimulator
    from geosim.io.raster import write_geotiff
    from tests.test_diagnose_effects import textured_uav

    uav = textured_uav(192, seed=5)
    real = np.clip(np.round(QSimulator(uav, phi=2, q_min=0.7)(1.4)), 0, 255).astype(np.uint8)
    for name in ("fa", "fb"):
        write_geotiff(tmp_path / f"{name}.tif", np.clip(uav, 0, 255).astype(np.uint8),
                      transform=Affine(0.25, 0, 500000.0, 0, -0.25, 6200000.0),
                      crs="EPSG:32756")
    write_geotiff(tmp_path / "sat.tif", real,
                  transform=Affine(0.5, 0, 500000.0, 0, -0.5, 6200000.0), crs="EPSG:32756")
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["diagnose", "--uav", str(tmp_path / "fa.tif"), "--uav",
                                   str(tmp_path / "fb.tif"), "--satellite",
                                   str(tmp_path / "sat.tif"), "--uav-gsd", "0.25", "--dpi",
                                   "40", "--out", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "diagnosis.json").read_text())
    assert "flights_combined.png" in doc["plots"]
    with Image.open(out / "flights_combined.png") as im:
        assert "All flights (combined): fa, fb" in im.info["Title"]
    for f in ("fa", "fb"):
        d = doc["flights"][f]["dir"]
        with Image.open(out / d / "mismatch_maps.png") as im:
            assert im.info["Title"] == f"Mismatch maps, flight {f}"
            assert im.size == (640, 184)   # 16 × 4.6 in at --dpi 40
    with Image.open(out / "mismatch_maps.png") as im:   # the reference flight's copy
        assert im.info["Title"] == "Mismatch maps, flight fa"
    report = (out / "report.md").read_text()
    assert "![flights_combined.png](flights_combined.png)" in report
    assert f"]({doc['flights']['fb']['dir']}/mismatch_maps.png)" in report
    assert json.loads((out / "run.json").read_text())["steps"]["diagnose_images"][
        "options"]["dpi"] == 40
