"""The committed sample site against its own truth, and the generator's reproducibility.

Truth here is what ``truth.json`` states and what GDAL / geopandas read back
from the files; geometric checks recompute the georeferencing error with numpy
from its parameters rather than with the generator's code.
"""

from __future__ import annotations

import datetime as dt
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
from rasterio.enums import ColorInterp, Resampling
from rasterio.warp import reproject
from shapely.geometry import LineString, Point

from geosim.io.raster import read_valid_mask
from geosim.samples.render_grid import LocalWarp, rotation_scale_about
from geosim.samples.sun import solar_position

FLIGHTS = ("PA1", "PA2", "PA3")
EFFECT_PARAMS = {
    "optics": {"q"},
    "detector_integration": {"pitch_px"},
    "atmospheric_blur": {"f0_cyc_per_px"},
    "motion_smear": {"length_px", "direction_deg"},
    "haze": {"transmission", "path_radiance_dn"},
    "sensor_noise": {"gain_dn", "read_var_dn2"},
    "misregistration": {"shift_m"},
}


@pytest.fixture(scope="module")
def truth(samples_dir: Path) -> dict:
    return json.loads((samples_dir / "truth.json").read_text())


@pytest.fixture(scope="module")
def masks(samples_dir: Path) -> dict[str, tuple[np.ndarray, Affine]]:
    out = {}
    for fid in FLIGHTS:
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            out[fid] = (read_valid_mask(ds), ds.transform)
    return out


# --------------------------------------------------------------------- files as stated


def test_flights_crs_transform_and_layout(samples_dir: Path, truth: dict) -> None:
    for fid in FLIGHTS:
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            assert ds.crs.to_epsg() == 28356
            t = ds.transform
            assert (t.a, t.b, t.d, t.e) == (0.05, 0.0, 0.0, -0.05)
            assert list(t)[:6] == truth["flights"][fid]["stated_transform"]
            assert (ds.width, ds.height) == (truth["flights"][fid]["width"],
                                             truth["flights"][fid]["height"])
            assert 1500 <= ds.width <= 2400 and 1500 <= ds.height <= 2400  # ~100 m at 5 cm
            assert ds.dtypes[0] == "uint8"
            assert ds.profile["tiled"] and ds.compression.value.lower() == "deflate"
            assert ds.tags()["GEOSIM_STEP"] == "samples"


def test_satellite_crs_transform(samples_dir: Path, truth: dict) -> None:
    with rasterio.open(samples_dir / "satellite" / "satellite.tif") as ds:
        assert ds.crs.to_epsg() == 32756
        t = ds.transform
        assert (t.a, t.b, t.d, t.e) == (0.5, 0.0, 0.0, -0.5)
        assert t.c % 0.5 == 0 and t.f % 0.5 == 0
        assert ds.count == 3 and ds.dtypes[0] == "uint8"
        assert ds.width * 0.5 >= 150 and ds.height * 0.5 >= 150  # larger than the flights
        assert list(t)[:6] == truth["satellite"]["transform"]
        bounds = ds.bounds
    # Every flight lies inside the scene (EPSG:28356 and 32756 coincide here to < 1 m).
    for fid in FLIGHTS:
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            b = ds.bounds
        assert bounds.left < b.left and b.right < bounds.right
        assert bounds.bottom < b.bottom and b.top < bounds.top


def test_mask_encodings(samples_dir: Path, masks: dict) -> None:
    with rasterio.open(samples_dir / "flights" / "PA1.tif") as ds:
        assert ds.count == 4 and ds.colorinterp[3] == ColorInterp.alpha
        assert set(np.unique(ds.read(4))) == {0, 255}
    with rasterio.open(samples_dir / "flights" / "PA2.tif") as ds:
        assert ds.count == 3 and ds.nodata == 0
        rgb = ds.read()
        valid = masks["PA2"][0]
        assert (rgb[:, valid] > 0).all()          # no valid pixel has a 0 in any band
        assert (rgb[:, ~valid] == 0).all()
    with rasterio.open(samples_dir / "flights" / "PA3.tif") as ds:
        assert ds.count == 3 and ds.nodata is None
        assert all(ColorInterp.alpha != c for c in ds.colorinterp)
        assert ds.mask_flag_enums[0] == [rasterio.enums.MaskFlags.per_dataset]


