"""The run as users open it: COGs, VRT mosaics, the tile index's locations, STAC, YOLO
datasets and the QGIS project, checked with external readers (GDAL/rasterio, gdalinfo,
pystac, the Ultralytics path rule, real QGIS) on a full run of the sample site."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import geopandas as gpd
import numpy as np
import pytest
import rasterio
from click.testing import CliRunner
from PIL import Image

from geosim.cli.main import cli
from geosim.deliver.yolo_dataset import label_path_for, split_tiles

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_dir(samples_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sample site run with keep_intermediates (so the whole-flight aligned/ rasters,
    large enough for overviews, are delivered and checked too)."""
    import re

    out = tmp_path_factory.mktemp("deliver")
    text = re.sub(r'^(image|labels|path|paddocks) = "([^"]+)"',
                  lambda m: f'{m[1]} = "{(samples_dir / m[2]).resolve().as_posix()}"',
                  (samples_dir / "site.toml").read_text(), flags=re.M)
    site = out.parent / "deliver_site.toml"
    site.write_text(text.replace("[parameters]\n", "[parameters]\nkeep_intermediates = true\n"))
    assert "keep_intermediates = true" in site.read_text()
    result = CliRunner().invoke(cli, ["run", str(site), "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def _tifs(run_dir: Path) -> list[Path]:
    return sorted(p for p in run_dir.rglob("*.tif") if "sample_site" not in p.parts)


def test_every_raster_is_a_cog_with_overviews(run_dir: Path) -> None:
    tifs = _tifs(run_dir)
    assert len(tifs) > 30
    big = 0
    for tif in tifs:
        with rasterio.open(tif) as ds:
            assert ds.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG", tif
            assert ds.compression.value.lower() == "deflate"
            assert ds.tags().get("GEOSIM_STEP"), tif          # provenance kept
            assert ds.crs is not None
            if max(ds.width, ds.height) > 512:
                big += 1
                assert ds.overviews(1), f"{tif}: {ds.width}×{ds.height} px without overviews"
                # the mask has overviews too (GDAL reads masked overviews)
                assert ds.dataset_mask(out_shape=(ds.height // 4, ds.width // 4)).any()
    assert big >= 3  # at least aligned/<flight>.tif


@pytest.mark.skipif(shutil.which("gdalinfo") is None, reason="gdalinfo (gdal-bin) not installed")
def test_gdalinfo_reports_cog_layout_and_overviews(run_dir: Path) -> None:
    for tif in (run_dir / "aligned" / "PA1.tif", run_dir / "tiles" / "PA2" / "r001_c001.tif"):
        info = subprocess.run(["gdalinfo", "-json", str(tif)], capture_output=True, text=True,
                              check=True)
        doc = json.loads(info.stdout)
        assert doc["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"] == "COG"
        assert doc["bands"][0]["overviews"], tif
        assert doc["bands"][0]["mask"]["flags"] == ["PER_DATASET"]


def test_tiles_keep_their_pixels_masks_and_acquisition_time(run_dir: Path,
                                                             samples_dir: Path) -> None:
    """The COG copy is lossless: tile pixels (resampled once, tile by tile, from the original
    flight) equal the kept whole-flight aligned raster's window."""
    with rasterio.open(run_dir / "tiles" / "PA3" / "r001_c002.tif") as t, \
            rasterio.open(run_dir / "aligned" / "PA3.tif") as a:
        win = a.window(*t.bounds)
        assert np.array_equal(t.read(), a.read(window=win))
        assert np.array_equal(t.read_masks(1), a.read_masks(1, window=win))
        tags = t.tags()
    assert tags["GEOSIM_ACQUIRED"] == "2021-07-15T15:00:00+10:00"
    assert tags["TIFFTAG_DATETIME"] == "2021:07:15 15:00:00"
    with rasterio.open(run_dir / "degraded" / "PA3" / "r001_c002.tif") as d:
        assert d.tags()["GEOSIM_ACQUIRED"] == "2021-07-15T15:00:00+10:00"


@pytest.mark.parametrize("kind", ["tiles", "degraded"])
def test_vrt_mosaics_show_the_tiles(run_dir: Path, kind: str) -> None:
    for flight in ("PA1", "PA2", "PA3"):
        vrt = run_dir / kind / f"{flight}.vrt"
        assert "relativeToVRT=\"1\"" in vrt.read_text()
        assert str(run_dir) not in vrt.read_text()        # relative paths only
        tiles = sorted((run_dir / kind / flight).glob("*.tif"))
        with rasterio.open(vrt) as m:
            for tif in tiles:
                with rasterio.open(tif) as t:
                    win = m.window(*t.bounds)
                    assert (win.col_off, win.row_off) == (round(win.col_off),
                                                          round(win.row_off))
                    assert np.array_equal(m.read(window=win), t.read())
                    assert np.array_equal(m.read_masks(1, window=win), t.read_masks(1))
                    assert m.crs == t.crs and m.res == t.res


def test_vrt_survives_moving_the_run_folder(run_dir: Path, tmp_path: Path) -> None:
    moved = tmp_path / "moved"
    shutil.copytree(run_dir / "tiles", moved / "tiles")
    with rasterio.open(moved / "tiles" / "PA1.vrt") as m, \
            rasterio.open(moved / "tiles" / "PA1" / "r001_c001.tif") as t:
        assert np.array_equal(m.read(window=m.window(*t.bounds)), t.read())


def test_tile_index_locations_open_the_tiles(run_dir: Path) -> None:
    """gdaltindex convention: ``location`` is the raster path relative to the index."""
    for name in ("index.geojson", "index.gpkg"):
        index = gpd.read_file(run_dir / "tiles" / name)
        assert len(index) == 4
        for row in index.itertuples():
            assert row.location == f"PA1/{row.tile_id}.tif"   # the reference flight
            for flight in ("PA1", "PA2", "PA3"):
                path = run_dir / "tiles" / getattr(row, f"location_{flight}")
                with rasterio.open(path) as ds:
                    geom = index.to_crs(ds.crs).geometry[row.Index]
                    assert np.allclose(geom.bounds, tuple(ds.bounds), atol=1e-6)


def test_stac_catalogue_reads_back_and_resolves(run_dir: Path) -> None:
    import pystac

    catalog = pystac.Catalog.from_file(str(run_dir / "stac" / "catalog.json"))
    (collection,) = list(catalog.get_children())
    assert isinstance(collection, pystac.Collection)
    items = list(collection.get_items())
    assert len(items) == 12 + 1                       # 4 tiles × 3 flights + satellite
    from pystac.extensions.projection import ProjectionExtension

    for item in items:
        props = item.properties
        assert item.datetime is not None
        # the files carry projection v1.1 (proj:epsg); pystac reads them as v2 (proj:code)
        raw = json.loads(Path(item.get_self_href()).read_text())["properties"]
        assert raw["proj:epsg"] == 32756
        assert ProjectionExtension.ext(item).code == "EPSG:32756"
        assert len(props["proj:transform"]) == 6 and len(props["proj:shape"]) == 2
        lon0, lat0, lon1, lat1 = item.bbox
        assert 150.3 < lon0 < lon1 < 150.4 and -34.5 < lat0 < lat1 < -34.4
        for asset in item.assets.values():
            assert not os.path.isabs(asset.to_dict()["href"])   # relative in the file
            assert Path(asset.get_absolute_href()).is_file(), asset.href
        image = item.assets["image"].get_absolute_href()
        with rasterio.open(image) as ds:
            t = ds.transform
            assert props["proj:shape"] == [ds.height, ds.width]
            assert props["proj:transform"] == pytest.approx([t.a, t.b, t.c, t.d, t.e, t.f])
        if item.id != "satellite":
            assert {"image", "degraded", "labels_yolo", "labels_yolo_0.5m",
                    "labels_geojson"} <= set(item.assets)
    by_id = {i.id: i for i in items}
    assert by_id["PA2_r001_c001"].datetime.isoformat() == "2021-07-15T03:00:00+00:00"
    assert by_id["satellite"].datetime.isoformat() == "2021-09-20T23:56:00+00:00"
    # structural checks (pystac's JSON-schema validation needs jsonschema and the network)
    files = sorted((run_dir / "stac").rglob("*.json"))
    assert len(files) == 1 + 1 + 13
    for f in files:
        doc = json.loads(f.read_text())
        for link in doc["links"]:
            assert not os.path.isabs(link["href"]) and "://" not in link["href"], (f, link)
            assert (f.parent / link["href"]).resolve().is_file(), (f, link)


@pytest.mark.parametrize("name,kind", [("yolo", "tiles"), ("yolo_0.5m", "degraded")])
def test_yolo_dataset_layout_and_split(run_dir: Path, name: str, kind: str) -> None:
    import yaml

    root = run_dir / name
    data = yaml.safe_load((root / "data.yaml").read_text())
    assert "path" not in data                         # resolved from the yaml's folder
    assert data["names"] == {0: "cattle"} and data["nc"] == 1
    images = sorted((root / "images").rglob("*.png"))
    assert len(images) == 12
    side_of: dict[str, set[str]] = {}
    n_boxes = 0
    for img in images:
        label = Path(label_path_for(str(img)))
        assert label.is_file(), label                  # the trainers' images→labels rule
        split = img.parent.name
        assert split in ("train", "val") and label.parent.name == split
        flight, tile = img.stem.split("_", 1)
        side_of.setdefault(tile, set()).add(split)
        source = run_dir / "labels" / name / flight / f"{tile}.txt"
        assert label.read_text() == source.read_text()
        n_boxes += len(label.read_text().split("\n")) - 1
        with rasterio.open(run_dir / kind / flight / f"{tile}.tif") as ds:
            arr = np.asarray(Image.open(img))
            assert arr.shape == (ds.height, ds.width, 3)
            assert np.array_equal(np.moveaxis(arr, -1, 0), ds.read([1, 2, 3]))
    assert n_boxes > 0
    # no leakage: every tile (all its flights) on one side; both sides used
    assert all(len(s) == 1 for s in side_of.values())
    assert {next(iter(s)) for s in side_of.values()} == {"train", "val"}
    for split in ("train", "val"):
        assert (root / data[split]).is_dir()


def test_split_tiles_is_seeded_and_whole() -> None:
    ids = [f"r{r:03d}_c{c:03d}" for r in range(5) for c in range(4)]
    a = split_tiles(ids, val_fraction=0.25, seed=3)
    assert a == split_tiles(list(reversed(ids)), val_fraction=0.25, seed=3)
    assert sum(v == "val" for v in a.values()) == 5
    assert a != split_tiles(ids, val_fraction=0.25, seed=4)
    assert set(split_tiles(["r000_c000", "r000_c001"], val_fraction=0.1, seed=0).values()) \
        == {"train", "val"}


def test_label_path_rule() -> None:
    p = os.sep.join(["", "d", "images", "x", "images", "train", "PA1_r001.png"])
    assert label_path_for(p) == os.sep.join(["", "d", "images", "x", "labels", "train",
                                             "PA1_r001.txt"])


QGIS_PYTHON = "/usr/bin/python3"


def _has_qgis() -> bool:
    if not Path(QGIS_PYTHON).is_file():
        return False
    probe = subprocess.run([QGIS_PYTHON, "-c", "import qgis.core"], capture_output=True)
    return probe.returncode == 0


@pytest.mark.skipif(not _has_qgis(), reason="QGIS Python bindings (Debian python3-qgis) "
                    "not installed for /usr/bin/python3")
def test_qgis_project_opens_with_every_layer_valid(run_dir: Path, tmp_path: Path) -> None:
    qgs = run_dir / "geosim.qgs"
    text = qgs.read_text()
    assert str(run_dir) not in text                   # relative paths
    moved = tmp_path / "moved_run"                    # …so the folder can move
    shutil.copytree(run_dir, moved, ignore=shutil.ignore_patterns("sample_site"))
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    env.pop("PYTHONPATH", None)
    png = tmp_path / "project.png"
    proc = subprocess.run([QGIS_PYTHON, str(ROOT / "tools" / "qgis_check_project.py"),
                           str(moved / "geosim.qgs"), "--png", str(png), "--width", "400"],
                          capture_output=True, text=True, env=env, timeout=300)
    doc = json.loads(proc.stdout.strip().splitlines()[-1])
    layers = doc["layers"]
    assert proc.returncode == 0, [ly for ly in layers if not ly["valid"]]
    assert all(ly["valid"] for ly in layers) and len(layers) >= 19
    assert doc["crs"] == "EPSG:32756"
    assert doc["groups"] == ["Cattle (per flight)", "Paddocks", "Tile index", "Footprints",
                             "Diagnosis", "Degraded (0.5 m)", "Flights (UAV mosaics)",
                             "Satellite"]
    by_name = {ly["name"]: ly for ly in layers}
    for ly in layers:
        assert ly["source"].startswith(str(moved)), ly   # resolved against the moved project
    cattle = gpd.read_file(run_dir / "labels" / "cattle.gpkg", layer="cattle")
    for flight in ("PA1", "PA2", "PA3"):
        assert by_name[f"cattle {flight}"]["features"] == int((cattle["flight"] == flight).sum())
        assert by_name[f"cattle {flight}"]["temporal"]
        assert by_name[f"flight {flight}"]["temporal"]
    assert by_name["paddocks (cattle per flight)"]["labels"]
    assert png.stat().st_size > 10_000


def test_cli_help_quiet_and_verbose(samples_dir: Path, tmp_path: Path) -> None:
    """-h works everywhere; -q leaves only results on stdout; -v names the loggers."""
    import tqdm

    original_init = tqdm.tqdm.__dict__["__init__"]
    runner = CliRunner()
    for args in (["-h"], ["deliver", "-h"], ["overlay-check", "-h"]):
        res = runner.invoke(cli, args)
        assert res.exit_code == 0 and "Usage:" in res.output
    site = str(samples_dir / "site.toml")
    out = str(tmp_path / "run")
    quiet = runner.invoke(cli, ["-q", "run", site, "--out", out, "--only", "grid"])
    assert quiet.exit_code == 0, quiet.output
    assert "[1/1]" not in quiet.stderr and "reproject" not in quiet.stderr
    assert "geosim 0.1.0: ok" in quiet.stdout
    loud = runner.invoke(cli, ["-v", "run", site, "--out", out, "--only", "footprints"])
    assert loud.exit_code == 0, loud.output
    assert "INFO geosim: [1/1] footprints" in loud.stderr
    assert tqdm.tqdm.__dict__["__init__"] is original_init   # -q is undone afterwards


def test_acquired_is_a_datetime_field_in_every_geopackage(run_dir: Path) -> None:
    import pyogrio

    seen = 0
    for gpkg in sorted(run_dir.rglob("*.gpkg")):
        for layer, _ in pyogrio.list_layers(gpkg):
            info = pyogrio.read_info(gpkg, layer=layer)
            fields = dict(zip(info["fields"], info["dtypes"], strict=True))
            if "acquired" in fields:
                assert fields["acquired"].startswith("datetime64"), (gpkg, layer, fields)
                seen += 1
    assert seen >= 3        # cattle, cattle_centres, footprints
    cattle = gpd.read_file(run_dir / "labels" / "cattle.gpkg", layer="cattle")
    pa3 = cattle.loc[cattle["flight"] == "PA3", "acquired"].iloc[0]
    assert pa3.isoformat() == "2021-07-15T05:00:00+00:00"     # 15:00 at +10:00, in UTC
    if shutil.which("ogrinfo"):
        out = subprocess.run(["ogrinfo", "-so", str(run_dir / "footprints.gpkg"),
                              "footprints"], capture_output=True, text=True, check=True)
        assert "acquired: DateTime" in out.stdout


def test_diagnosis_reports_embed_their_figures(run_dir: Path) -> None:
    import re

    reports = sorted((run_dir / "diagnosis").glob("*/report.md"))
    assert reports
    for report in reports:
        links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report.read_text())
        assert len(links) == 3, report
        for link in links:
            assert (report.parent / link).is_file(), (report, link)
