"""Honest run records: run.json from the start, interruptions recorded, no stale outputs.

The truth here is the file system and run.json as read back from disk: which files exist
after a rerun, what their pixel sizes are (read with rasterio), and what the record says
after a real SIGTERM delivered to another process.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import rasterio
from click.testing import CliRunner

from geosim.config import SiteConfig
from geosim.errors import InputFileError
from geosim.pipeline import run_pipeline
from geosim.rundir import RunDir
from tests.test_tiles_pairs import make_run

QUIET = {"echo": lambda s: None}


def _site_outside(tmp_path: Path) -> tuple[SiteConfig, Path]:
    """A run folder with grid, alignment and aligned rasters; the flights' inputs elsewhere."""
    site, out, _ = make_run(tmp_path, keep_partial=True)
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    flights = []
    for f in site.flights:
        shutil.copy(f.image, inputs / f.image.name)
        flights.append(dataclasses.replace(f, image=inputs / f.image.name))
    return dataclasses.replace(site, flights=tuple(flights)), out


def _with_tile_px(site: SiteConfig, tile_px: int) -> SiteConfig:
    params = dataclasses.replace(site.parameters, tile_px=tile_px)
    return dataclasses.replace(site, parameters=params)


def _tile_sizes(folder: Path) -> set[int]:
    sizes = set()
    for p in folder.rglob("*.tif"):
        with rasterio.open(p) as ds:
            sizes.add(ds.width)
    return sizes