def test_footprints_differ_and_overlap(masks: dict, truth: dict) -> None:
    # Valid masks on a common 0.25 m grid (nearest), by GDAL.
    common = Affine(0.25, 0, 255050.0, 0, -0.25, 6184960.0)
    on_grid = {}
    for fid, (mask, t) in masks.items():
        assert int(mask.sum()) == truth["flights"][fid]["valid_pixels"]
        assert 0.6 < mask.mean() < 0.97           # irregular, not the whole rectangle
        dst = np.zeros((720, 720), dtype=np.uint8)
        reproject(mask.astype(np.uint8), dst, src_transform=t, src_crs="EPSG:28356",
                  dst_transform=common, dst_crs="EPSG:28356", resampling=Resampling.nearest)
        on_grid[fid] = dst.astype(bool)
    areas = {fid: m.sum() * 0.0625 for fid, m in on_grid.items()}
    for a in areas.values():
        assert 5000 < a < 10000                   # ~85 m × 85 m of data
    vals = sorted(areas.values())
    assert min(b - a for a, b in zip(vals, vals[1:], strict=False)) > 20.0  # m², all differ
    all3 = on_grid["PA1"] & on_grid["PA2"] & on_grid["PA3"]
    for m in on_grid.values():
        assert all3.sum() / m.sum() > 0.6         # most of every flight is common
    for a, b in (("PA1", "PA2"), ("PA1", "PA3"), ("PA2", "PA3")):
        iou = (on_grid[a] & on_grid[b]).sum() / (on_grid[a] | on_grid[b]).sum()
        assert iou < 0.95                         # shapes differ


# --------------------------------------------------------------------- georeferencing


def _matrix(shift, rot_deg, scale, centre) -> np.ndarray:
    t = math.radians(rot_deg)
    r = scale * np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    c = np.asarray(centre)
    return np.c_[r, c + np.asarray(shift) - r @ c]


def test_georef_error_in_range_and_consistent(truth: dict) -> None:
    shifts = []
    for fid in FLIGHTS:
        f = truth["flights"][fid]
        e = f["georef_error"]
        assert 0.0 < math.hypot(*e["shift_m"]) <= 1.5
        assert 0.0 < abs(e["rotation_deg"]) <= 0.5
        assert 0.0 < abs(e["scale"] - 1.0) <= 0.005
        s = f["stated_transform"]
        centre = (s[2] + s[0] * f["width"] / 2, s[5] + s[4] * f["height"] / 2)
        assert np.allclose(e["about_stated_xy"], centre, atol=1e-6)
        m = _matrix(e["shift_m"], e["rotation_deg"], e["scale"], centre)
        assert np.allclose(m, e["stated_to_true"], atol=1e-6)
        inv = np.linalg.inv(np.vstack([m, [0, 0, 1]]))[:2]
        assert np.allclose(inv, e["true_to_stated"], atol=1e-6)
        true_t = np.vstack([m, [0, 0, 1]]) @ np.array([[s[0], s[1], s[2]], [s[3], s[4], s[5]],
                                                       [0, 0, 1]])
        assert np.allclose(true_t[:2].ravel(), f["true_transform"], atol=1e-6)
        shifts.append(tuple(e["shift_m"]))
    assert len(set(shifts)) == 3


