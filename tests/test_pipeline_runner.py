"""The runner records steps, timings, inputs with checksums, and failures, in run.json."""

from __future__ import annotations

import hashlib
import json
import sys
import types
from pathlib import Path

import pytest

from geosim.config import site_from_images
from geosim.errors import ConfigError
from geosim.pipeline import Step, run_pipeline, select_steps
from geosim.result import StepResult
from tests.helpers import gdal_cache_bytes, textured_rgb, write_raster


@pytest.fixture
def fake_steps(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    calls: list[str] = []
    mod = types.ModuleType("fake_steps")

    def ok(site, out):  # noqa: ANN001, ANN202
        calls.append("ok")
        (out / "ok.txt").write_text("x")
        return StepResult("wrote ok.txt", outputs=["ok.txt"], record={"written": 1})

    def boom(site, out):  # noqa: ANN001, ANN202
        raise RuntimeError("step exploded")

    mod.ok, mod.boom = ok, boom
    monkeypatch.setitem(sys.modules, "fake_steps", mod)
    monkeypatch.setattr("geosim.pipeline.STEPS", (
        Step("one", "fake_steps", "ok"), Step("sat", "fake_steps", "ok", needs_satellite=True),
        Step("two", "fake_steps", "boom")))
    monkeypatch.setattr("geosim.pipeline.STEP_NAMES", ("one", "sat", "two"))
    return calls


def test_run_json_records_inputs_steps_and_failure(tmp_path: Path, fake_steps: list[str]) -> None:
    img = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    site = site_from_images([img], None)
    with pytest.raises(RuntimeError, match="exploded"):
        run_pipeline(site, tmp_path / "out", echo=lambda s: None)
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["status"] == "failed"
    assert record["steps"]["one"]["status"] == "ok" and record["steps"]["one"]["seconds"] >= 0
    assert record["steps"]["sat"]["status"] == "skipped"
    assert record["steps"]["two"] == {**record["steps"]["two"], "status": "failed",
                                      "error": "step exploded"}
    expected = hashlib.sha256(img.read_bytes()).hexdigest()
    assert record["inputs"]["flights.a.image"]["sha256"] == expected
    assert record["site"]["parameters"]["phi"] == 10


def test_input_checksums_reused_only_for_the_same_file(
        tmp_path: Path, fake_steps: list[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """A rerun reuses run.json's checksum of an input with the same path, size and mtime,
    and hashes again one whose bytes changed (same size, new mtime)."""
    import os

    from geosim import pipeline

    img = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    site = site_from_images([img], None)
    out = tmp_path / "out"
    hashed: list[str] = []
    real = pipeline.sha256_file
    monkeypatch.setattr(pipeline, "sha256_file", lambda p: hashed.append(Path(p).name) or real(p))

    def inputs() -> dict:
        with pytest.raises(RuntimeError, match="exploded"):
            run_pipeline(site, out, echo=lambda s: None)
        return json.loads((out / "run.json").read_text())["inputs"]["flights.a.image"]

    first = inputs()
    assert hashed == ["a.tif"] and first["sha256"] == hashlib.sha256(img.read_bytes()).hexdigest()
    assert inputs() == first and hashed == ["a.tif"]  # reused: not hashed again
    data = bytearray(img.read_bytes())
    data[-1] ^= 0xFF  # same size, other bytes (the last byte of the pixel data)
    img.write_bytes(bytes(data))
    os.utime(img, ns=(first["mtime_ns"] + 10**9, first["mtime_ns"] + 10**9))
    third = inputs()
    assert hashed == ["a.tif", "a.tif"]
    assert third["sha256"] == hashlib.sha256(bytes(data)).hexdigest() != first["sha256"]


def test_only_selects_steps_in_order(fake_steps: list[str]) -> None:
    assert [s.name for s in select_steps(["two", "one"])] == ["one", "two"]
    with pytest.raises(ConfigError, match="unknown step"):
        select_steps(["three"])


def test_partial_run_keeps_earlier_step_records(tmp_path: Path, fake_steps: list[str],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    img = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    site = site_from_images([img], None)
    out = tmp_path / "out"
    monkeypatch.setattr("geosim.pipeline.STEPS", (Step("one", "fake_steps", "ok"),
                                                  Step("two", "fake_steps", "ok")))
    monkeypatch.setattr("geosim.pipeline.STEP_NAMES", ("one", "two"))
    run_pipeline(site, out, echo=lambda s: None)
    first = json.loads((out / "run.json").read_text())["steps"]
    record = run_pipeline(site, out, only=["two"], echo=lambda s: None)
    assert list(record["steps"]) == ["one", "two"]
    assert record["steps"]["one"] == {**first["one"], "from_earlier_run": True}
    assert "from_earlier_run" not in record["steps"]["two"]


# ------------------------------------------------------------------- GDAL block cache


def _gdal_cache_bytes(_: object = None) -> int:
    got = gdal_cache_bytes()
    if got is None:
        pytest.skip("needs /proc/self/maps (Linux) and one loaded libgdal")
    return got


def test_in_process_tasks_get_the_bounded_gdal_cache_in_megabytes(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A step's in-process engine tasks and a command's body run with GDAL_CACHE_MB MB of
    block cache, as GDAL itself reports it (rasterio.Env takes an integer GDAL_CACHEMAX as
    bytes: the runner's former GDAL_CACHEMAX=256 left a 256-byte cache)."""
    from geosim.engine import parallel_map
    from geosim.pipeline import GDAL_CACHE_MB
    from geosim.record import command_record

    seen: list[int] = []
    mod = types.ModuleType("cache_steps")

    def probe(site, out):  # noqa: ANN001, ANN202
        seen.extend(parallel_map(_gdal_cache_bytes, [0, 1]))
        return StepResult("probed")

    mod.probe = probe
    monkeypatch.setitem(sys.modules, "cache_steps", mod)
    monkeypatch.setattr("geosim.pipeline.STEPS", (Step("probe", "cache_steps", "probe"),))
    monkeypatch.setattr("geosim.pipeline.STEP_NAMES", ("probe",))
    img = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    run_pipeline(site_from_images([img], None), tmp_path / "out", echo=lambda s: None)
    with command_record("movement", tmp_path / "cmd" / "run.json", inputs={},
                        options={}):
        seen.append(_gdal_cache_bytes())
    assert seen == [GDAL_CACHE_MB * 2**20] * 3
