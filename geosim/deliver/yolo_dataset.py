"""YOLO datasets laid out as trainers read them, split by tile (no ground in both splits).

Layout (Ultralytics / YOLOv5-8 convention)::

    yolo/data.yaml                      train/val image folders, class names
    yolo/images/{train,val}/<flight>_<tile>.png
    yolo/labels/{train,val}/<flight>_<tile>.txt

A trainer finds an image's labels by replacing the last ``/images/`` of its path with
``/labels/`` and the suffix with ``.txt``. The split is spatial: whole tiles go to
train or val, so every flight of a tile (the same ground on other dates) is on the same
side and no validation ground was seen in training.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rasterio

from geosim.errors import ConfigError, InputFileError
from geosim.io.atomic import atomic_path, write_text
from geosim.io.raster import image_band_indexes, read_valid_mask

SPLITS = ("train", "val")


def split_tiles(tile_ids: Iterable[str], *, val_fraction: float, seed: int
                ) -> dict[str, str]:
    """Assign whole tiles to ``train`` or ``val``, seeded.

    Parameters
    ----------
    tile_ids
        Tile ids (duplicates are ignored).
    val_fraction
        Fraction of tiles for validation, in ``[0, 1)``; rounded to whole tiles, at least
        one val tile when there are two or more tiles and ``val_fraction > 0``, and at least
        one train tile.
    seed
        Seed of the ``numpy.random.Generator`` that shuffles the sorted ids.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ConfigError(f"val_fraction = {val_fraction}: give a fraction in [0, 1)")
    ids = sorted(set(tile_ids))
    n_val = round(val_fraction * len(ids))
    if val_fraction > 0 and len(ids) >= 2:
        n_val = max(n_val, 1)
    n_val = min(n_val, max(len(ids) - 1, 0))
    order = np.random.default_rng(seed).permutation(len(ids))
    val = {ids[i] for i in order[:n_val]}
    return {t: ("val" if t in val else "train") for t in ids}


def label_path_for(image_path: str) -> str:
    """The Ultralytics rule: last ``/images/`` → ``/labels/``, suffix → ``.txt``."""
    sa, sb = f"{os.sep}images{os.sep}", f"{os.sep}labels{os.sep}"
    return sb.join(image_path.rsplit(sa, 1)).rsplit(".", 1)[0] + ".txt"


def data_yaml(names: Sequence[str], *, train: str = "images/train", val: str = "images/val",
              note: str = "") -> str:
    """Text of a ``data.yaml``; no ``path`` key, so trainers resolve paths from its folder."""
    lines = [f"# {note}" for note in note.splitlines()] if note else []
    lines += [f"train: {train}", f"val: {val}", f"nc: {len(names)}", "names:"]
    lines += [f"  {i}: {n}" for i, n in enumerate(names)]
    return "\n".join(lines) + "\n"


def tile_png(src: Path, dst: Path) -> None:
    """Write a tile's image bands as an 8-bit PNG (masked pixels black), atomically."""
    import cv2

    with rasterio.open(src) as ds:
        img = ds.read(image_band_indexes(ds)[:3])
        valid = read_valid_mask(ds)
    if img.dtype != np.uint8:
        raise InputFileError(f"{src}: {img.dtype} tiles cannot be written as 8-bit PNG "
                             "training images; YOLO datasets need uint8 tiles")
    img[:, ~valid] = 0
    bgr = np.ascontiguousarray(np.moveaxis(img[::-1] if img.shape[0] == 3 else img, 0, -1))
    with atomic_path(dst) as tmp:
        if not cv2.imwrite(str(tmp), bgr):
            raise InputFileError(f"{dst}: PNG encoding failed; check the folder is writable")


@dataclass(frozen=True)
class YoloDataset:
    """What :func:`write_yolo_dataset` wrote."""

    root: Path
    images: dict[str, int]     # split -> number of images
    tiles: dict[str, str]      # tile id -> split


def write_yolo_dataset(root: Path, items: Sequence[tuple[str, str, Path, Path]],
                       names: Sequence[str], *, val_fraction: float, seed: int,
                       note: str = "") -> YoloDataset:
    """Write a YOLO dataset from georeferenced tiles and their label files.

    Parameters
    ----------
    root
        Dataset folder (``yolo/`` or ``yolo_0.5m/``); earlier images and labels are replaced.
    items
        ``(flight, tile_id, tile_tif, label_txt)`` per image.
    names
        Class names (line order of ``labels/classes.txt``).
    val_fraction, seed
        See :func:`split_tiles`.
    """
    import shutil

    split = split_tiles((t for _, t, _, _ in items), val_fraction=val_fraction, seed=seed)
    for sub in ("images", "labels"):
        shutil.rmtree(root / sub, ignore_errors=True)
    counts = dict.fromkeys(SPLITS, 0)
    for flight, tile, tif, txt in items:
        s, stem = split[tile], f"{flight}_{tile}"
        tile_png(tif, root / "images" / s / f"{stem}.png")
        text = txt.read_text() if txt.is_file() else ""
        write_text(root / "labels" / s / f"{stem}.txt", text)
        counts[s] += 1
    write_text(root / "data.yaml", data_yaml(names, note=note))
    return YoloDataset(root, counts, split)


def write_split_lists(root: Path, images_by_tile: dict[str, list[str]], names: Sequence[str],
                      *, val_fraction: float, seed: int, note: str = "") -> dict[str, int]:
    """Split a flat ``images/`` + ``labels/`` folder by tile with list files and a data.yaml.

    Writes ``root/train.txt`` and ``root/val.txt`` (one ``./images/...`` path per line,
    which trainers resolve from the list's folder) and ``root/data.yaml`` pointing at them.

    Parameters
    ----------
    images_by_tile
        ``{tile_id: [image path relative to root]}``: all images made from a tile go to
        the same split.
    """
    split = split_tiles(images_by_tile, val_fraction=val_fraction, seed=seed)
    lists: dict[str, list[str]] = {s: [] for s in SPLITS}
    for tile, paths in sorted(images_by_tile.items()):
        lists[split[tile]] += [f"./{p}" for p in paths]
    for s in SPLITS:
        write_text(root / f"{s}.txt", "".join(f"{p}\n" for p in sorted(lists[s])))
    write_text(root / "data.yaml", data_yaml(names, train="train.txt", val="val.txt",
                                             note=note))
    return {s: len(v) for s, v in lists.items()}


__all__ = ["SPLITS", "YoloDataset", "data_yaml", "label_path_for", "split_tiles",
           "write_split_lists", "write_yolo_dataset"]