def test_rotation_scale_about_matches_numpy() -> None:
    a = rotation_scale_about((100.0, 200.0), rotation_deg=0.3, scale=1.004, shift_xy=(1.0, -0.5))
    m = _matrix((1.0, -0.5), 0.3, 1.004, (100.0, 200.0))
    assert np.allclose([[a.a, a.b, a.c], [a.d, a.e, a.f]], m)
    assert np.allclose(a @ (100.0, 200.0), (101.0, 199.5))  # the centre only shifts


def test_images_follow_the_true_georeference(samples_dir: Path, truth: dict) -> None:
    """Resampling PA2 and PA3 into PA1's pixels through the *true* mappings aligns
    the ground texture to a fraction of a pixel; the stated transforms alone do not."""
    def grey(fid: str) -> tuple[np.ndarray, Affine]:
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            img = ds.read([1, 2, 3]).astype(np.float32)
            return cv2.cvtColor(np.ascontiguousarray(img.transpose(1, 2, 0)),
                                cv2.COLOR_RGB2GRAY), ds.transform

    ref, ref_t = grey("PA1")
    t1 = Affine(*truth["flights"]["PA1"]["true_transform"])
    r0, c0, n = ref.shape[0] // 2 - 256, ref.shape[1] // 2 - 256, 512
    win = ref[r0:r0 + n, c0:c0 + n]
    hann = cv2.createHanningWindow((n, n), cv2.CV_32F)
    for fid in ("PA2", "PA3"):
        img, stated = grey(fid)
        ti = Affine(*truth["flights"][fid]["true_transform"])
        for mapping, expect_aligned in ((~ti @ t1, True), (~stated @ ref_t, False)):
            m = mapping @ Affine.translation(c0, r0)
            warped = cv2.warpAffine(img, np.array([[m.a, m.b, m.c], [m.d, m.e, m.f]]), (n, n),
                                    flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
            # OpenCV 5 multiplies its inputs by the window in place: pass copies (win is reused)
            (dx, dy), _ = cv2.phaseCorrelate(win.copy(), warped.copy(), hann)
            if expect_aligned:
                assert math.hypot(dx, dy) < 0.5, (fid, dx, dy)
            else:
                assert math.hypot(dx, dy) > 5.0, (fid, dx, dy)


def test_exposure_seams_are_in_the_images(samples_dir: Path, truth: dict, masks: dict) -> None:
    """Across each flight's seam line, brightness steps by the recorded gain."""
    for fid in FLIGHTS:
        seam = truth["flights"][fid]["artefacts"]["exposure_seam"]
        mask = masks[fid][0]
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            grey = ds.read([1, 2, 3]).astype(np.float32).mean(axis=0)
        p0 = np.array(seam["p0_px"])
        d = np.array(seam["p1_px"]) - p0
        length = float(np.hypot(*d))
        d /= length
        left = np.array([d[1], -d[0]])  # left of p0 -> p1 with rows growing downwards
        t = np.linspace(0.0, length, 20000)
        sides = {}
        for sign in (1, -1):
            vals = []
            for k in range(3, 13):
                c, r = (p0[:, None] + d[:, None] * t + sign * k * left[:, None]).astype(int)
                ok = (c >= 0) & (c < grey.shape[1]) & (r >= 0) & (r < grey.shape[0])
                ok[ok] &= mask[r[ok], c[ok]]
                vals.append(grey[r[ok], c[ok]])
            sides[sign] = np.concatenate(vals)
        ratio = np.median(sides[1]) / np.median(sides[-1])
        assert abs(ratio - seam["gain_left"]) < 0.04, (fid, ratio, seam["gain_left"])


# --------------------------------------------------------------------- cattle and labels


def test_cattle_counts_sizes_and_movement(truth: dict) -> None:
    ids = []
    for fid in FLIGHTS:
        cattle = truth["flights"][fid]["cattle"]
        assert 20 <= len(cattle) <= 40 and truth["flights"][fid]["n_cattle"] == len(cattle)
        for c in cattle:
            assert 2.0 <= c["length_m"] <= 2.6 and 0.7 <= c["width_m"] <= 1.0
            c0, r0, c1, r1 = c["box_px"]
            sides_m = sorted(((c1 - c0) * 0.05, (r1 - r0) * 0.05))
            assert sides_m[0] >= c["width_m"] - 0.02      # a box holds the whole animal
            assert sides_m[1] <= c["length_m"] + 0.02
            assert math.hypot(*sides_m) >= c["length_m"] * 0.95
        ids.append({c["id"]: c for c in cattle})
    for prev, cur in zip(ids, ids[1:], strict=False):
        common = set(prev) & set(cur)
        moved = [i for i in common if math.dist(prev[i]["centre_xy"], cur[i]["centre_xy"]) > 1.0]
        stayed = [i for i in common if math.dist(prev[i]["centre_xy"], cur[i]["centre_xy"]) < 0.01]
        assert len(moved) >= 5 and len(stayed) >= 3
        assert all(cur[i]["moved_since_previous_flight"] for i in moved)
        assert not any(cur[i]["moved_since_previous_flight"] for i in stayed)
    coats = {c["coat"] for f in FLIGHTS for c in truth["flights"][f]["cattle"]}
    assert len(coats) >= 4


def _yolo_centres(path: Path, transform: Affine, width: int, height: int) -> np.ndarray:
    pts = []
    for line in path.read_text().splitlines():
        cls, cx, cy, w, h = line.split()
        assert cls == "0" and all(len(v.split(".")[1]) == 6 for v in (cx, cy, w, h))
        pts.append(transform @ (float(cx) * width, float(cy) * height))
    return np.array(pts)


def _match(found: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """Distance from each expected point to its nearest found point (one-to-one check)."""
    d = np.hypot(found[:, None, 0] - expected[None, :, 0], found[:, None, 1] - expected[None, :, 1])
    nearest = d.argmin(axis=0)
    assert len(set(nearest.tolist())) == len(expected)
    return d.min(axis=0)


def test_yolo_labels_agree_with_truth(samples_dir: Path, truth: dict) -> None:
    for fid in ("PA1", "PA2"):
        folder = samples_dir / "labels" / fid
        assert (folder / "classes.txt").read_text().split() == ["cattle"]
        with rasterio.open(samples_dir / "flights" / f"{fid}.tif") as ds:
            centres = _yolo_centres(folder / f"{fid}.txt", ds.transform, ds.width, ds.height)
        expected = np.array([c["centre_stated_xy"] for c in truth["flights"][fid]["cattle"]])
        assert len(centres) == len(expected)
        assert _match(centres, expected).max() < 2 * 0.05   # within 2 px


def test_geojson_labels_agree_with_truth(samples_dir: Path, truth: dict) -> None:
    gdf = gpd.read_file(samples_dir / "labels" / "PA3.geojson")
    assert gdf.crs.to_epsg() == 4326 and set(gdf["class"]) == {"cattle"}
    boxes = gdf.to_crs("EPSG:28356")
    centres = np.array([[g.centroid.x, g.centroid.y] for g in boxes.geometry])
    cattle = truth["flights"]["PA3"]["cattle"]
    expected = np.array([c["centre_stated_xy"] for c in cattle])
    assert len(centres) == len(expected)
    assert _match(centres, expected).max() < 2 * 0.05


def test_paddock_counts_by_point_in_polygon(samples_dir: Path, truth: dict) -> None:
    paddocks = gpd.read_file(samples_dir / "paddocks.geojson").to_crs("EPSG:28356")
    assert len(paddocks) >= 2 and paddocks["name"].is_unique
    fences = [LineString(f) for f in truth["world"]["fences"]]
    for key in (*FLIGHTS, "satellite"):
        block = truth["flights"][key] if key != "satellite" else truth["satellite"]
        counts = dict.fromkeys(paddocks["name"], 0)
        for c in block["cattle"]:
            p = Point(c["centre_xy"])
            inside = [n for n, g in zip(paddocks["name"], paddocks.geometry, strict=True)
                      if g.contains(p)]
            assert len(inside) == 1
            counts[inside[0]] += 1
            assert min(f.distance(p) for f in fences) >= 3.0 - 0.3  # box centre vs body point
        assert counts == block["paddock_counts"], key


def test_cattle_well_inside_their_footprints(masks: dict, truth: dict) -> None:
    """Every labelled animal sits ≥ 2 m inside the valid data of its image."""
    r_px = int(2.0 / 0.05)
    yy, xx = np.mgrid[-r_px:r_px + 1, -r_px:r_px + 1]
    disc = xx**2 + yy**2 <= r_px**2
    for fid in FLIGHTS:
        mask, t = masks[fid]
        for c in truth["flights"][fid]["cattle"]:
            col, row = ~t @ tuple(c["centre_stated_xy"])
            col, row = int(col), int(row)
            patch = mask[row - r_px:row + r_px + 1, col - r_px:col + r_px + 1]
            assert patch.shape == disc.shape and patch[disc].all(), (fid, c["id"])


# --------------------------------------------------------------------- satellite truth


def test_satellite_chain_schema_and_magnitudes(truth: dict) -> None:
    sat = truth["satellite"]
    eff = sat["effects"]
    assert set(eff) == set(EFFECT_PARAMS)
    for name, params in EFFECT_PARAMS.items():
        assert set(eff[name]) == params, name
    assert 1.3 <= eff["optics"]["q"] <= 1.7
    assert eff["detector_integration"]["pitch_px"] == 1.0
    assert 0.6 <= eff["motion_smear"]["length_px"] <= 1.0
    assert 0 <= eff["motion_smear"]["direction_deg"] < 180
    t = eff["haze"]["transmission"]
    lp = eff["haze"]["path_radiance_dn"]
    assert 1 > t[0] > t[1] > t[2] > 0 and 0 < lp[0] < lp[1] < lp[2]  # blue strongest
    assert eff["sensor_noise"]["gain_dn"] > 0 and eff["sensor_noise"]["read_var_dn2"] > 0
    assert math.hypot(*eff["misregistration"]["shift_m"]) < 1.5
    assert sat["crs"] == "EPSG:32756" and 20 <= sat["n_cattle"] <= 60


def test_satellite_haze_lifts_shadows(samples_dir: Path) -> None:
    """Path radiance: the darkest satellite pixels are far from 0, bluest highest."""
    with rasterio.open(samples_dir / "satellite" / "satellite.tif") as ds:
        img = ds.read().reshape(3, -1).astype(float)
    dark = np.percentile(img, 0.5, axis=1)
    assert (dark > 5).all() and dark[2] > dark[0]


# --------------------------------------------------------------------- kernels


def test_solar_noon_elevation_and_azimuth() -> None:
    """At local solar noon the sun is due north (southern winter) at 90° − |φ − δ|."""
    aest = dt.timezone(dt.timedelta(hours=10))
    lon, lat = 150.0, -34.0
    times = [dt.datetime(2021, 7, 15, 11, 0, tzinfo=aest) + dt.timedelta(minutes=m)
             for m in range(0, 120)]
    els = [solar_position(t, lon, lat)[1] for t in times]
    noon = times[int(np.argmax(els))]
    az, el = solar_position(noon, lon, lat)
    decl = 21.5  # solar declination on 15 July, degrees (almanac)
    assert abs(el - (90 - abs(lat - decl))) < 0.5
    assert min(az, 360 - az) < 1.0
    # Equation of time in mid-July is about −6 min: noon near 12:06 AEST at 150° E.
    assert abs((noon.hour * 60 + noon.minute) - (12 * 60 + 6)) <= 2


def test_exposure_seam_brightens_the_left_side() -> None:
    from geosim.samples.flights import ExposureSeam

    # A line running east (+col) along row 10: "left" is up (smaller rows).
    f = ExposureSeam(p0_px=(0.0, 10.0), p1_px=(100.0, 10.0), gain=1.1, width_px=2.0).factor(20, 5)
    assert np.allclose(f[:8], 1.1) and np.allclose(f[12:], 1.0)


def test_local_warp_decays_and_peaks() -> None:
    w = LocalWarp(centre_px=(100.0, 100.0), sigma_px=20.0, amplitude_px=4.0,
                  direction_rad=0.0, swirl_px=0.0)
    dc, dr = w.displacement(np.array([100.0, 100.0 + w.reach_px()]), np.array([100.0, 100.0]))
    assert dc[0] == pytest.approx(4.0) and dr[0] == pytest.approx(0.0)
    assert abs(dc[1]) < 0.011


def test_label_box_matches_rendered_animal() -> None:
    """The label box (from the outline geometry) bounds the rendered animal's pixels."""
    from geosim.samples.cattle import Animal, Cow, coverage
    from geosim.samples.labels import box_in_image
    from geosim.samples.render_grid import RenderGrid

    stated = Affine(0.05, 0, 1000.0, 0, -0.05, 2000.0)
    error = rotation_scale_about((1005.0, 1995.0), rotation_deg=0.4, scale=1.004,
                                 shift_xy=(0.7, -0.3))
    grid = RenderGrid(200, 200, error @ stated)
    animal = Animal(id=1, coat="hereford", length_m=2.4, width_m=0.9, body_rgb=(1, 1, 1),
                    face_rgb=None, stripe_rgb=None, sheen_dn=0.0, texture_seed=1)
    for heading, turn in ((0.0, 0.0), (37.0, 25.0), (128.0, -30.0), (260.0, 10.0)):
        cx, cy = grid.pixel_to_map @ (100, 100)
        cow = Cow(animal=animal, x=cx, y=cy, heading_deg=heading, head_turn_deg=turn,
                  grazing=True)
        x, y = grid.coords(0, 200, 0, 200)
        body, head = coverage(cow, grid, x, y)
        rows, cols = np.nonzero(body + head > 0.5)
        c0, r0, c1, r1 = box_in_image(cow.outline(), ~error, stated)
        assert abs(cols.min() - c0) < 1.0 and abs(cols.max() + 1 - c1) < 1.0
        assert abs(rows.min() - r0) < 1.0 and abs(rows.max() + 1 - r1) < 1.0


def test_grid_in_crs_of_the_world_crs_is_the_transform() -> None:
    from geosim.samples.render_grid import grid_in_crs

    t = Affine(0.05, 0, 255000.0, 0, -0.05, 6185000.0)
    g = grid_in_crs("EPSG:28356", t, 100, 80)
    assert np.allclose(list(g.pixel_to_map)[:6], list(t)[:6], atol=1e-6)


# --------------------------------------------------------------------- reproducibility


def test_generator_reproduces_committed_files(samples_dir: Path, tmp_path: Path) -> None:
    """``geosim samples make --seed 0`` writes exactly the committed sample site.

    GeoTIFFs are compared by decoded pixels and masks (file bytes may differ with
    the GDAL version), every other file byte for byte.
    """
    from geosim.cli.main import cli
    from geosim.samples.generate import site_checksums

    committed = json.loads((samples_dir / "checksums.json").read_text())
    # The committed files are what their checksums say.
    assert site_checksums(samples_dir) == committed["files"]
    result = CliRunner().invoke(cli, ["samples", "make", "--out", str(tmp_path), "--seed", "0"])
    assert result.exit_code == 0, result.output
    regenerated = site_checksums(tmp_path)
    for name, expected in committed["files"].items():
        assert regenerated[name] == expected, name
    assert (tmp_path / "checksums.json").read_text() == \
        (samples_dir / "checksums.json").read_text()
