"""run.json of the commands that do not run pipeline steps (geosim/record.py):
augment, cattle-per-paddock --out, movement, overlay-check. Checksums are checked
against hashlib, outputs against the files on disk."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import geopandas as gpd
import numpy as np
import rasterio
import shapely
from affine import Affine
from click.testing import CliRunner

from geosim.cli.main import cli
from tests.test_augment_cli import run_dir  # noqa: F401  (the fixture)

X0, Y0 = 280000.0, 6175000.0


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _herd(path: Path) -> Path:
    """PA1 -> PA2: c1 stays 0.3 m, c2 moves 6 m, c3 goes, n4 appears."""
    pts = {"PA1": {"c1": (0.0, 0.0), "c2": (20.0, 0.0), "c3": (40.0, 40.0)},
           "PA2": {"n1": (0.3, 0.0), "n2": (26.0, 0.0), "n4": (90.0, 90.0)}}
    rows, geoms = [], []
    for flight, d in pts.items():
        for cid, (x, y) in d.items():
            rows.append({"cattle_id": cid, "flight": flight})
            geoms.append(shapely.box(X0 + x - 1.0, Y0 + y - 0.4, X0 + x + 1.0, Y0 + y + 0.4))
    gpd.GeoDataFrame(rows, geometry=geoms, crs="EPSG:32756").to_file(
        path, layer="cattle", driver="GPKG")
    return path


def _record(path: Path) -> dict:
    doc = json.loads(path.read_text())
    for key in ("geosim_version", "python", "started", "finished", "seconds", "engine",
                "inputs", "options", "steps"):
        assert key in doc, key
    return doc


def _outputs_exist(doc: dict, command: str, root: Path) -> list[str]:
    outs = doc["steps"][command]["outputs"]
    assert outs and all((root / o).is_file() for o in outs)
    return outs


def test_movement_records_inputs_outputs_and_unchanged_output(tmp_path: Path) -> None:
    labels = _herd(tmp_path / "cattle.gpkg")
    out = tmp_path / "mv"
    res = CliRunner().invoke(cli, ["movement", "--labels", str(labels), "--from", "PA1",
                                   "--to", "PA2", "--radius-m", "10", "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert res.stdout.splitlines() == [
        "PA1 -> PA2 (radius 10 m, stayed within 1 m)", "  stayed        1",
        "  moved         1", "  gone          1", "  appeared      1",
        "  median distance moved: 6.00 m"]
    doc = _record(out / "run.json")
    assert doc["status"] == "ok" and doc["command"] == "movement"
    assert doc["inputs"]["labels"]["sha256"] == _sha(labels)
    assert doc["options"]["radius_m"] == 10 and doc["options"]["from"] == "PA1"
    assert doc["engine"]["kind"] == "in-process"
    step = doc["steps"]["movement"]
    assert step["status"] == "ok" and "1 moved" in step["summary"]["text"]
    assert _outputs_exist(doc, "movement", out) == ["movement_PA1_PA2.csv",
                                                    "movement_PA1_PA2.geojson"]


def test_failing_command_records_failed_with_the_message(tmp_path: Path) -> None:
    labels = _herd(tmp_path / "cattle.gpkg")
    out = tmp_path / "mv"
    res = CliRunner().invoke(cli, ["movement", "--labels", str(labels), "--from", "PA1",
                                   "--to", "PA9", "--radius-m", "10", "--out", str(out)])
    assert res.exit_code != 0 and "PA9" in res.output
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == "failed"
    step = doc["steps"]["movement"]
    assert step["status"] == "failed" and "PA9" in step["error"] and step["outputs"] == []


def test_cattle_per_paddock_records_beside_the_csv(tmp_path: Path) -> None:
    labels = _herd(tmp_path / "cattle.gpkg")
    paddocks = tmp_path / "paddocks.geojson"
    gpd.GeoDataFrame({"name": ["P"]}, geometry=[shapely.box(X0 - 5, Y0 - 5, X0 + 30, Y0 + 5)],
                     crs="EPSG:32756").to_file(paddocks, driver="GeoJSON")
    args = ["cattle-per-paddock", "--labels", str(labels), "--paddocks", str(paddocks)]
    plain = CliRunner().invoke(cli, args)
    assert plain.exit_code == 0, plain.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cattle.gpkg", "paddocks.geojson"]
    out = tmp_path / "counts.csv"
    res = CliRunner().invoke(cli, [*args, "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert res.stdout == plain.stdout  # the table is unchanged by the record
    doc = _record(tmp_path / "counts.csv.run.json")
    assert doc["status"] == "ok"
    assert doc["inputs"]["labels"]["sha256"] == _sha(labels)
    assert doc["inputs"]["paddocks"]["sha256"] == _sha(paddocks)
    assert _outputs_exist(doc, "cattle-per-paddock", tmp_path) == ["counts.csv"]


def _raster(path: Path, shift_m: float = 0.0) -> Path:
    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.normal(size=(300, 300)).astype(np.float32), (0, 0), 2.0)
    t = Affine(1.0, 0, 300000.0 + shift_m, 0, -1.0, 6200000.0)
    with rasterio.open(path, "w", driver="GTiff", width=300, height=300, count=1,
                       dtype="float32", crs="EPSG:32756", transform=t) as dst:
        dst.write(img, 1)
    return path


def test_overlay_check_records_and_joins_a_pipeline_record(tmp_path: Path) -> None:
    a, b = _raster(tmp_path / "a.tif"), _raster(tmp_path / "b.tif", 1.0)
    out = tmp_path / "ov"
    res = CliRunner().invoke(cli, ["overlay-check", "--a", str(a), "--b", str(b),
                                   "--out", str(out), "--window-px", "64"])
    assert res.exit_code == 0, res.output
    doc = _record(out / "run.json")
    assert doc["status"] == "ok"
    assert {v["sha256"] for v in doc["inputs"].values()} == {_sha(a), _sha(b)}
    outs = _outputs_exist(doc, "overlay-check", out)
    assert "overlay.json" in outs and "overlay_arrows.geojson" in outs
    assert any(o.endswith(".png") for o in outs)
    # a run folder's record (here a minimal pipeline record) is kept; the step is added
    pipeline = {"status": "ok", "site": {"x": 1}, "steps": {"grid": {"status": "ok"}}}
    (out / "run.json").write_text(json.dumps(pipeline))
    res = CliRunner().invoke(cli, ["overlay-check", "--a", str(a), "--b", str(b),
                                   "--out", str(out), "--window-px", "64"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "run.json").read_text())
    assert doc["status"] == "ok" and doc["site"] == {"x": 1} and "grid" in doc["steps"]
    step = doc["steps"]["overlay-check"]
    assert step["status"] == "ok" and step["inputs"]["a_b.a"]["sha256"] == _sha(a)


def test_augment_plot_warp_records_beside_the_png(tmp_path: Path) -> None:
    src = tmp_path / "frame.png"
    cv2.imwrite(str(src), np.random.default_rng(0).integers(0, 255, (90, 120, 3), np.uint8))
    out = tmp_path / "fig.png"
    res = CliRunner().invoke(cli, ["augment", "--plot-warp", str(src), "--out", str(out),
                                   "--seed", "2"])
    assert res.exit_code == 0, res.output
    doc = _record(tmp_path / "fig.png.run.json")
    assert doc["status"] == "ok" and doc["options"]["seed"] == 2
    assert doc["inputs"]["image"]["sha256"] == _sha(src)
    assert _outputs_exist(doc, "augment", tmp_path) == ["fig.png"]
    assert doc["steps"]["augment"]["summary"]["text"] in res.stdout


def test_augment_records_the_run_and_a_refusal_keeps_it(run_dir: Path,  # noqa: F811
                                                        tmp_path: Path) -> None:
    pairs = run_dir / "pairs.csv"
    out = tmp_path / "aug"
    res = CliRunner().invoke(cli, ["augment", "--pairs", str(pairs), "--n", "1",
                                   "--out", str(out), "--seed", "3"])
    assert res.exit_code == 0, res.output
    doc = _record(out / "run.json")
    assert doc["status"] == "ok" and doc["options"]["n"] == 1
    assert doc["inputs"]["pairs"]["sha256"] == _sha(pairs)
    outs = _outputs_exist(doc, "augment", out)
    on_disk = sorted(str(p.relative_to(out)) for p in out.rglob("*")
                     if p.is_file() and p.name != "run.json")
    assert outs == on_disk and "augmented_pairs.csv" in outs
    assert doc["steps"]["augment"]["summary"]["text"] in res.stdout
    before = (out / "run.json").read_text()
    res = CliRunner().invoke(cli, ["augment", "--pairs", str(pairs), "--out", str(out)])
    assert res.exit_code == 2 and "already holds" in res.output
    assert (out / "run.json").read_text() == before  # refused before recording


def test_ctrl_c_is_recorded_interrupted(tmp_path: Path) -> None:
    import pytest

    from geosim.record import command_record

    with pytest.raises(KeyboardInterrupt), command_record(
            "movement", tmp_path / "run.json", inputs={}, options={}) as rec:
        (tmp_path / "x.txt").write_text("not atomic")
        rec.outputs.append(tmp_path / "x.txt")
        raise KeyboardInterrupt
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["status"] == "interrupted" and doc["steps"]["movement"]["outputs"] == ["x.txt"]
