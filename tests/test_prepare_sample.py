"""End-to-end preparation: synthetic flights with known georeference errors, and the sample site.

Truth never comes from the code under test: flights are resampled from one "world"
texture with known map-space errors of their stated georeference, and bright
features sit at known world positions.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import geopandas as gpd
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from rasterio.windows import Window
from scipy import ndimage
from shapely.geometry import box

from geosim.cli.main import cli
from geosim.errors import AlignmentError, ExtentError
from geosim.prepare.alignment import (
    correction_affine,
    correction_from_matrix,
    window_to_grid_matrix,
)
from geosim.prepare.grid import SiteGrid

WORLD_T = Affine(0.05, 0.0, 300000.0, 0.0, -0.05, 6200060.0)   # world raster, EPSG:32756
WORLD_PX = 1200


def similarity_about(cx: float, cy: float, *, rotation_deg: float, scale: float,
                     shift: tuple[float, float]) -> Affine:
    """Map-space similarity: rotate CCW / scale about (cx, cy), then shift (metres)."""
    return (Affine.translation(cx + shift[0], cy + shift[1]) @ Affine.rotation(rotation_deg)
            @ Affine.scale(scale) @ Affine.translation(-cx, -cy))


def world_image(seed: int = 0) -> np.ndarray:
    """(3, WORLD_PX, WORLD_PX) uint8 multi-scale texture with bright blobs on a lattice."""
    rng = np.random.default_rng(seed)
    acc = np.zeros((WORLD_PX, WORLD_PX), np.float32)
    for sigma, weight in ((1.5, 0.4), (5.0, 0.6), (20.0, 1.0)):
        acc += weight * sigma * cv2.GaussianBlur(
            rng.standard_normal((WORLD_PX, WORLD_PX)).astype(np.float32), (0, 0), sigma)
    grey = 110 + 30 * (acc - acc.mean()) / acc.std()
    return np.clip(np.stack([grey, grey * 0.95 + 8, grey * 0.8 + 10]), 1, 254).astype(np.uint8)


def write_flight(path: Path, world: np.ndarray, stated: Affine, error: Affine, size: int,
                 *, crs: str = "EPSG:32756", world_t: Affine = WORLD_T) -> None:
    """A flight whose file states ``stated`` while its pixels show the world at
    ``error⁻¹(stated(c, r))``: its stated georeference is displaced by ``error``."""
    # flight pixel centre → world pixel centre (both centre-at-integer for cv2)
    m = (Affine.translation(-0.5, -0.5) @ ~world_t @ ~error @ stated
         @ Affine.translation(0.5, 0.5))
    mat = np.array([[m.a, m.b, m.c], [m.d, m.e, m.f]])
    bands = [cv2.warpAffine(world[b], mat, (size, size), flags=cv2.INTER_CUBIC
                            | cv2.WARP_INVERSE_MAP, borderValue=0) for b in range(3)]
    ones = cv2.warpAffine(np.ones(world.shape[1:], np.uint8), mat, (size, size),
                          flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=0)
    img = np.stack(bands)
    alpha = (ones * 255).astype(np.uint8)
    with rasterio.open(path, "w", driver="GTiff", width=size, height=size, count=4,
                       dtype="uint8", crs=crs, transform=stated, photometric="RGB",
                       alpha="YES") as dst:
        dst.write(np.concatenate([img, alpha[None]]))


# --------------------------------------------------------------------------- pure


def test_correction_round_trip_with_known_similarity():
    grid_t = Affine(0.05, 0.0, 300000.0, 0.0, -0.05, 6200000.0)
    win = Window(400, 300, 512, 512)
    center = grid_t @ (400 + 256, 300 + 256)
    true_c = similarity_about(*center, rotation_deg=0.37, scale=1.0012, shift=(0.41, -0.23))
    # the kernel's matrix: reference window pixel → moving window pixel (centres at integers)
    g = np.array(list(grid_t)[:6] + [0, 0, 1.0]).reshape(3, 3)
    c = np.array(list(true_c)[:6] + [0, 0, 1.0]).reshape(3, 3)
    m_grid = np.linalg.inv(g) @ np.linalg.inv(c) @ g
    k = np.array([[1, 0, 400.5], [0, 1, 300.5], [0, 0, 1.0]])
    m_win = (np.linalg.inv(k) @ m_grid @ k)[:2]
    entry = correction_from_matrix(m_win, win, grid_t)
    assert entry["shift_m"] == pytest.approx([0.41, -0.23], abs=1e-6)
    assert entry["rotation_deg"] == pytest.approx(0.37, abs=1e-7)
    assert entry["scale"] == pytest.approx(1.0012, abs=1e-9)
    assert entry["center_m"] == pytest.approx(list(center))
    assert correction_affine(entry).almost_equals(true_c, precision=1e-6)
    np.testing.assert_allclose(window_to_grid_matrix(m_win, win), m_grid, atol=1e-9)
    # via the window + grid instead of center_m
    grid = SiteGrid(crs=rasterio.crs.CRS.from_epsg(32756), uav_transform=grid_t,
                    uav_shape=(2000, 2000), sat_transform=grid_t @ Affine.scale(10),
                    sat_shape=(200, 200))
    e2 = {k: v for k, v in entry.items() if k != "center_m"}
    e2["window"] = {"col_off": 400, "row_off": 300, "width": 512, "height": 512}
    assert correction_affine(e2, grid).almost_equals(true_c, precision=1e-6)
    # a pure shift moves every point by shift_m; a CCW rotation turns east into north-east
    pure = correction_affine({"center_m": [10.0, 20.0], "shift_m": [1.5, -2.0],
                              "rotation_deg": 0.0, "scale": 1.0})
    assert pure @ (3.0, 4.0) == pytest.approx((4.5, 2.0))
    rot = correction_affine({"center_m": [0.0, 0.0], "shift_m": [0.0, 0.0],
                             "rotation_deg": 90.0, "scale": 2.0})
    assert rot @ (1.0, 0.0) == pytest.approx((0.0, 2.0))


def test_aligned_and_registration_windows():
    from shapely.geometry import Polygon

    from geosim.prepare.alignment import aligned_window, registration_window
    from geosim.prepare.grid import snap_grid

    grid = snap_grid((0.0, 0.0, 100.0, 100.0), rasterio.crs.CRS.from_epsg(32756),
                     uav_gsd_m=0.05, sat_gsd_m=0.5)
    common = box(10.03, 20.01, 60.02, 90.0)
    aw = aligned_window(common, grid)
    # bbox → pixels [200.6, 1000.4] cols, [200, 1599.8] rows, grown to multiples of 10
    assert (aw.col_off, aw.row_off, aw.width, aw.height) == (200, 200, 1010, 1400)
    rw = registration_window(common, grid, aw, 512)
    assert (rw.width, rw.height) == (512, 512)
    assert (rw.col_off + 256, rw.row_off + 256) == (705, 900)       # central window
    # an L-shaped extent whose bbox centre is outside it: the window moves inside
    ell = Polygon([(0, 0), (100, 0), (100, 20), (20, 20), (20, 100), (0, 100)])
    aw = aligned_window(ell, grid)
    rw = registration_window(ell, grid, aw, 300)
    x0, y0 = grid.uav_transform @ (rw.col_off, rw.row_off)
    x1, y1 = grid.uav_transform @ (rw.col_off + rw.width, rw.row_off + rw.height)
    win_box = box(x0, y1, x1, y0)
    assert ell.intersection(win_box).area > 0.9 * win_box.area


# --------------------------------------------------------------------------- synthetic site


def blob_world_points() -> list[tuple[float, float]]:
    return [(300012.0 + 9 * i, 6200045.0 - 8 * j) for i in range(4) for j in range(4)]


def add_blobs(world: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[0:WORLD_PX, 0:WORLD_PX]
    out = world.astype(np.float32)
    for x, y in blob_world_points():
        c, r = ~WORLD_T @ (x, y)
        out += 120 * np.exp(-((xx - c + 0.5) ** 2 + (yy - r + 0.5) ** 2) / (2 * 2.5 ** 2))
    return np.clip(out, 0, 255).astype(np.uint8)


ERRORS = {   # stated georeference = error(true), about the site centre
    "F1": dict(rotation_deg=0.0, scale=1.0, shift=(0.0, 0.0)),
    "F2": dict(rotation_deg=0.4, scale=1.002, shift=(0.63, -0.41)),
    "F3": dict(rotation_deg=-0.25, scale=0.9985, shift=(-0.37, 0.52)),
}
CENTER = (300030.0, 6200030.0)


@pytest.fixture(scope="module")
def synthetic_site(tmp_path_factory):
    d = tmp_path_factory.mktemp("synsite")
    world = add_blobs(world_image())
    (d / "flights").mkdir()
    for i, (fid, err) in enumerate(ERRORS.items()):
        error = similarity_about(*CENTER, **err)
        stated = Affine(0.05, 0.0, 300003.0 + 1.1 * i, 0.0, -0.05, 6200057.0 - 0.7 * i)
        write_flight(d / "flights" / f"{fid}.tif", world, stated, error, 1000)
    toml = ['[site]', 'name = "synthetic"', 'crs = "EPSG:32756"', 'reference_flight = "F1"',
            '[parameters]', 'tile_px = 300', 'align_window_px = 512']
    for i, fid in enumerate(ERRORS):
        toml += ["[[flights]]", f'id = "{fid}"', f'image = "flights/{fid}.tif"',
                 f'acquired = "2021-07-1{5 + i}T11:00:00+10:00"']
    (d / "site.toml").write_text("\n".join(toml) + "\n")
    out = d / "run"
    res = CliRunner().invoke(cli, ["prepare", str(d / "site.toml"), "--out", str(out)])
    assert res.exit_code == 0, res.output + str(res.exception)
    return d, out


def test_synthetic_corrections_match_truth(synthetic_site):
    _d, out = synthetic_site
    doc = json.loads((out / "alignment.json").read_text())
    assert doc["reference"] == "F1"
    ref_error = similarity_about(*CENTER, **ERRORS["F1"])
    for fid, err in ERRORS.items():
        entry = doc["flights"][fid]
        corr = correction_affine(entry)
        truth = ref_error @ ~similarity_about(*CENTER, **err)   # stated(F) → stated(F1)
        # every blob's stated position in F maps to its stated position in F1
        for w in blob_world_points():
            p_f = similarity_about(*CENTER, **err) @ w
            got = corr @ p_f
            want = ref_error @ w
            assert math.hypot(got[0] - want[0], got[1] - want[1]) < 0.02, (fid, w)
        t_rot = math.degrees(math.atan2(truth.d, truth.a))
        t_scale = math.sqrt(abs(truth.determinant))
        assert entry["rotation_deg"] == pytest.approx(t_rot, abs=0.01)
        assert entry["scale"] == pytest.approx(t_scale, rel=1e-4)
        c = entry["center_m"]
        tc = truth @ c
        assert entry["shift_m"] == pytest.approx([tc[0] - c[0], tc[1] - c[1]], abs=0.01)
        assert entry["confidence"] > 0.3
    for fid, stats in doc["local_check"].items():
        assert stats["median_shift_px"] < 0.5, fid


def blob_centroid_m(path: Path, xy: tuple[float, float]) -> tuple[float, float]:
    """Map position of the intensity centroid of the bright blob near ``xy``."""
    with rasterio.open(path) as ds:
        c, r = ~ds.transform @ xy
        win = Window(int(c) - 8, int(r) - 8, 17, 17)
        g = ds.read(1, window=win).astype(float)
        t = ds.window_transform(win)
    wgt = np.clip(g - (g.max() - 70), 0, None)
    cy, cx = ndimage.center_of_mass(wgt)
    return t @ (cx + 0.5, cy + 0.5)


def test_synthetic_aligned_outputs(synthetic_site):
    _d, out = synthetic_site
    grid = SiteGrid.from_dict(json.loads((out / "grid" / "grid.json").read_text()))
    doc = json.loads((out / "alignment.json").read_text())
    at = Affine(*doc["aligned_grid"]["transform"])
    aw = doc["aligned_grid"]["window_px"]
    assert at == grid.uav_transform @ Affine.translation(aw["col_off"], aw["row_off"])
    assert aw["col_off"] % grid.phi == 0 and aw["row_off"] % grid.phi == 0
    # blobs land where the reference flight's own file (written by this test) shows them
    ref_error = similarity_about(*CENTER, **ERRORS["F1"])
    points = [ref_error @ w for w in blob_world_points()]
    want = [blob_centroid_m(_d / "flights" / "F1.tif", p) for p in points]
    # no whole-flight aligned rasters (keep_intermediates = false): the tiles, resampled
    # once from the original flights, are the aligned product
    assert not (out / "aligned").exists()
    checked = 0
    for fid in ERRORS:
        for tile in sorted((out / "tiles" / fid).glob("*.tif")):
            with rasterio.open(tile) as ds:
                assert ds.crs.to_epsg() == 32756
                c0, r0 = ~at @ (ds.transform.c, ds.transform.f)   # whole aligned pixels
                assert (c0, r0) == (round(c0), round(r0)) and ds.transform.a == at.a
                inner = [p for p in points if 10 <= (~ds.transform @ p)[0] < ds.width - 10
                         and 10 <= (~ds.transform @ p)[1] < ds.height - 10]
            for p in inner:
                wx, wy = want[points.index(p)]
                gx, gy = blob_centroid_m(tile, p)
                assert math.hypot(gx - wx, gy - wy) < 0.5 * 0.05, (fid, tile.name, p)  # 0.5 px
                checked += 1
    assert checked >= 3 * 5
    # outputs readable with the right CRS
    for name in ("footprints.geojson", "common_extent.geojson", "tiles/index.geojson",
                 "alignment_check.geojson"):
        assert gpd.read_file(out / name).crs.to_epsg() == 4326, name
    for name in ("footprints.gpkg", "common_extent.gpkg", "tiles/index.gpkg"):
        assert gpd.read_file(out / name).crs.to_epsg() == 32756, name
    fp = gpd.read_file(out / "footprints.gpkg")
    # rotated flights: footprints are traced polygons, area ≈ 50 m × 50 m
    assert (fp["area_m2"] - 2500).abs().max() < 40
    tiles = sorted((out / "tiles" / "F1").glob("*.tif"))
    assert tiles and (out / "pairs.csv").read_text().count("\n") == 1 + 3 * len(tiles)
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "ok" and set(run["steps"]) == {"grid", "footprints", "align",
                                                           "tiles", "pairs"}


def test_cli_reports_disjoint_flights(tmp_path):
    world = world_image(3)[:, :400, :400]
    (tmp_path / "f").mkdir()
    ident = Affine.identity()
    write_flight(tmp_path / "f" / "A.tif", np.pad(world, ((0, 0), (0, 800), (0, 800))),
                 WORLD_T, ident, 300)
    far = Affine(0.05, 0, 300500.0, 0, -0.05, 6200060.0)
    write_flight(tmp_path / "f" / "B.tif", np.pad(world, ((0, 0), (0, 800), (0, 800))),
                 far, Affine.translation(500.0, 0.0), 300)
    (tmp_path / "s.toml").write_text(
        '[[flights]]\nid = "A"\nimage = "f/A.tif"\nacquired = "2021-01-01T00:00:00"\n'
        '[[flights]]\nid = "B"\nimage = "f/B.tif"\nacquired = "2021-01-02T00:00:00"\n')
    res = CliRunner().invoke(cli, ["grid", str(tmp_path / "s.toml"), "--out",
                                   str(tmp_path / "o")])
    assert res.exit_code == 2
    assert "A∩B" in res.output and "common extent" in res.output
    assert isinstance(ExtentError("x"), ValueError) and issubclass(AlignmentError, RuntimeError)


# --------------------------------------------------------------------------- real imagery


def test_sjer_known_transform_recovered_across_seasons(realdata, tmp_path):
    """A 2018 (dry) tile with a known georeference error, registered against 2017 (green).

    The two years are themselves misregistered by a few pixels (unknown truth), so the
    site holds the 2018 tile twice — as is, and with the known error — and the test
    checks that the two corrections differ by exactly that error:
    ``C_error = C_asis ∘ error⁻¹``.
    """
    from geosim.config import FlightConfig, Parameters, SiteConfig
    from geosim.prepare.steps import run_align, run_footprints, run_grid

    name = "SJER_021.tif"
    with rasterio.open(realdata / "sjer_2018" / name) as ds:
        img18, t18, crs = ds.read(), ds.transform, ds.crs.to_string()
    centre = t18 @ (200, 200)
    error = similarity_about(*centre, rotation_deg=0.6, scale=1.006, shift=(0.55, -0.35))
    write_flight(tmp_path / "y2018e.tif", img18, t18, error, 400, crs=crs, world_t=t18)
    acq = __import__("datetime").datetime(2018, 1, 1)
    site = SiteConfig(
        path=None, name="sjer", crs="auto", reference_flight="y2017",
        flights=(FlightConfig("y2017", realdata / "sjer_2017" / name, acq),
                 FlightConfig("y2018", realdata / "sjer_2018" / name, acq),
                 FlightConfig("y2018e", tmp_path / "y2018e.tif", acq)),
        parameters=Parameters(uav_gsd_m=0.1, sat_gsd_m=0.5, tile_px=100, align_window_px=320))
    out = tmp_path / "run"
    run_grid(site, out)
    run_footprints(site, out)
    run_align(site, out)
    flights = json.loads((out / "alignment.json").read_text())["flights"]
    got = correction_affine(flights["y2018e"])
    want = correction_affine(flights["y2018"]) @ ~error
    c = flights["y2018e"]["center_m"]
    shift_err_m = math.dist(got @ c, want @ c)
    rot_err_deg = abs(math.degrees(math.atan2(got.d, got.a) - math.atan2(want.d, want.a)))
    scale_err = abs(math.sqrt(got.determinant / want.determinant) - 1)
    print(f"SJER {name}: shift error {shift_err_m * 100:.2f} cm, rotation error "
          f"{rot_err_deg:.4f}°, scale error {scale_err * 100:.4f} %, confidence "
          f"{flights['y2018e']['confidence']:.2f} (as is: {flights['y2018']['confidence']:.2f}, "
          f"natural 2017→2018 shift {flights['y2018']['shift_m']} m)")
    assert shift_err_m < 0.02                  # 0.2 px at 0.1 m
    assert rot_err_deg < 0.05
    assert scale_err < 0.0005


# --------------------------------------------------------------------------- the sample site


@pytest.fixture(scope="module")
def sample_run(samples_dir, tmp_path_factory):
    import dataclasses

    from geosim.config import load_site
    from geosim.prepare.steps import run_align, run_footprints, run_grid, run_pairs, run_tiles

    site = load_site(samples_dir / "site.toml")
    params = dataclasses.replace(site.parameters, tile_px=500,
                                 align_window_px=min(site.parameters.align_window_px, 1024))
    site = dataclasses.replace(site, parameters=params)
    out = tmp_path_factory.mktemp("sample") / "run"
    for step in (run_grid, run_footprints, run_align, run_tiles, run_pairs):
        step(site, out)
    truth = json.loads((samples_dir / "truth.json").read_text())
    return site, out, truth


def _truth_flights(truth: dict) -> dict:
    flights = truth.get("flights", truth)
    return flights if isinstance(flights, dict) else {f["id"]: f for f in flights}


def test_sample_site_transforms_match_truth(sample_run):
    """Recovered corrections vs truth.json: translation ≤ 0.10 m, rotation ≤ 0.05°,
    scale ≤ 0.05 %.

    truth.json gives each flight's ``stated_to_true`` S (EPSG:28356). A ground point
    stated at p_f by flight f is stated at S_ref⁻¹ S_f p_f by the reference, so the
    true correction is ``S_ref⁻¹ ∘ S_f``; it is compared in EPSG:28356 after moving
    points there from the site CRS with pyproj.
    """
    from pyproj import Transformer

    site, out, truth = sample_run
    doc = json.loads((out / "alignment.json").read_text())
    tflights = _truth_flights(truth)
    grid = SiteGrid.from_dict(json.loads((out / "grid" / "grid.json").read_text()))
    to_t = Transformer.from_crs(grid.crs.to_wkt(), "EPSG:28356", always_xy=True)
    from_t = Transformer.from_crs("EPSG:28356", grid.crs.to_wkt(), always_xy=True)

    def s2t(fid: str) -> Affine:
        (a, b, c), (d, e, f) = tflights[fid]["georef_error"]["stated_to_true"]
        return Affine(a, b, c, d, e, f)

    ref = doc["reference"]
    report = []
    for fid, entry in doc["flights"].items():
        got = correction_affine(entry)
        true_c = ~s2t(ref) @ s2t(fid)
        cx, cy = entry["center_m"]
        # three points 25 m apart around the window centre, through the true correction
        pts = [(cx, cy), (cx + 25.0, cy), (cx, cy + 25.0)]
        moved = []
        for x, y in pts:
            tx, ty = to_t.transform(x, y)
            moved.append(from_t.transform(*(true_c @ (tx, ty))))
        shift_err = math.dist(got @ pts[0], moved[0])
        ang_true = math.atan2(moved[1][1] - moved[0][1], moved[1][0] - moved[0][0])
        gx = got @ pts[1]
        g0 = got @ pts[0]
        ang_got = math.atan2(gx[1] - g0[1], gx[0] - g0[0])
        rot_err = abs(math.degrees(ang_got - ang_true))
        scale_true = math.dist(moved[0], moved[2]) / 25.0
        scale_err = abs(entry["scale"] / scale_true - 1)
        report.append((fid, shift_err, rot_err, scale_err, entry["confidence"]))
        assert shift_err <= 0.10, report
        assert rot_err <= 0.05, report
        assert scale_err <= 0.0005, report
    print("\n".join(f"{fid}: translation error {s * 100:.2f} cm, rotation error {r:.4f}°, "
                    f"scale error {k * 100:.4f} %, confidence {c:.2f}"
                    for fid, s, r, k, c in report))


def test_sample_site_overlay_and_outputs(sample_run):
    site, out, _truth = sample_run
    doc = json.loads((out / "alignment.json").read_text())
    for fid, stats in doc["local_check"].items():
        assert stats["n_confident"] >= 4, fid
        assert stats["median_shift_px"] <= 2.0, (fid, stats)
    # every output readable with the right CRS
    grid = SiteGrid.from_dict(json.loads((out / "grid" / "grid.json").read_text()))
    for p in [*(out / "grid").glob("*.tif"), *(out / "aligned").glob("*.tif"),
              *(out / "tiles").glob("*/*.tif")]:
        with rasterio.open(p) as ds:
            assert ds.crs == grid.crs, p
    for name in ("footprints.geojson", "common_extent.geojson", "tiles/index.geojson"):
        assert gpd.read_file(out / name).crs.to_epsg() == 4326
    at = Affine(*doc["aligned_grid"]["transform"])
    ids: dict[str, set] = {}
    for p in (out / "tiles").glob("*/*.tif"):
        row, col = int(p.stem[1:4]), int(p.stem[6:9])
        with rasterio.open(p) as ds:
            assert ds.transform == at @ Affine.translation(col * 500, row * 500)
            ids.setdefault(p.stem, set()).add(tuple(ds.bounds))
    assert ids and all(len(b) == 1 for b in ids.values())
    fp = gpd.read_file(out / "footprints.gpkg")
    flights = fp[fp["kind"] == "flight"]
    assert (flights["area_m2"] < 0.98 * flights["bbox_area_m2"]).all()   # traced, not boxes
