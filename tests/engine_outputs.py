"""Digests of a run folder's outputs as a reader sees them, to compare two runs.

GeoTIFFs by their decoded pixels, mask, georeference and tags (not their bytes: GDAL may
lay blocks out differently); GeoPackages by their features read back (the file holds
write times); JSON with the timing fields taken out; other text and PNGs by their bytes
(PNG pixels decoded). ``run.json`` (timings, engine) and the manifest are left out.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

#: JSON keys that hold wall-clock times or durations, which differ between any two runs.
TIMING_KEYS = {"seconds", "started", "finished", "seconds_per_tile", "pairs_per_second",
               "elapsed_s", "created"}
SKIP = {"run.json"}


def _drop_timing(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop_timing(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [_drop_timing(v) for v in obj]
    return obj


def _tif_digest(path: Path, run_dir: Path) -> str:
    import rasterio

    h = hashlib.sha256()
    with rasterio.open(path) as ds:
        h.update(np.ascontiguousarray(ds.read()).tobytes())
        h.update(np.ascontiguousarray(ds.dataset_mask()).tobytes())
        h.update(repr((tuple(ds.transform), ds.crs.to_wkt() if ds.crs else None,
                       ds.dtypes, ds.nodata,
                       sorted((k, v.replace(str(run_dir), "<run>"))
                              for k, v in ds.tags().items()),
                       ds.descriptions)).encode())
    return h.hexdigest()


def _gpkg_digest(path: Path) -> str:
    import pyogrio

    h = hashlib.sha256()
    for name, _ in pyogrio.list_layers(path):
        df = pyogrio.read_dataframe(path, layer=name)
        h.update(name.encode())
        h.update(df.to_json(sort_keys=True, default=str).encode())
    return h.hexdigest()


def _png_digest(path: Path) -> str:
    from PIL import Image

    with Image.open(path) as im:
        return hashlib.sha256(np.asarray(im).tobytes()).hexdigest()


def output_digests(run_dir: Path) -> dict[str, str]:
    """{path relative to ``run_dir``: digest} of every output file."""
    out: dict[str, str] = {}
    for path in sorted(run_dir.rglob("*")):
        rel = path.relative_to(run_dir)
        if not path.is_file() or rel.parts[0] in {".geosim", "sample_site"} \
                or rel.as_posix() in SKIP or path.name.startswith("."):
            continue
        suffix = path.suffix.lower()
        if suffix in {".tif", ".tiff"}:
            out[rel.as_posix()] = _tif_digest(path, run_dir)
        elif suffix == ".gpkg":
            out[rel.as_posix()] = _gpkg_digest(path)
        elif suffix == ".png":
            out[rel.as_posix()] = _png_digest(path)
        elif suffix == ".json":
            doc = _drop_timing(json.loads(path.read_text().replace(str(run_dir), "<run>")))
            out[rel.as_posix()] = hashlib.sha256(
                json.dumps(doc, sort_keys=True).encode()).hexdigest()
        else:
            out[rel.as_posix()] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def differing(a: dict[str, str], b: dict[str, str]) -> list[str]:
    """Paths present in only one of two digests, or whose digests differ."""
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
