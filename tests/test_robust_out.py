"""Inputs are sacred: --out may not be, contain or sit inside an input (issue 12, item 1),
and the labels step never deletes files in OUT/labels that geosim did not write."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from geosim.config import load_site
from geosim.errors import OutputError
from geosim.io.publish import MANIFEST, publish_folder
from geosim.validate import check_out_dir
from tests.robust_helpers import assert_one_line_error, copy_site, run_cli, tree_digest


@pytest.fixture()
def site_copy(samples_dir: Path, tmp_path: Path) -> Path:
    return copy_site(samples_dir, tmp_path / "site")


def test_out_equal_to_site_folder_is_refused_and_labels_survive(site_copy: Path) -> None:
    # On the old main this ran for a minute, exited 0 and deleted labels/PA1, PA2, PA3.geojson.
    site_dir = site_copy.parent
    before = tree_digest(site_dir)
    result = run_cli("run", site_copy, "--out", site_dir)
    assert_one_line_error(result, "--out", "contains", "choose a new folder")
    assert tree_digest(site_dir) == before  # nothing written, nothing deleted


@pytest.mark.parametrize("where", ["labels/PA1", "labels/PA1/run", "flights/run",
                                   "satellite", "labels"])
def test_out_inside_an_input_folder_is_refused(site_copy: Path, where: str) -> None:
    site = load_site(site_copy)
    with pytest.raises(OutputError, match="input"):
        check_out_dir(site, site_copy.parent / where)


def test_out_containing_the_inputs_is_refused(site_copy: Path) -> None:
    site = load_site(site_copy)
    with pytest.raises(OutputError, match="contains the site file"):
        check_out_dir(site, site_copy.parent.parent)


def test_out_beside_the_inputs_is_allowed(site_copy: Path) -> None:
    site = load_site(site_copy)
    assert check_out_dir(site, site_copy.parent / "out") == (site_copy.parent / "out").resolve()
    assert check_out_dir(site, site_copy.parent.parent / "run")


def test_out_an_existing_file_is_one_line_error(site_copy: Path, tmp_path: Path) -> None:
    target = tmp_path / "a_file"
    target.write_text("mine\n")
    result = run_cli("run", site_copy, "--out", target)
    assert_one_line_error(result, str(target), "existing file")
    assert target.read_text() == "mine\n"
    below = run_cli("run", site_copy, "--out", target / "run")
    assert_one_line_error(below, "is a file")


# ------------------------------------------------------------------ labels/ publication


def _stage(tmp_path: Path, files: dict[str, str]) -> Path:
    stage = tmp_path / ".labels.partial-test"
    for rel, text in files.items():
        (stage / rel).parent.mkdir(parents=True, exist_ok=True)
        (stage / rel).write_text(text)
    return stage


def test_publish_keeps_foreign_files_and_removes_only_stale_own(tmp_path: Path) -> None:
    final = tmp_path / "labels"
    publish_folder(_stage(tmp_path, {"a.txt": "1", "yolo/PA1/r000_c000.txt": "x"}), final)
    assert json.loads((final / MANIFEST).read_text())["files"] == [
        "a.txt", "yolo/PA1/r000_c000.txt"]
    (final / "notes.md").write_text("my notes")
    (final / "yolo" / "PA1" / "mine.txt").write_text("keep")
    counts = publish_folder(_stage(tmp_path, {"a.txt": "2", "b.txt": "3"}), final)
    assert counts == {"written": 2, "removed": 1, "kept": 2}
    assert (final / "a.txt").read_text() == "2" and (final / "b.txt").read_text() == "3"
    assert (final / "notes.md").read_text() == "my notes"
    assert (final / "yolo" / "PA1" / "mine.txt").read_text() == "keep"
    assert not (final / "yolo" / "PA1" / "r000_c000.txt").exists()
    assert not list(tmp_path.glob(".labels*"))  # stage consumed


def test_publish_refuses_to_overwrite_a_foreign_file(tmp_path: Path) -> None:
    final = tmp_path / "labels"
    final.mkdir()
    (final / "classes.txt").write_text("cow\nhorse\n")  # not written by geosim, no manifest
    with pytest.raises(OutputError, match="not written by geosim"):
        publish_folder(_stage(tmp_path, {"classes.txt": "cattle\n"}), final,
                       legacy_own=lambda rel: False)
    assert (final / "classes.txt").read_text() == "cow\nhorse\n"


def test_publish_swaps_a_folder_of_own_files_whole(tmp_path: Path) -> None:
    final = tmp_path / "labels"
    publish_folder(_stage(tmp_path, {"a.txt": "1", "old.txt": "o"}), final)
    publish_folder(_stage(tmp_path, {"a.txt": "2"}), final)
    assert sorted(p.name for p in final.iterdir()) == [MANIFEST, "a.txt"]


@pytest.mark.slow
def test_labels_rerun_keeps_user_files_in_out_labels(site_copy: Path, tmp_path: Path) -> None:
    # On the old main the labels step swapped a new folder over OUT/labels, deleting these.
    out = tmp_path / "run"
    steps = ["--only", "grid", "--only", "footprints", "--only", "align", "--only", "tiles",
             "--only", "labels"]
    first = run_cli("run", site_copy, "--out", out, *steps)
    assert first.code == 0, first.stderr[-2000:]
    own = tree_digest(out / "labels")
    assert "cattle.gpkg" in own and any(k.startswith("yolo/PA1/") for k in own)
    (out / "labels" / "notes.txt").write_text("counted by hand: 37\n")
    (out / "labels" / "yolo" / "PA1" / "extra_frame.txt").write_text("0 0.5 0.5 0.1 0.1\n")
    again = run_cli("run", site_copy, "--out", out, "--only", "labels")
    assert again.code == 0, again.stderr[-2000:]
    assert (out / "labels" / "notes.txt").read_text() == "counted by hand: 37\n"
    assert (out / "labels" / "yolo" / "PA1" / "extra_frame.txt").is_file()
    after = tree_digest(out / "labels")
    for rel in own:  # geosim's own outputs were rewritten, identical (same inputs)
        if rel != MANIFEST and not rel.endswith(".gpkg"):
            assert after[rel] == own[rel], rel


def test_cattle_per_paddock_out_never_overwrites_its_inputs(samples_dir: Path,
                                                            tmp_path: Path) -> None:
    paddocks = tmp_path / "paddocks.geojson"
    paddocks.write_bytes((samples_dir / "paddocks.geojson").read_bytes())
    labels = tmp_path / "cattle.geojson"
    labels.write_bytes((samples_dir / "labels" / "PA3.geojson").read_bytes())
    before = tree_digest(tmp_path)
    for target in (paddocks, labels):
        result = run_cli("cattle-per-paddock", "--labels", labels, "--paddocks", paddocks,
                         "--out", target)
        assert_one_line_error(result, str(target), "input")
    assert tree_digest(tmp_path) == before


def test_unwritable_out_is_refused(site_copy: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The permission branch (tests run as root here, where chmod does not stop writes)."""
    import geosim.validate as v

    monkeypatch.setattr(v.os, "access", lambda path, mode: False)
    with pytest.raises(OutputError, match="is not writable"):
        check_out_dir(load_site(site_copy), site_copy.parent.parent / "run")
