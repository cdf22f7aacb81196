"""The resume manifest: an output is current only while its inputs, parameters and the
output itself are what was recorded."""

from __future__ import annotations

import os
from pathlib import Path

from geosim import manifest


def _setup(tmp_path: Path) -> tuple[Path, Path, Path]:
    run = tmp_path / "run"
    (run / "tiles").mkdir(parents=True)
    src = run / "tiles" / "a.tif"
    src.write_bytes(b"input bytes")
    out = run / "degraded" / "a.tif"
    out.parent.mkdir(parents=True)
    out.write_bytes(b"output bytes")
    return run, src, out


def test_current_after_record_and_not_before(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    params = {"q": 2.0}
    assert not manifest.is_current(run, out, [src], params)
    manifest.record_output(run, out, [src], params)
    assert manifest.is_current(run, out, [src], params)
    assert (run / ".geosim" / "manifest" / "degraded" / "a.tif.json").is_file()


def test_changed_params_input_or_output_are_not_current(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    manifest.record_output(run, out, [src], {"q": 2.0})
    assert not manifest.is_current(run, out, [src], {"q": 2.5})
    assert not manifest.is_current(run, out, [src, out], {"q": 2.0})  # other input list
    st = src.stat()
    src.write_bytes(b"INPUT BYTES")  # same size, other content, a later mtime
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert not manifest.is_current(run, out, [src], {"q": 2.0})


def test_input_rewritten_with_same_bytes_stays_current(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    manifest.record_output(run, out, [src], {"q": 2.0})
    st = src.stat()
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 5_000_000_000))  # only mtime moved
    assert manifest.is_current(run, out, [src], {"q": 2.0})


def test_touched_or_missing_output_is_not_current(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    manifest.record_output(run, out, [src], {"q": 2.0})
    out.write_bytes(b"edited by hand")  # another size
    assert not manifest.is_current(run, out, [src], {"q": 2.0})
    manifest.record_output(run, out, [src], {"q": 2.0})
    out.unlink()
    assert not manifest.is_current(run, out, [src], {"q": 2.0})


def test_cached_record_round_trips_and_a_broken_entry_is_ignored(tmp_path: Path) -> None:
    run, src, _ = _setup(tmp_path)
    result = {"q": 1.7734295718091746, "curve": [1.0, 2.5]}
    manifest.record(run, "calibration/PA1", [src], {"phi": 10}, result=result)
    entry = manifest.cached(run, "calibration/PA1", [src], {"phi": 10})
    assert entry is not None and entry["result"] == result
    (run / ".geosim" / "manifest" / "calibration" / "PA1.json").write_text("{not json")
    assert manifest.cached(run, "calibration/PA1", [src], {"phi": 10}) is None


def test_moved_run_folder_keeps_entries(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    manifest.record_output(run, out, [src], {"q": 2.0})
    moved = tmp_path / "moved"
    run.rename(moved)
    # rename keeps sizes and mtimes; entries name files relative to the run folder
    assert manifest.is_current(moved, moved / "degraded" / "a.tif", [moved / "tiles" / "a.tif"],
                               {"q": 2.0})


def _copy(task: tuple[str, str]) -> None:
    Path(task[1]).write_bytes(Path(task[0]).read_bytes() + b"!")


def test_run_resumable_skips_until_the_task_or_its_input_changes(tmp_path: Path) -> None:
    run, src, out = _setup(tmp_path)
    out.unlink()
    job = manifest.ResumableTask(str(run), _copy, (str(src), str(out)), str(out), (str(src),))
    assert manifest.run_resumable(job) is False and out.read_bytes() == b"input bytes!"
    assert manifest.run_resumable(job) is True
    other = manifest.ResumableTask(str(run), _copy, (str(src), str(out), "x"), str(out),
                                   (str(src),))
    assert manifest.run_resumable(other) is False  # another task (its pickle differs)


def test_input_made_in_the_run_folder_is_not_hashed_and_tracks_its_recipe(
        tmp_path: Path, monkeypatch) -> None:
    """An input with its own entry (a tile written by a task) is fingerprinted by what made
    it, without reading it: rewritten by its task with the same recipe it stays current;
    with another recipe, or edited by hand, it is changed."""
    run, tile, out = _setup(tmp_path)
    flight = tmp_path / "flight.tif"
    flight.write_bytes(b"flight")
    manifest.record_output(run, tile, [flight], {"tile": 1})  # the tile step's entry
    calls: list[Path] = []
    real = manifest.sha256_file
    monkeypatch.setattr(manifest, "sha256_file", lambda p: calls.append(Path(p)) or real(p))
    manifest.record_output(run, out, [tile], {"q": 2.0})
    assert Path(tile) not in calls  # the tile was not read to be hashed
    entry = (run / ".geosim" / "manifest" / "degraded" / "a.tif.json").read_text()
    assert '"made_by"' in entry and entry.count('"sha256"') == 0
    assert manifest.is_current(run, out, [tile], {"q": 2.0})

    def rewrite(params: dict, data: bytes = b"input bytes") -> None:
        st = tile.stat()
        tile.write_bytes(data)
        os.utime(tile, ns=(st.st_atime_ns, st.st_mtime_ns + 2_000_000_000))
        manifest.record_output(run, tile, [flight], params)

    rewrite({"tile": 1})  # the same task again: same bytes, new mtime
    assert manifest.is_current(run, out, [tile], {"q": 2.0})
    rewrite({"tile": 2}, b"INPUT BYTES")  # another recipe, same size
    assert not manifest.is_current(run, out, [tile], {"q": 2.0})
    manifest.record_output(run, out, [tile], {"q": 2.0})
    assert manifest.is_current(run, out, [tile], {"q": 2.0})
    st = tile.stat()  # edited by hand: its entry no longer vouches for it
    tile.write_bytes(b"input BYTES")
    os.utime(tile, ns=(st.st_atime_ns, st.st_mtime_ns + 3_000_000_000))
    assert not manifest.is_current(run, out, [tile], {"q": 2.0})
    flight.write_bytes(b"FLIGHT")  # an upstream input changed and the tile was remade
    rewrite({"tile": 2}, b"INPUT BYTES")
    assert not manifest.is_current(run, out, [tile], {"q": 2.0})