def _record(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def test_rerun_with_other_tile_px_leaves_no_stale_tiles_and_keeps_user_files(
        tmp_path: Path) -> None:
    site, out = _site_outside(tmp_path)
    run_pipeline(site, out, only=["tiles", "pairs"], **QUIET)
    run_pipeline(site, out, only=["degrade"], options={"degrade": {"q": 2.0}}, **QUIET)
    old_tiles = {p.relative_to(out) for p in (out / "tiles").rglob("r*.tif")}
    assert _tile_sizes(out / "tiles") == {120} and _tile_sizes(out / "degraded") == {12}
    # the user's own files in the run folder, one of them named like a tile
    mine = [out / "tiles" / "PA1" / "notes.txt", out / "degraded" / "PA1" / "r099_c099.tif",
            out / "my_map.qgz"]
    for p in mine:
        p.write_bytes(b"mine")

    site60 = _with_tile_px(site, 60)
    record = run_pipeline(site60, out, only=["tiles"], **QUIET)
    # tiles of 120 px that 60 px tiling does not produce are gone, and so are the degraded
    # tiles made from the old tiles (a later step: they would mix two runs)
    assert _tile_sizes(out / "tiles") == {60}
    assert not (out / "degraded" / "PA1" / "r000_c000.tif").exists()
    assert not any((out / "degraded").rglob("r00*_c00*.tif"))
    assert "parameters" in record["cleaned"]["site_changed"]
    assert "degrade" not in record["steps"]  # its record went with its outputs
    new_tiles = {p.relative_to(out) for p in (out / "tiles").rglob("r*.tif")}
    assert new_tiles - old_tiles  # 60 px tiles have ids 120 px tiles do not
    for p in mine:
        assert p.read_bytes() == b"mine"
    assert _record(out)["site"]["parameters"]["tile_px"] == 60

    run_pipeline(site60, out, only=["degrade"], options={"degrade": {"q": 2.0}}, **QUIET)
    degraded = [p for p in (out / "degraded").rglob("*.tif") if p.name != "r099_c099.tif"]
    assert {p.relative_to(out / "degraded") for p in degraded} == {
        p.relative_to(out / "tiles") for p in (out / "tiles").rglob("r*.tif")}
    assert _tile_sizes(out / "degraded" / "PA2") == {6}
    assert (out / "degraded" / "PA1" / "r099_c099.tif").read_bytes() == b"mine"


def test_interrupted_step_is_recorded_interrupted_and_its_partial_outputs_cleaned(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    site, out = _site_outside(tmp_path)
    run_pipeline(site, out, only=["tiles"], **QUIET)
    run_pipeline(site, out, only=["degrade"], options={"degrade": {"q": 2.0}}, **QUIET)

    import geosim.prepare.tiles as prep  # the tile tasks write through prepare.tiles.create_geotiff

    real = prep.create_geotiff
    calls = {"n": 0}

    def write_then_interrupt(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls["n"] += 1
        if calls["n"] > 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    # The interruption is an event, not a time: the 4th tile write raises in this process
    # (the default in-process engine runs the tile tasks one after the other), so exactly
    # 3 tiles are finished before it, however loaded the machine is.
    monkeypatch.setattr(prep, "create_geotiff", write_then_interrupt)
    site60 = _with_tile_px(site, 60)
    with pytest.raises(KeyboardInterrupt):
        run_pipeline(site60, out, only=["tiles", "pairs"], **QUIET)
    assert calls["n"] == 4, calls  # 3 tiles written, the 4th interrupted
    record = _record(out)
    assert record["status"] == "interrupted"
    assert record["steps"]["tiles"]["status"] == "interrupted"
    assert "pairs" not in record["steps"]
    assert record["site"]["parameters"]["tile_px"] == 60  # the parameters of this run
    # no 120 px tile and no degraded tile of the old run is left; the 3 new tiles written
    # before the interruption are recorded as outputs
    on_disk = sorted(p.relative_to(out).as_posix() for p in (out / "tiles").rglob("*.tif"))
    assert _tile_sizes(out / "tiles") == {60}, (on_disk, record["steps"]["tiles"])
    assert not (out / "degraded").exists() or not any((out / "degraded").rglob("*.tif"))
    partial = [p for p in record["steps"]["tiles"]["outputs"] if p.endswith(".tif")]
    assert len(partial) == 3 and sorted(partial) == on_disk, (partial, on_disk)

    # a rerun with the old tile_px removes the partial 60 px tiles it does not write
    monkeypatch.setattr(prep, "create_geotiff", real)
    record = run_pipeline(site, out, only=["tiles"], **QUIET)
    assert record["status"] == "ok" and _tile_sizes(out / "tiles") == {120}


def test_run_json_is_written_at_the_start_with_status_running(tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch
                                                              ) -> None:
    site, out = _site_outside(tmp_path)
    seen = {}

    import geosim.prepare.steps as prep

    real = prep.run_pairs

    def spy(site, out_dir):  # noqa: ANN001, ANN202
        seen.update(_record(out))
        return real(site, out_dir)

    monkeypatch.setattr(prep, "run_pairs", spy)
    record = run_pipeline(site, out, only=["tiles", "pairs"], **QUIET)
    assert seen["status"] == "running"
    assert seen["steps"]["tiles"]["status"] == "ok"       # written after each step
    assert seen["steps"]["pairs"]["status"] == "running"
    assert seen["site"]["parameters"]["tile_px"] == 120
    assert record["status"] == "ok" and _record(out)["status"] == "ok"
    outputs = record["steps"]["pairs"]["outputs"]
    assert outputs == ["pairs.csv"]
    assert "tiles/index.json" in record["steps"]["tiles"]["outputs"]


def test_leftover_temp_files_are_cleaned_at_start_user_hidden_files_kept(tmp_path: Path
                                                                          ) -> None:
    site, out = _site_outside(tmp_path)
    (out / "tiles" / "PA1").mkdir(parents=True)
    leftovers = [out / "tiles" / "PA1" / ".r000_c000.k2j4h5g6.part.tif",
                 out / "grid" / ".grid.a1b2c3d4.part.json",
                 out / ".labels.partial-x9y8z7w6" / "cattle.geojson"]
    for p in leftovers:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("half")
    mine = out / ".my_settings"
    mine.write_text("keep")
    with pytest.raises(InputFileError, match=r"tiles/index.json not found in .*geosim tile"):
        run_pipeline(site, out, only=["pairs"], **QUIET)
    record = _record(out)
    assert record["status"] == "failed"
    assert sorted(record["cleaned"]["temp_files"]) == sorted(
        ["tiles/PA1/.r000_c000.k2j4h5g6.part.tif", "grid/.grid.a1b2c3d4.part.json",
         ".labels.partial-x9y8z7w6"])
    assert not any(p.exists() for p in leftovers)
    assert not (out / ".labels.partial-x9y8z7w6").exists()
    assert mine.read_text() == "keep"


def test_sigterm_is_recorded_interrupted(tmp_path: Path) -> None:
    img = tmp_path / "a.tif"
    from tests.helpers import textured_rgb, write_raster

    write_raster(img, textured_rgb(32, 32))
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import time
        from pathlib import Path
        import geosim.pipeline as gp
        from geosim.config import site_from_images

        def slow(site, out):
            (Path(out) / "started").write_text("x")
            time.sleep(120)

        gp.STEPS = (gp.Step("slow", "__main__", "slow"),)
        gp.STEP_NAMES = ("slow",)
        gp.run_pipeline(site_from_images([{str(img)!r}]), {str(out)!r}, echo=lambda s: None)
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.Popen([sys.executable, "-c", script], env=env,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300  # generous: imports are slow on a loaded machine
        while not (out / "started").exists():
            assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
            assert time.monotonic() < deadline, "the step did not start within 300 s"
            time.sleep(0.1)
        during = _record(out)
        assert during["status"] == "running" and during["steps"]["slow"]["status"] == "running"
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode != 0
    record = _record(out)
    assert record["status"] == "interrupted"
    assert record["steps"]["slow"]["status"] == "interrupted"
    assert "signal 15" in record["steps"]["slow"]["error"]


def test_sigkill_leaves_a_journal_the_next_run_cleans(tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGKILL cannot be caught: run.json stays 'running' (never 'ok') and the journal of
    completed outputs lets a rerun with other parameters remove them."""
    from tests.helpers import textured_rgb, write_raster

    img = write_raster(tmp_path / "a.tif", textured_rgb(32, 32))
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import time
        from pathlib import Path
        import geosim.pipeline as gp
        from geosim.config import site_from_images
        from geosim.io.atomic import write_text

        def slow(site, out):
            for i in range(3):
                write_text(Path(out) / "made" / f"part{{i}}.txt", "x")
            (Path(out) / "started").write_text("x")
            time.sleep(120)

        gp.STEPS = (gp.Step("slow", "__main__", "slow"),)
        gp.STEP_NAMES = ("slow",)
        gp.run_pipeline(site_from_images([{str(img)!r}], q=2.0), {str(out)!r},
                        echo=lambda s: None)
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    proc = subprocess.Popen([sys.executable, "-c", script], env=env)
    try:
        deadline = time.monotonic() + 300  # generous: imports are slow on a loaded machine
        while not (out / "started").exists():
            assert proc.poll() is None, "the run ended before it could be killed"
            assert time.monotonic() < deadline, "the step did not start within 300 s"
            time.sleep(0.1)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert _record(out)["status"] == "running"
    assert len((out / ".geosim-outputs.journal").read_text().splitlines()) == 3
    (out / "made" / "mine.txt").write_text("mine")

    import types

    from geosim.config import site_from_images
    from geosim.pipeline import Step
    from geosim.result import StepResult

    mod = types.ModuleType("fake_quick")
    mod.quick = lambda site, out: StepResult("nothing")
    monkeypatch.setitem(sys.modules, "fake_quick", mod)
    monkeypatch.setattr("geosim.pipeline.STEPS", (Step("slow", "fake_quick", "quick"),))
    monkeypatch.setattr("geosim.pipeline.STEP_NAMES", ("slow",))
    record = run_pipeline(site_from_images([img], q=3.0), out, **QUIET)  # other parameters
    assert sorted(record["cleaned"]["stale_outputs"]) == [f"made/part{i}.txt" for i in range(3)]
    assert [p.name for p in (out / "made").iterdir()] == ["mine.txt"]
    assert not (out / ".geosim-outputs.journal").exists() and record["status"] == "ok"


def test_cli_interrupt_is_one_line_and_recorded(tmp_path: Path, samples_dir: Path,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    from geosim.cli.main import cli

    def interrupted(site, out):  # noqa: ANN001, ANN202
        raise KeyboardInterrupt

    monkeypatch.setattr("geosim.prepare.steps.run_grid", interrupted)
    out = tmp_path / "run"
    result = CliRunner().invoke(cli, ["grid", str(samples_dir / "site.toml"), "--out", str(out)])
    assert result.exit_code == 130
    assert "interrupted" in result.output and "Traceback" not in result.output
    assert _record(out)["status"] == "interrupted"
    assert _record(out)["steps"]["grid"]["status"] == "interrupted"


def test_rundir_require_names_the_folder_and_the_command(tmp_path: Path) -> None:
    run = RunDir(tmp_path)
    with pytest.raises(InputFileError) as e:
        run.require_aligned("PA1")
    msg = str(e.value)
    assert msg == (f"aligned/PA1.tif (flight PA1) not found in {tmp_path}; run 'geosim align' "
                   "(or 'geosim run') first")
    assert run.tile("PA1", "r000_c001") == tmp_path / "tiles" / "PA1" / "r000_c001.tif"


def test_every_step_command_writes_run_json(tmp_path: Path) -> None:
    """degrade, labels and calibrate used to bypass the runner and write no run.json."""
    from geosim.cli.main import cli

    site, out = _site_outside(tmp_path)
    run_pipeline(site, out, only=["tiles"], **QUIET)
    (out / "run.json").unlink()
    toml = tmp_path / "site.toml"
    flights = "\n".join(
        f'[[flights]]\nid = "{f.id}"\nimage = "{f.image}"\n'
        f'acquired = "2021-07-1{5 + i}T11:00:00+10:00"\n'
        for i, f in enumerate(site.flights))
    toml.write_text(f'[site]\nname = "t"\nreference_flight = "PA1"\n\n[parameters]\n'
                    f"tile_px = 120\nkeep_partial_tiles = true\n\n{flights}")
    result = CliRunner().invoke(cli, ["degrade", str(toml), "--out", str(out), "--q", "4.34"])
    assert result.exit_code == 0, result.output
    record = _record(out)
    assert record["status"] == "ok" and record["steps"]["degrade"]["status"] == "ok"
    assert record["steps"]["degrade"]["options"] == {"q": 4.34, "method": "fast"}
    assert "Q = 4.34" in result.output
    # Q = 4.34 is above the 0.5–2 of real cameras: the warning is printed and recorded
    (warning,) = record["steps"]["degrade"]["warnings"]
    assert "geosim diagnose" in warning and f"warning: {warning}" in result.output
    n_tiles = len(list((out / "tiles").rglob("r*.tif")))
    assert len([p for p in record["steps"]["degrade"]["outputs"]
                if p.startswith("degraded/")]) == n_tiles
