"""``geosim augment`` end to end on a tiny synthetic run folder (two flights, two tiles)."""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from click.testing import CliRunner
from rasterio.errors import NotGeoreferencedWarning

from geosim.cli.main import cli
from geosim.io.raster import write_geotiff

CRS = "EPSG:32756"
TILE_PX = 80
FLIGHTS = ("PA1", "PA2")
TILES = ("r000_c000", "r000_c001")
BOXES = "0 0.500000 0.500000 0.200000 0.150000\n0 0.250000 0.700000 0.100000 0.100000\n"

GEOMETRIC = """
[[functions]]
name = "mirror"
p_ud = 1.0
p_lr = 0.0
[[functions]]
name = "rotate"
min_deg = 5.0
max_deg = 20.0
"""
PHOTOMETRIC = """
[[functions]]
name = "colour"
sigma_dn = 10.0
[[functions]]
name = "value"
sigma_dn = 10.0
"""


def _uav_transform(tile_col: int) -> Affine:
    return Affine(0.05, 0.0, 500000.0 + tile_col * TILE_PX * 0.05, 0.0, -0.05, 6200000.0)


@pytest.fixture()
def run_dir(tmp_path: Path) -> Path:
    """A run folder as `geosim run` lays it out (only what augment reads)."""
    d = tmp_path / "run"
    rng = np.random.default_rng(0)
    rows = []
    for col, tile in enumerate(TILES):
        for flight in FLIGHTS:
            img = rng.integers(30, 220, (3, TILE_PX, TILE_PX), dtype=np.uint8)
            mask = np.ones((TILE_PX, TILE_PX), bool)
            mask[:, :4] = False  # a strip of no data
            t = _uav_transform(col)
            write_geotiff(d / "tiles" / flight / f"{tile}.tif", img, transform=t, crs=CRS,
                          mask=mask, band_descriptions=["red", "green", "blue"])
            small = img[:, ::10, ::10].copy()
            write_geotiff(d / "degraded" / flight / f"{tile}.tif", small,
                          transform=t @ Affine.scale(10), crs=CRS,
                          mask=np.ones((8, 8), bool))
            for sub in ("yolo", "yolo_0.5m"):
                (d / "labels" / sub / flight).mkdir(parents=True, exist_ok=True)
                (d / "labels" / sub / flight / f"{tile}.txt").write_text(BOXES)
        x0 = 500000.0 + col * 4.0
        rows.append({"pair_id": f"{tile}_PA1_PA2", "tile_id": tile, "flight_a": "PA1",
                     "flight_b": "PA2", "acquired_a": "2021-07-15T13:10:00+10:00",
                     "acquired_b": "2021-07-16T13:10:00+10:00",
                     "path_a": f"tiles/PA1/{tile}.tif", "path_b": f"tiles/PA2/{tile}.tif",
                     "minx": x0, "miny": 6199996.0, "maxx": x0 + 4.0, "maxy": 6200000.0,
                     "crs": CRS})
    (d / "labels" / "classes.txt").write_text("cattle\n")
    with open(d / "pairs.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return d


def _invoke(*args: str):
    return CliRunner().invoke(cli, ["augment", *map(str, args)], catch_exceptions=False)


def _config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "aug.toml"
    p.write_text(text)
    return p


def _read(path: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        with rasterio.open(path) as ds:
            return ds.read(), ds.dataset_mask(), ds.crs, ds.transform, ds.tags()


def test_geometric_run_writes_everything_off_the_map_grid(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "aug"
    res = _invoke("--pairs", run_dir / "pairs.csv", "--config", _config(tmp_path, GEOMETRIC),
                  "--n", 2, "--out", out, "--seed", 7)
    assert res.exit_code == 0, res.output
    ids = [f"{t}_PA1_PA2_k{k:03d}" for t in TILES for k in range(2)]
    for aug_id in ids:
        for side in "ab":
            assert (out / "images" / f"{aug_id}_{side}.tif").is_file()
            assert (out / "labels" / f"{aug_id}_{side}.txt").is_file()
        assert (out / "meta" / f"{aug_id}.json").is_file()
    for name in ("augmented_pairs.csv", "parameters.csv", "classes.txt", "augment.json"):
        assert (out / name).is_file()
    with open(out / "augmented_pairs.csv") as f:
        manifest = list(csv.DictReader(f))
    assert [m["aug_id"] for m in manifest] == ids
    assert all(m["on_map_grid_a"] == "False" for m in manifest)

    data, mask, crs, transform, tags = _read(out / "images" / f"{ids[0]}_a.tif")
    assert crs is None and transform == Affine.identity()  # no false geotransform
    assert tags["GEOSIM_ON_MAP_GRID"] == "false"
    assert "no longer on the map grid" in tags["GEOSIM_NOTE"]
    assert tags["GEOSIM_SOURCE_TILE"] == "tiles/PA1/r000_c000.tif"
    assert json.loads(tags["GEOSIM_SOURCE_TRANSFORM"]) == list(_uav_transform(0))[:6]
    chain = json.loads(tags["GEOSIM_TRANSFORM_CHAIN"])
    assert chain[0]["kind"] == "affine" and chain[0]["functions"] == ["mirror", "rotate"]
    assert data.shape == (3, TILE_PX, TILE_PX)
    assert (mask == 0).any() and (mask == 255).mean() > 0.7  # rotated corners invalid
    assert (data[:, mask == 0] == 0).all()

    params = list(csv.DictReader(open(out / "parameters.csv")))
    assert len(params) == 4 and "01_rotate.rotation_deg" in params[0]
    assert all(5.0 <= float(p["01_rotate.rotation_deg"]) <= 20.0 for p in params)
    meta = json.loads((out / "meta" / f"{ids[0]}.json").read_text())
    drawn = meta["records"][1]["params"]["rotation_deg"]
    assert drawn == float(params[0]["01_rotate.rotation_deg"])  # CSV holds exact values
    lines = (out / "labels" / f"{ids[0]}_a.txt").read_text().split("\n")
    assert 1 <= len([ln for ln in lines if ln]) <= 2
    assert all(0.0 <= float(v) <= 1.0 for ln in lines if ln for v in ln.split()[1:])

    # same seed → same files; existing output refused without --overwrite
    again = tmp_path / "again"
    _invoke("--pairs", run_dir / "pairs.csv", "--config", tmp_path / "aug.toml", "--n", 2,
            "--out", again, "--seed", 7)
    for rel in (f"images/{ids[3]}_b.tif", f"labels/{ids[3]}_b.txt"):
        if rel.endswith(".tif"):
            assert np.array_equal(_read(out / rel)[0], _read(again / rel)[0])
        else:
            assert (out / rel).read_text() == (again / rel).read_text()
    assert (out / "parameters.csv").read_text() == (again / "parameters.csv").read_text()
    res = CliRunner().invoke(cli, ["augment", "--pairs", str(run_dir / "pairs.csv"),
                                   "--out", str(out), "--seed", "7"])
    assert res.exit_code == 2 and "already holds" in res.output
    res = _invoke("--pairs", run_dir / "pairs.csv", "--config", tmp_path / "aug.toml",
                  "--n", 1, "--out", out, "--overwrite")
    assert res.exit_code == 0 and len(list((out / "images").iterdir())) == 4


def test_photometric_only_keeps_the_geotransform(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "aug"
    res = _invoke("--pairs", run_dir / "pairs.csv", "--config", _config(tmp_path, PHOTOMETRIC),
                  "--n", 1, "--out", out, "--seed", 1)
    assert res.exit_code == 0, res.output
    _, _, crs, transform, tags = _read(out / "images" / "r000_c001_PA1_PA2_k000_b.tif")
    assert crs == rasterio.crs.CRS.from_string(CRS) and transform == _uav_transform(1)
    assert tags["GEOSIM_ON_MAP_GRID"] == "true"
    # boxes untouched by photometric functions
    assert (out / "labels" / "r000_c001_PA1_PA2_k000_b.txt").read_text() == BOXES


def test_degraded_tiles_with_shipped_config_and_png(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "aug"
    res = _invoke("--pairs", run_dir / "pairs.csv", "--n", 2, "--out", out, "--seed", 3,
                  "--resolution", "0.5m", "--format", "png")
    assert res.exit_code == 0, res.output
    png = cv2.imread(str(out / "images" / "r000_c000_PA1_PA2_k000_a.png"), cv2.IMREAD_UNCHANGED)
    assert png.shape == (8, 8, 4) and set(np.unique(png[..., 3])) <= {0, 255}
    summary = json.loads((out / "augment.json").read_text())
    assert summary["resolution"] == "0.5m" and summary["augmented_pairs"] == 4
    params = list(csv.DictReader(open(out / "parameters.csv")))
    assert float(params[0]["length_scale"]) == pytest.approx(0.1)  # 0.05 m reference → 0.5 m


def test_augmented_yolo_dataset_is_split_by_source_tile(run_dir: Path, tmp_path: Path
                                                        ) -> None:
    """data.yaml + train/val lists: the trainers' path rules find every label, and the
    images of one source tile (both flights, every k) are all on one side."""
    import yaml

    from geosim.deliver.yolo_dataset import label_path_for

    out = tmp_path / "aug"
    res = _invoke("--pairs", run_dir / "pairs.csv", "--n", 2, "--out", out, "--seed", 3,
                  "--format", "png")
    assert res.exit_code == 0, res.output
    data = yaml.safe_load((out / "data.yaml").read_text())
    assert data["names"] == {0: "cattle"} and "path" not in data
    side_of: dict[str, set[str]] = {}
    n = 0
    for split in ("train", "val"):
        for line in (out / data[split]).read_text().splitlines():
            assert line.startswith("./images/")
            img = out / line[2:]            # './' lines resolve from the list's folder
            assert img.is_file() and Path(label_path_for(str(img))).is_file()
            side_of.setdefault(img.name[:9], set()).add(split)   # source tile id
            n += 1
    assert n == len(list((out / "images").glob("*.png"))) == 8
    assert all(len(s) == 1 for s in side_of.values()) and len(side_of) == 2
    assert {next(iter(s)) for s in side_of.values()} == {"train", "val"}


def test_interrupted_or_repeated_run_resumes(run_dir: Path, tmp_path: Path) -> None:
    """Resumable: after an interrupted run (no augmented_pairs.csv yet) the rerun skips the
    pairs already made and finishes with the same files as an uninterrupted run; an
    --overwrite rerun with nothing changed skips every pair and says so; another seed
    makes every pair again."""
    import hashlib

    def digests(folder: Path) -> dict[str, str]:
        return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()
                and ".geosim" not in p.parts and p.name not in ("augment.json", "run.json")}

    args = ("--pairs", run_dir / "pairs.csv", "--n", 2, "--seed", 5)
    whole = tmp_path / "whole"
    assert _invoke(*args, "--out", whole).exit_code == 0
    want = digests(whole)
    assert len(want) > 20

    cut = tmp_path / "cut"
    assert _invoke(*args, "--out", cut).exit_code == 0
    # an interrupted run: the last pair never finished, the dataset files not written
    (cut / "augmented_pairs.csv").unlink()
    (cut / "data.yaml").unlink()
    last = sorted((cut / ".geosim" / "manifest" / "pairs").glob("*.json"))[-1]
    last.unlink()
    for p in (cut / "images").glob(f"{last.stem}_k001_*"):
        p.unlink()
    res = _invoke(*args, "--out", cut)
    assert res.exit_code == 0, res.output
    n_pairs = len(list((cut / ".geosim" / "manifest" / "pairs").glob("*.json")))
    assert f"{n_pairs - 1} of {n_pairs} pairs already current, skipped" in res.output
    assert digests(cut) == want
    assert json.loads((cut / "augment.json").read_text())["skipped_current"] == n_pairs - 1

    res = _invoke(*args, "--out", cut, "--overwrite")
    assert f"{n_pairs} of {n_pairs} pairs already current, skipped" in res.output
    assert digests(cut) == want
    res = _invoke("--pairs", run_dir / "pairs.csv", "--n", 1, "--seed", 6, "--out", cut,
                  "--overwrite")
    assert res.exit_code == 0 and "already current" not in res.output
    assert len(list((cut / "images").glob("*"))) == 2 * n_pairs  # the n = 2 files removed


def test_bad_inputs_give_one_line_errors(run_dir: Path, tmp_path: Path) -> None:
    runner = CliRunner()
    res = runner.invoke(cli, ["augment", "--pairs", str(tmp_path / "nope.csv"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "does not exist" in res.output
    res = runner.invoke(cli, ["augment", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "--pairs" in res.output
    (run_dir / "labels" / "yolo" / "PA2" / "r000_c001.txt").write_text("0 0.5 0.5 0.1\n")
    res = runner.invoke(cli, ["augment", "--pairs", str(run_dir / "pairs.csv"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "r000_c001.txt, line 1" in res.output


def test_plot_warp_writes_the_figure(tmp_path: Path) -> None:
    img = np.random.default_rng(0).integers(0, 255, (90, 120, 3), dtype=np.uint8)
    src = tmp_path / "frame.png"
    cv2.imwrite(str(src), img)
    out = tmp_path / "fig.png"
    res = _invoke("--plot-warp", src, "--out", out, "--seed", 2)
    assert res.exit_code == 0, res.output
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    res = CliRunner().invoke(cli, ["augment", "--plot-warp", str(src), "--out", str(out),
                                   "--max-px", "40", "--filter-sigma-px", "5"])
    assert res.exit_code == 2 and "fold" in res.output


ALL_KINDS = GEOMETRIC + PHOTOMETRIC + """
[[functions]]
name = "shift"
sigma_px = 3.0
[[functions]]
name = "local_warp"
max_px = 2.0
filter_sigma_px = 12.0
mode = "independent"
[[functions]]
name = "hue"
sigma_deg = 20.0
[[functions]]
name = "saturation"
sigma_dn = 20.0
[[functions]]
name = "noise"
sigma_dn = 4.0
"""


def test_one_and_two_workers_give_identical_outputs(run_dir: Path, tmp_path: Path) -> None:
    # Every kind of stage (affine fused with the local warp, HSV, OpenCV-drawn noise) on a
    # two-process cluster, where OpenCV runs single-threaded, equals the in-process run.
    cfg = _config(tmp_path, ALL_KINDS)
    outs = {}
    for workers in ("1", "2"):
        outs[workers] = tmp_path / f"w{workers}"
        res = _invoke("--pairs", run_dir / "pairs.csv", "--config", cfg, "--n", 2, "--out",
                      outs[workers], "--seed", 3, "--workers", workers)
        assert res.exit_code == 0, res.output
    images = sorted(p.name for p in (outs["1"] / "images").iterdir())
    assert len(images) == 8 and images == sorted(p.name for p in (outs["2"] / "images").iterdir())
    for name in images:
        one, two = _read(outs["1"] / "images" / name), _read(outs["2"] / "images" / name)
        assert np.array_equal(one[0], two[0]) and np.array_equal(one[1], two[1]), name
    for name in sorted(p.name for p in (outs["1"] / "labels").iterdir()):
        assert (outs["1"] / "labels" / name).read_text() == (
            outs["2"] / "labels" / name).read_text()
    assert (outs["1"] / "parameters.csv").read_text() == (
        outs["2"] / "parameters.csv").read_text()


def test_compress_none_writes_the_same_pixels_uncompressed(run_dir: Path, tmp_path: Path
                                                           ) -> None:
    """--compress none (fastest to write and to load) changes only the encoding."""
    args = ("--pairs", run_dir / "pairs.csv", "--n", 1, "--seed", 9)
    assert _invoke(*args, "--out", tmp_path / "d").exit_code == 0
    res = _invoke(*args, "--out", tmp_path / "n", "--compress", "none")
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "n" / "augment.json").read_text())["compress"] == "none"
    names = sorted(p.name for p in (tmp_path / "d" / "images").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "n" / "images").iterdir())
    for name in names:
        a, b = tmp_path / "d" / "images" / name, tmp_path / "n" / "images" / name
        (da, ma, *_), (db, mb, *_) = _read(a), _read(b)
        assert np.array_equal(da, db) and np.array_equal(ma, mb)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(a) as ds_a, rasterio.open(b) as ds_b:
                assert ds_a.compression.value.lower() == "deflate"
                assert ds_b.compression is None
