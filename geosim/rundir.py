"""The run folder: every path a step reads or writes, named once.

A :class:`RunDir` wraps the ``--out`` folder. Steps ask it for paths
(``run.aligned("PA1")``) instead of joining string literals, and ask it to
``require_*`` an earlier step's output, which raises the one message
"X not found in DIR; run 'geosim Y' first" when it is missing.

Layout (see docs/outputs.md)::

    grid/grid.json, grid/<flight>.tif, grid/satellite.tif      step grid
    footprints.geojson/.gpkg, common_extent.geojson/.gpkg      step footprints
    alignment.json, alignment_check.geojson, aligned/<flight>.tif   step align
    tiles/<flight>/<tile_id>.tif, tiles/index.{geojson,gpkg,json}   step tiles
    pairs.csv                                                  step pairs
    labels/                                                    step labels
    calibration.json, calibration.png                          step calibrate
    degraded/<flight>/<tile_id>.tif                            step degrade
    diagnosis/                                                 step diagnose
    run.json                                                   the run record
"""

from __future__ import annotations

import os
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from geosim.errors import InputFileError
from geosim.io.paths import relative_if_inside

#: A tile id: row and column of the tile's upper-left corner in tiles (``r000_c003``).
TILE_ID = re.compile(r"^r\d{3,}_c\d{3,}$")
#: Temporary names of :func:`geosim.io.atomic.atomic_path` (``.<stem>.<random>.part<suffix>``,
#: with GDAL's ``.aux.xml`` side-car) and of the labels step's staging folder
#: (``.labels.partial-<random>``): what a killed run can leave behind.
#: Sub-folders of ``labels/`` holding the YOLO files of each tile resolution.
YOLO_SUBDIRS = {"uav": "yolo", "0.5m": "yolo_0.5m"}
TEMP_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}\.part(\.[^/]*)?$"
                       r"|^\.labels\.partial-[A-Za-z0-9_]{8}$")


