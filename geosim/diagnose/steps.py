"""File layer of the diagnosis: read grids, build the baseline, run, write.

* :func:`run_diagnose` — pipeline step: reads ``out_dir/grid/satellite.tif``
  (0.5 m shared grid), every flight on the aligned 0.05 m grid (read through its composed
  warp from the original file, :mod:`geosim.prepare.aligned`) and
  ``out_dir/calibration.json``; writes ``out_dir/diagnosis/``.
* :func:`diagnose_images` — standalone: any-CRS UAV and satellite GeoTIFFs are
  reprojected onto a shared nested grid (UAV ``phi`` × finer) over their common
  extent, then diagnosed.

Every flight that overlaps the satellite scene is diagnosed on its own (one at a time,
so only one flight's window is in memory), into ``diagnosis/<flight>/``; the combined
verdict (:mod:`geosim.diagnose.combine`) and copies of the reference flight's GeoTIFFs,
maps and plots are written to ``diagnosis/`` itself.

The diagnosis works on one window of at most ``max_sat_px`` × ``max_sat_px``
satellite pixels at the centre of the common valid area (the UAV part of it is
``phi``² times larger and must fit in memory).

One flight's pixels and their diagnosis: :mod:`~geosim.diagnose.grids`; several flights
and the combined verdict: :mod:`~geosim.diagnose.flights`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.warp import transform_bounds

from geosim.diagnose.flights import diagnose_flights, recorded_files
from geosim.diagnose.grids import MAX_SAT_PX, FlightPixels, central_window
from geosim.diagnose.report_figures import DEFAULT_DPI
from geosim.errors import ExtentError
from geosim.io.paths import unique_name
from geosim.io.raster import RasterData, open_raster, read_valid_mask, read_window
from geosim.prepare.grid import sat_grid_offset
from geosim.prepare.reproject import reproject_to_array
from geosim.result import StepResult
from geosim.rundir import RunDir, RunPath

__all__ = ["run_diagnose", "run_diagnose_images", "diagnose_images"]


def _summary(doc: dict[str, Any], out: Path) -> dict[str, Any]:
    base, ref = doc["baseline"], doc["refined"]
    claimed = ", ".join(e["name"] for e in doc["effects"]) or "none"
    flights = doc.get("flights") or {}
    n = len(flights)
    head = (f"{n} flights, majority verdict: " if n > 1 else "")
    text = (f"{head}Q {base['q']:.2f} (LV) -> {ref['q']:.2f} refitted; claimed: {claimed}; "
            f"RMSE {base['rmse']:.2f} -> {ref['rmse']:.2f} DN, spectral error "
            f"{base['spectral_error']:.3f} -> {ref['spectral_error']:.3f}")
    out_d: dict[str, Any] = {
        "text": text, "out": str(out), "q_base": base["q"], "q_refined": ref["q"],
        "effects": {e["name"]: e["params"] for e in doc["effects"]},
        "rmse": [doc["baseline"]["rmse"], doc["refined"]["rmse"]],
        "spectral_error": [doc["baseline"]["spectral_error"], doc["refined"]["spectral_error"]]}
    if flights:
        out_d["reference_flight"] = doc.get("reference_flight")
        out_d["flights"] = {
            f: {"q_base": d["baseline"]["q"], "q_refined": d["refined"]["q"],
                "claimed": [e["name"] for e in d["effects"]],
                "spectral_error": [d["baseline"]["spectral_error"],
                                   d["refined"]["spectral_error"]]}
            for f, d in flights.items()}
        if doc.get("flights_skipped"):
            out_d["flights_skipped"] = doc["flights_skipped"]
    return out_d


def _read_q_base(path: Path, flight: str) -> float | None:
    """The calibrated Q for ``flight`` from calibration.json (its own Q, else the mean)."""
    if not path.is_file():
        return None
    data = json.loads(path.read_text())
    for f in data.get("flights", []) or []:
        if isinstance(f, dict) and f.get("flight") == flight and f.get("status", "ok") == "ok" \
                and isinstance(f.get("q"), (int, float)):
            return float(f["q"])
    for key in ("mean_q", "q"):
        if isinstance(data.get(key), (int, float)):
            return float(data[key])
    return None


def _read_flight(run: RunDir, sat_path: Path, aligned: Any, phi: int) -> FlightPixels:
    """The satellite window over one aligned flight (a
    :class:`geosim.prepare.aligned.AlignedFlight`) and the flight's UAV pixels under it."""
    flight = aligned.flight
    uav_path = aligned.path or aligned.warp.src_path
    with open_raster(sat_path, what="satellite on grid") as ds, aligned.open() as du:
        row_off, col_off = sat_grid_offset(du.transform, ds.transform, phi,
                                           f"aligned flight {flight}")
        # satellite pixels fully inside the aligned flight's extent
        r0, c0 = max(row_off, 0), max(col_off, 0)
        r1 = min(row_off + du.height // phi, ds.height)
        c1 = min(col_off + du.width // phi, ds.width)
        if c1 - c0 < 16 or r1 - r0 < 16:
            raise ExtentError(f"{uav_path} and {sat_path} overlap by less than 16 satellite "
                              "pixels; the diagnosis needs a common extent")
        inner = rasterio.windows.Window(c0, r0, c1 - c0, r1 - r0)
        svalid = read_valid_mask(ds, inner)
        rs, cs = central_window(svalid, MAX_SAT_PX)
        win = rasterio.windows.Window(c0 + cs.start, r0 + rs.start, cs.stop - cs.start,
                                      rs.stop - rs.start)
        sat = read_window(ds, win, max_bands=3, out_dtype=np.float64, path=sat_path)
        uwin = rasterio.windows.Window((win.col_off - col_off) * phi,
                                       (win.row_off - row_off) * phi,
                                       win.width * phi, win.height * phi)
        array, valid = du.read(uwin, n_bands=3)
        uav = RasterData(array=array.astype(np.float32), valid=valid,
                         transform=du.transform @ Affine.translation(int(uwin.col_off),
                                                                     int(uwin.row_off)),
                         crs=du.crs, band_names=tuple(du.descriptions[:array.shape[0]]),
                         path=Path(uav_path))
    return FlightPixels(uav=uav, sat=sat, q_base=_read_q_base(run.calibration_json, flight),
                        sources=(str(sat_path), str(uav_path)))


def run_diagnose(site: Any, out: RunPath, *, dpi: int = DEFAULT_DPI) -> StepResult:
    """Pipeline step ``diagnose``: reads the run folder, writes ``diagnosis/`` in it.

    Every flight of the site is diagnosed against the satellite scene (flights without
    enough overlap are skipped and listed); the record is the combined verdict.
    """
    run = RunDir.of(out)
    sat_path = run.require_satellite_grid()
    started = time.time()
    reference = site.reference_flight if site.reference_flight else site.flights[0].id
    phi = site.parameters.phi

    from geosim.prepare.aligned import aligned_flights

    flights = aligned_flights(site, run)
    loaders = [(fid, functools.partial(_read_flight, run, sat_path, flights[fid], phi))
               for fid in flights]
    resume = {fid: (run.root, _flight_inputs(run, sat_path, flights[fid])) for fid in flights}
    counts: dict[str, int] = {}
    doc = diagnose_flights(loaders, run.diagnosis_dir, reference=reference, phi=phi,
                           q_min=site.parameters.q_min, q_max=site.parameters.q_max, dpi=dpi,
                           resume=resume, counts=counts)
    summary = _summary(doc, run.diagnosis_dir)
    n_skipped = counts.get("skipped_current", 0)
    if n_skipped:
        summary["text"] += (f"; {n_skipped} of {len(site.flights)} flight diagnoses already "
                            "current, skipped")
    # the bundled sample site ships its ground truth: put fitted and true side by side
    site_path = getattr(site, "path", None)
    truth_path = Path(site_path).parent / "truth.json" if site_path else None
    if truth_path is not None and truth_path.is_file():
        from geosim.diagnose.truth_compare import compare_with_truth, format_truth_comparison
        from geosim.io.atomic import write_text

        rows = compare_with_truth(doc, json.loads(truth_path.read_text()))
        summary["truth_comparison"] = rows
        write_text(run.diagnosis_dir / "truth_comparison.txt", format_truth_comparison(rows)
                   + "\n(fitted = the combined verdict over the diagnosed flights: medians of "
                     "the flights that claimed each effect; haze is fitted relative to the "
                     "flights' radiometry (each flight's exposure and white balance divide the "
                     "transmission; with an exposure seam, relative to the brighter side of "
                     "the seam), truth.json gives it relative to the true ground; "
                     "misregistration is the reference flight's, compared with the "
                     "satellite-minus-reference-flight offset in truth.json)\n")
    text = summary.pop("text")
    # the diagnosis writes many files (some through matplotlib): record those written now
    # ... and those of the flights whose diagnosis was reused (still the recorded files)
    reused = {p for d in (doc.get("flights") or {}).values() if isinstance(d, dict)
              for p in recorded_files(run.root, f"diagnosis/{d.get('dir')}/flight")}
    outputs = [run.rel(p) for p in sorted(run.diagnosis_dir.rglob("*"))
               if p.is_file() and (p.stat().st_mtime >= started - 1.0 or p in reused)]
    summary["skipped_current"] = n_skipped
    return StepResult(summary=text, outputs=outputs, record=summary)


def _flight_inputs(run: RunDir, sat_path: Path, aligned: Any) -> tuple[Path, ...]:
    """The files :func:`_read_flight` reads for a flight (its diagnosis' manifest inputs);
    ``alignment.json`` too, for the flight's correction."""
    files = [sat_path, *(Path(p) for p in aligned.sources)]
    files += [p for p in (run.alignment_json, run.calibration_json) if p.is_file()]
    return tuple(files)


def diagnose_images(uav_paths: list[str | Path], satellite_path: str | Path,
                    out_dir: str | Path, *, uav_gsd_m: float = 0.05, sat_gsd_m: float = 0.5,
                    crs: str | None = None, seed: int = 0, q_min: float = 0.5,
                    q_max: float = 8.0, max_sat_px: int = MAX_SAT_PX, dpi: int = DEFAULT_DPI
                    ) -> dict[str, Any]:
    """Standalone diagnosis from GeoTIFFs in any CRS, every ``--uav`` against the satellite.

    The satellite's CRS is used when projected (else the UTM zone of its centre, or
    ``crs``). For each UAV image, the common extent with the satellite is snapped to the
    satellite GSD, both are reprojected (cubic) onto nested grids, and the central window
    of at most ``max_sat_px`` satellite pixels is diagnosed (into ``out_dir/<stem>/``);
    UAV images that overlap the satellite by less than 16 pixels are skipped. The first
    diagnosed image is the reference (its GeoTIFFs are copied to ``out_dir``) and the
    combined verdict is written to ``out_dir/diagnosis.json``. Each image keeps its own
    georeference (no alignment between them), so misregistration is per image.
    """
    from geosim.prepare.grid import gsd_ratio, utm_crs_for_lonlat

    phi = gsd_ratio(uav_gsd_m, sat_gsd_m)
    sat_path = Path(satellite_path)
    with open_raster(sat_path, what="--satellite") as ds:
        if crs is not None:
            dst_crs = CRS.from_user_input(crs)
        elif ds.crs.is_projected:
            dst_crs = ds.crs
        else:
            b = transform_bounds(ds.crs, "EPSG:4326", *ds.bounds)
            dst_crs = utm_crs_for_lonlat((b[0] + b[2]) / 2, (b[1] + b[3]) / 2)
        sb = transform_bounds(ds.crs, dst_crs, *ds.bounds)

    def load(uav_path: Path) -> FlightPixels:
        with open_raster(uav_path, what="--uav") as du:
            ub = transform_bounds(du.crs, dst_crs, *du.bounds)
        left, bottom = max(sb[0], ub[0]), max(sb[1], ub[1])
        right, top = min(sb[2], ub[2]), min(sb[3], ub[3])
        if right - left < 16 * sat_gsd_m or top - bottom < 16 * sat_gsd_m:
            raise ExtentError(f"--uav {uav_path} and --satellite {sat_path} overlap by less "
                              "than 16 satellite pixels; give images of the same place")
        cx, cy = (left + right) / 2, (top + bottom) / 2
        half = max_sat_px * sat_gsd_m / 2
        left, right = max(left, cx - half), min(right, cx + half)
        bottom, top = max(bottom, cy - half), min(top, cy + half)
        left = np.ceil(left / sat_gsd_m) * sat_gsd_m
        top = np.floor(top / sat_gsd_m) * sat_gsd_m
        w = int(np.floor((right - left) / sat_gsd_m))
        h = int(np.floor((top - bottom) / sat_gsd_m))
        st = Affine(sat_gsd_m, 0, left, 0, -sat_gsd_m, top)
        ut = Affine(uav_gsd_m, 0, left, 0, -uav_gsd_m, top)
        sat = reproject_to_array(sat_path, crs=dst_crs, transform=st, shape=(h, w),
                                 max_bands=3, what="--satellite")
        uav = reproject_to_array(uav_path, crs=dst_crs, transform=ut, shape=(h * phi, w * phi),
                                 max_bands=3, what="--uav")
        return FlightPixels(uav=uav, sat=dataclasses.replace(sat, array=sat.array.astype(float)),
                            sources=(str(sat_path), str(uav_path)))

    ids: list[str] = []
    taken: set[str] = set()
    loaders = []
    for p in uav_paths:
        fid = unique_name(Path(p).stem, taken)
        ids.append(fid)
        loaders.append((fid, lambda p=Path(p): load(p)))
    out = Path(out_dir)
    doc = diagnose_flights(loaders, out, reference=ids[0], phi=phi, seed=seed, q_min=q_min,
                           q_max=q_max, dpi=dpi)
    return _summary(doc, out)


def run_diagnose_images(site: Any, out: RunPath, *, seed: int = 0, dpi: int = DEFAULT_DPI
                        ) -> StepResult:
    """Pipeline step of ``geosim diagnose --uav ... --satellite ...`` (standalone).

    The site's flights (any CRS, as given) are diagnosed against its satellite scene with
    :func:`diagnose_images`, written into the run folder itself (``diagnosis.json``,
    ``report.md``, ``<flight>/``), at the site's ``uav_gsd_m`` and ``sat_gsd_m``.
    """
    run = RunDir.of(out)
    started = time.time()
    p = site.parameters
    summary = diagnose_images([f.image for f in site.flights], site.satellite.image, run.root,
                              uav_gsd_m=p.uav_gsd_m, sat_gsd_m=p.sat_gsd_m, seed=seed,
                              q_min=p.q_min, q_max=p.q_max, dpi=dpi)
    text = summary.pop("text")
    outputs = [run.rel(f) for f in sorted(run.root.rglob("*"))
               if f.is_file() and f != run.run_json and f.stat().st_mtime >= started - 1.0]
    return StepResult(summary=text, outputs=outputs, record=summary)