@dataclass(frozen=True)
class RunDir:
    """The run folder ``root`` and the paths of everything in it.

    Parameters
    ----------
    root
        The ``--out`` folder.
    """

    root: Path

    @classmethod
    def of(cls, out: str | os.PathLike[str] | RunDir) -> RunDir:
        """``out`` as a :class:`RunDir` (a RunDir is returned as is)."""
        return out if isinstance(out, RunDir) else cls(Path(out))

    def __fspath__(self) -> str:
        return os.fspath(self.root)

    def __truediv__(self, other: str) -> Path:
        return self.root / other

    # ----------------------------------------------------------------- paths

    @property
    def run_json(self) -> Path:
        return self.root / "run.json"

    @property
    def output_journal(self) -> Path:
        """Paths written by the running step, one a line (removed when the run ends)."""
        return self.root / ".geosim-outputs.journal"

    @property
    def grid_dir(self) -> Path:
        return self.root / "grid"

    @property
    def grid_json(self) -> Path:
        return self.grid_dir / "grid.json"

    def grid_raster(self, flight_id: str) -> Path:
        """A flight on the shared UAV grid: ``grid/<flight>.tif``."""
        return self.grid_dir / f"{flight_id}.tif"

    @property
    def satellite_grid(self) -> Path:
        """The satellite scene on the shared 0.5 m grid: ``grid/satellite.tif``."""
        return self.grid_dir / "satellite.tif"

    @property
    def footprints_geojson(self) -> Path:
        return self.root / "footprints.geojson"

    @property
    def footprints_gpkg(self) -> Path:
        return self.root / "footprints.gpkg"

    @property
    def common_extent_geojson(self) -> Path:
        return self.root / "common_extent.geojson"

    @property
    def common_extent_gpkg(self) -> Path:
        return self.root / "common_extent.gpkg"

    @property
    def alignment_json(self) -> Path:
        return self.root / "alignment.json"

    @property
    def alignment_check_geojson(self) -> Path:
        return self.root / "alignment_check.geojson"

    def alignment_field(self, flight_id: str) -> Path:
        """A flight's local displacement field (``align_model = "local"``):
        ``alignment_field/<flight>.tif``."""
        return self.root / "alignment_field" / f"{flight_id}.tif"

    @property
    def aligned_dir(self) -> Path:
        return self.root / "aligned"

    def aligned(self, flight_id: str) -> Path:
        """A flight resampled onto the aligned grid: ``aligned/<flight>.tif``."""
        return self.aligned_dir / f"{flight_id}.tif"

    @property
    def tiles_dir(self) -> Path:
        return self.root / "tiles"

    def tile(self, flight_id: str, tile_id: str) -> Path:
        """``tiles/<flight>/<tile_id>.tif``."""
        return self.tiles_dir / flight_id / f"{tile_id}.tif"

    def tile_files(self, flight_id: str) -> list[Path]:
        """The flight's UAV tiles, sorted; files whose name is not a tile id are not tiles."""
        return _tile_files(self.tiles_dir / flight_id)

    @property
    def tiles_index_geojson(self) -> Path:
        return self.tiles_dir / "index.geojson"

    @property
    def tiles_index_gpkg(self) -> Path:
        return self.tiles_dir / "index.gpkg"

    @property
    def tiles_index_json(self) -> Path:
        return self.tiles_dir / "index.json"

    @property
    def pairs_csv(self) -> Path:
        return self.root / "pairs.csv"

    @property
    def labels_dir(self) -> Path:
        return self.root / "labels"

    def yolo_dir(self, resolution: str = "uav") -> Path:
        """YOLO label files per tile: ``labels/yolo`` (UAV) or ``labels/yolo_0.5m``."""
        return self.labels_dir / YOLO_SUBDIRS[resolution]

    def yolo_file(self, resolution: str, flight_id: str, tile_id: str) -> Path:
        """``labels/<yolo dir>/<flight>/<tile_id>.txt``."""
        return self.yolo_dir(resolution) / flight_id / f"{tile_id}.txt"

    @property
    def classes_txt(self) -> Path:
        return self.labels_dir / "classes.txt"

    @property
    def calibration_json(self) -> Path:
        return self.root / "calibration.json"

    @property
    def calibration_png(self) -> Path:
        return self.root / "calibration.png"

    @property
    def degraded_dir(self) -> Path:
        return self.root / "degraded"

    def degraded(self, flight_id: str, tile_id: str) -> Path:
        """``degraded/<flight>/<tile_id>.tif``: a tile degraded to the satellite grid."""
        return self.degraded_dir / flight_id / f"{tile_id}.tif"

    def tile_at(self, resolution: str, flight_id: str, tile_id: str) -> Path:
        """The tile at ``resolution``: ``"uav"`` (:meth:`tile`) or ``"0.5m"`` (:meth:`degraded`)."""
        if resolution not in YOLO_SUBDIRS:
            raise ValueError(f"resolution must be one of {', '.join(YOLO_SUBDIRS)}")
        return (self.tile if resolution == "uav" else self.degraded)(flight_id, tile_id)

    def degraded_files(self, flight_id: str) -> list[Path]:
        """The flight's degraded tiles, sorted (only names that are tile ids)."""
        return _tile_files(self.degraded_dir / flight_id)

    @property
    def diagnosis_dir(self) -> Path:
        return self.root / "diagnosis"

    def rel(self, path: str | os.PathLike[str]) -> str:
        """``path`` relative to the run folder (POSIX); as given when outside it."""
        return relative_if_inside(path, self.root)

    # ----------------------------------------------------------------- checks

    def require(self, path: Path, command: str, *, what: str | None = None,
                is_dir: bool = False) -> Path:
        """``path`` if it exists, else the one "run 'geosim COMMAND' first" error.

        Parameters
        ----------
        path
            An earlier step's output inside the run folder.
        command
            The command that writes it (``"grid"``, ``"align"``, ...).
        what
            Words after the path in the message (e.g. ``"(flight PA1)"``).
        is_dir
            The output is a folder.

        Raises
        ------
        InputFileError
            ``<rel path> not found in <root>; run 'geosim <command>' (or 'geosim run') first``.
        """
        ok = path.is_dir() if is_dir else path.is_file()
        if not ok:
            label = self.rel(path) + (f" {what}" if what else "")
            raise InputFileError(f"{label} not found in {self.root}; run 'geosim {command}' "
                                 "(or 'geosim run') first")
        return path

    def require_grid(self) -> Path:
        return self.require(self.grid_json, "grid")

    def require_satellite_grid(self) -> Path:
        return self.require(self.satellite_grid, "grid",
                            what="(the satellite scene on the shared grid)")

    def require_common_extent(self) -> Path:
        return self.require(self.common_extent_gpkg, "grid")

    def require_alignment(self) -> Path:
        return self.require(self.alignment_json, "align")

    def require_aligned(self, flight_id: str) -> Path:
        return self.require(self.aligned(flight_id), "align", what=f"(flight {flight_id})")

    def require_tiles_index(self) -> Path:
        return self.require(self.tiles_index_json, "tile")

    def require_tiles_dir(self) -> Path:
        return self.require(self.tiles_dir, "tile", is_dir=True)

    def require_calibration(self) -> Path:
        return self.require(self.calibration_json, "calibrate",
                            what="(it needs a [satellite] scene; or give Q explicitly: "
                                 "q = 4.34 under [parameters], or --q 4.34)")

    # ----------------------------------------------------------------- housekeeping

    def leftover_temp_files(self) -> list[Path]:
        """Temporary files and staging folders a killed run left (names of geosim's own)."""
        if not self.root.is_dir():
            return []
        return sorted(p for p in _walk(self.root) if TEMP_NAME.match(p.name))

    def clean_leftovers(self) -> list[str]:
        """Remove :meth:`leftover_temp_files`; returns their paths relative to the folder."""
        removed = []
        for p in self.leftover_temp_files():
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(self.rel(p))
        return removed

    def remove_outputs(self, rel_paths: list[str]) -> list[str]:
        """Delete these files (paths relative to the folder, as recorded in run.json).

        Only files inside the folder are touched; folders left empty are removed.
        Returns the paths that were deleted.
        """
        root = self.root.resolve()
        removed = []
        for rel in rel_paths:
            p = (self.root / rel)
            try:
                p.resolve().relative_to(root)
            except ValueError:
                continue  # never outside the run folder
            if p.is_file() or p.is_symlink():
                p.unlink()
                removed.append(rel)
                _prune_empty(p.parent, root)
        return removed


def _tile_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob("*.tif") if TILE_ID.match(p.stem))


def _walk(root: Path) -> Iterator[Path]:
    for dirpath, dirnames, filenames in os.walk(root):
        base = Path(dirpath)
        for name in filenames:
            yield base / name
        for name in list(dirnames):
            if TEMP_NAME.match(name):
                dirnames.remove(name)  # a staging folder: removed whole, not walked
                yield base / name


def _prune_empty(folder: Path, root: Path) -> None:
    while folder.resolve() != root and folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()
        folder = folder.parent


#: What step functions accept as the run folder: a path or a :class:`RunDir`.
RunPath = str | os.PathLike[str]
