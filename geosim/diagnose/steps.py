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
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
from affine import Affine
from rasterio.crs import CRS
from rasterio.warp import transform_bounds

from geosim.diagnose.engine import diagnose_arrays
from geosim.diagnose.locate import laplacian_variance
from geosim.diagnose.report import write_diagnosis
from geosim.diagnose.report_figures import DEFAULT_DPI
from geosim.diagnose.simulate import QSimulator
from geosim.engine import parallel_map
from geosim.errors import DiagnosisError, ExtentError
from geosim.io.atomic import to_jsonable
from geosim.io.paths import safe_name, unique_name
from geosim.io.raster import RasterData, open_raster, read_valid_mask, read_window
from geosim.physics.radiometry import luma
from geosim.prepare.grid import sat_grid_offset
from geosim.prepare.reproject import reproject_to_array
from geosim.result import StepResult
from geosim.rundir import RunDir, RunPath

__all__ = ["run_diagnose", "run_diagnose_images", "diagnose_images", "calibrate_q_lv",
           "diagnose_grids"]

MAX_SAT_PX = 384


def calibrate_q_lv(sim: QSimulator, real_grey: np.ndarray, valid: np.ndarray, *,
                   q_min: float = 0.5, q_max: float = 8.0, quantized: bool = True) -> float:
    """Q at which the paper model's Laplacian variance equals the real scene's.

    The project's calibration (:func:`geosim.degrade.calibrate.calibrate_q`: a bracketed
    root finder that also accounts for the LV that rounding to whole DN adds, and raises
    :class:`~geosim.errors.CalibrationError` when the target is outside the bracket).
    """
    from geosim.degrade.calibrate import calibrate_q
    from geosim.errors import CalibrationError

    target = laplacian_variance(real_grey, valid)
    lo = max(q_min, sim.q_min)
    try:
        return float(calibrate_q(sim.uav, sim.valid, target, phi=sim.phi, q_min=lo,
                                 q_max=q_max, quantized=quantized, name="UAV image"))
    except CalibrationError:
        # noise (or compression) can make the scene look sharper than the sharpest
        # simulation: that is a finding for the diagnosis, whose baseline is then the
        # sharpest Q; anything else (flat scene, no overlap) is still an error
        if np.isfinite(target) and target > laplacian_variance(luma(sim(lo)), valid):
            import warnings

            warnings.warn(f"the satellite scene looks sharper (LV {target:.4g}) than the "
                          f"sharpest simulation (Q = {lo:g}); the diagnosis baseline is "
                          f"Q = {lo:g} (noise or compression raise the LV)", stacklevel=2)
            return float(lo)
        raise


def _central_window(valid: np.ndarray, max_px: int) -> tuple[slice, slice]:
    rows = np.flatnonzero(valid.any(axis=1))
    cols = np.flatnonzero(valid.any(axis=0))
    if rows.size == 0:
        raise ExtentError("satellite scene on the grid: no valid pixel in the common extent; "
                          "check that UAV and satellite images overlap")
    rc, cc = (rows[0] + rows[-1]) // 2, (cols[0] + cols[-1]) // 2
    h = min(max_px, rows[-1] - rows[0] + 1)
    w = min(max_px, cols[-1] - cols[0] + 1)
    r0 = max(0, rc - h // 2)
    c0 = max(0, cc - w // 2)
    return slice(r0, r0 + h), slice(c0, c0 + w)


@dataclass(frozen=True)
class FlightPixels:
    """What one flight's diagnosis reads: a satellite window and the UAV pixels under it.

    Attributes
    ----------
    uav
        The flight on the UAV grid nested in the satellite window (pixel size
        ``sat.transform.a / phi``, same origin).
    sat
        The satellite scene's window (its ``transform`` and ``crs`` place every output).
    q_base
        Calibrated Q to start from (None: calibrate here by Laplacian variance).
    sources
        Input files, recorded in the provenance tags.
    """

    uav: RasterData
    sat: RasterData
    q_base: float | None = None
    sources: tuple[str, ...] = ()

    @classmethod
    def of_arrays(cls, uav: np.ndarray, sat: np.ndarray, *, sat_transform: Affine, crs: CRS,
                  phi: int, uav_valid: np.ndarray | None = None,
                  sat_valid: np.ndarray | None = None, q_base: float | None = None
                  ) -> FlightPixels:
        """From in-memory ``(bands, rows, cols)`` arrays: the UAV grid is the satellite
        window's grid refined ``phi`` times (same origin); masks default to all valid."""
        def data(a: np.ndarray, valid: np.ndarray | None, t: Affine) -> RasterData:
            v = np.ones(a.shape[-2:], bool) if valid is None else np.asarray(valid, bool)
            return RasterData(array=a, valid=v, transform=t, crs=crs,
                              band_names=(None,) * a.shape[0])

        return cls(uav=data(uav, uav_valid, sat_transform * Affine.scale(1.0 / phi)),
                   sat=data(sat, sat_valid, sat_transform), q_base=q_base)


def diagnose_grids(pixels: FlightPixels, out_dir: Path, *, phi: int, seed: int = 0,
                   q_min: float = 0.5, q_max: float = 8.0, extra: dict[str, Any] | None = None,
                   dpi: int = DEFAULT_DPI) -> dict[str, Any]:
    """Diagnose one flight's co-gridded pixels (UAV at sat/phi, satellite at the sat grid)
    and write diagnosis.json, GeoTIFFs and figures (at ``dpi``) into ``out_dir``."""
    sat_transform, crs = pixels.sat.transform, pixels.sat.crs
    uav, sat = common_bands(pixels.uav.array, pixels.sat.array)
    sim = QSimulator(uav.astype(np.float32), phi=phi, valid=pixels.uav.valid, q_min=0.6)
    s0 = sim(2.0)
    valid = pixels.sat.valid & sim_valid(pixels.uav.valid, phi, s0.shape[-2:])
    q_base = pixels.q_base
    if q_base is None:
        q_base = calibrate_q_lv(sim, luma(sat), valid, q_min=q_min, q_max=q_max)
    diag = diagnose_arrays(sat, sim, q_base=q_base, rng=np.random.default_rng(seed),
                           valid=valid, gsd_m=abs(sat_transform.a), q_lo=0.7)
    return write_diagnosis(diag, out_dir, transform=sat_transform, crs=crs,
                           sources=list(pixels.sources), extra=extra, dpi=dpi)


def common_bands(uav: np.ndarray, sat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two images with the same bands: both as they are, or both grey (luma).

    A grey (1-band) flight or satellite scene says nothing about colour, so when one
    image is grey and the other RGB the RGB one is compared by its luma (BT.601).

    Parameters
    ----------
    uav, sat
        (bands, rows, cols) arrays, DN; 1 or >= 3 bands each.
    """
    nu, ns = uav.shape[0], sat.shape[0]
    if nu == ns:
        return uav, sat
    if 1 not in (nu, ns):
        raise DiagnosisError(f"UAV imagery has {nu} band(s) and the satellite scene {ns}; "
                             "give both the same bands (RGB) or one of them grey")
    if nu > 1:
        uav = luma(uav)[np.newaxis].astype(uav.dtype, copy=False)
    if ns > 1:
        sat = luma(sat)[np.newaxis].astype(np.float32, copy=False)
    return uav, sat


def sim_valid(uav_valid: np.ndarray, phi: int, shape: tuple[int, int]) -> np.ndarray:
    r, c = shape
    v = uav_valid[: r * phi, : c * phi].reshape(r, phi, c, phi)
    return v.all(axis=(1, 3))


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


def _flight_dir(flight: str, taken: set[str]) -> str:
    """A folder name for a flight id (safe characters only, unique)."""
    name = unique_name(safe_name(flight, default="flight"), taken | {"diagnosis"})
    taken.add(name)
    return name


@dataclass(frozen=True)
class DiagnoseFlightTask:
    """One flight to diagnose: ``load()`` reads its :class:`FlightPixels` (picklable)."""

    flight: str
    load: Callable[[], FlightPixels]
    out_dir: Path
    phi: int
    seed: int
    q_min: float
    q_max: float
    dpi: int = DEFAULT_DPI
    #: Resumable when set: (run folder, the files ``load`` reads) — a rerun with the same
    #: inputs and parameters reuses the flight's diagnosis instead of making it again.
    resume: tuple[Path, tuple[Path, ...]] | None = None


def _diagnose_one(task: DiagnoseFlightTask) -> tuple[dict[str, Any] | None, str | None]:
    try:
        doc = diagnose_grids(task.load(), task.out_dir, phi=task.phi, seed=task.seed,
                             q_min=task.q_min, q_max=task.q_max,
                             extra={"flight": task.flight}, dpi=task.dpi)
    except (DiagnosisError, ExtentError) as exc:
        return None, str(exc)
    # through JSON (NaN kept), so that a fresh and a reused diagnosis are the same values
    return to_jsonable(doc), None


def diagnose_flight_task(task: DiagnoseFlightTask) -> tuple[dict[str, Any] | None, str | None]:
    """Diagnose one flight into ``task.out_dir``: (diagnosis.json dict, None), or
    (None, why) when it cannot be diagnosed (too little overlap, no usable data).

    With ``task.resume`` the flight's diagnosis is skipped when its manifest entry is
    current (same input files, parameters and output files); the dict then comes from
    the entry (``"skipped": true`` is not added: callers count skips with
    :func:`diagnosis_was_current`).
    """
    if task.resume is None:
        return _diagnose_one(task)
    from geosim import manifest

    run_dir, inputs = task.resume
    key = f"diagnosis/{task.out_dir.name}/flight"
    params = {"step": "diagnose", "flight": task.flight, "phi": task.phi, "seed": task.seed,
              "q_min": task.q_min, "q_max": task.q_max, "dpi": task.dpi,
              "dir": task.out_dir.name, "max_sat_px": MAX_SAT_PX}
    recorded = _recorded_files(run_dir, key)
    entry = manifest.cached(run_dir, key, inputs, params, outputs=recorded)
    if entry is not None and recorded and isinstance(entry.get("result"), dict):
        return entry["result"], _CURRENT
    doc, why = _diagnose_one(task)
    if doc is not None:
        outputs = sorted(p for p in task.out_dir.rglob("*") if p.is_file())
        manifest.record(run_dir, key, inputs, params, outputs=outputs, result=doc)
    return doc, why


#: ``why`` of a diagnosis reused from the manifest (the dict is returned with it).
_CURRENT = "already current"


def diagnosis_was_current(result: tuple[dict[str, Any] | None, str | None]) -> bool:
    """Whether :func:`diagnose_flight_task` reused a current diagnosis."""
    return result[0] is not None and result[1] == _CURRENT


def _recorded_files(run_dir: Path, key: str) -> list[Path]:
    """The output files a manifest entry lists (to check they are still those files)."""
    from geosim import manifest

    try:
        entry = json.loads((Path(run_dir) / manifest.MANIFEST_DIR / f"{key}.json").read_text())
        return [Path(run_dir) / rel for rel in entry["outputs"]]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def diagnose_flights(loaders: list[tuple[str, Callable[[], FlightPixels]]], out_dir: Path, *,
                     reference: str | None, phi: int, seed: int = 0, q_min: float = 0.5,
                     q_max: float = 8.0, dpi: int = DEFAULT_DPI,
                     resume: dict[str, tuple[Path, tuple[Path, ...]]] | None = None,
                     counts: dict[str, int] | None = None) -> dict[str, Any]:
    """Diagnose several flights one at a time and write the combined verdict.

    Parameters
    ----------
    loaders
        (flight id, load) pairs in site order; ``load()`` returns the flight's
        :class:`FlightPixels`, or raises :class:`~geosim.errors.DiagnosisError` /
        ``ExtentError`` when the flight cannot be diagnosed (it is then skipped, with the
        reason in ``flights_skipped``).
    reference
        The flight whose GeoTIFFs, maps and plots are copied to the top level (default,
        or when it was skipped: the first diagnosed flight).
    resume
        Per flight, (run folder, the files its ``load`` reads): its diagnosis is reused
        when current (:func:`diagnose_flight_task`).
    counts
        Filled with ``skipped_current``: flights whose diagnosis was reused.

    Returns
    -------
    dict
        The combined diagnosis.json dict.
    """
    from geosim.diagnose.report import write_combined

    per: dict[str, dict[str, Any]] = {}
    dirs: dict[str, str] = {}
    skipped: dict[str, str] = {}
    taken: set[str] = set()
    tasks = [DiagnoseFlightTask(fid, load, out_dir / _flight_dir(fid, taken), phi=phi,
                                seed=seed + 1000 * i, q_min=q_min, q_max=q_max, dpi=dpi,
                                resume=(resume or {}).get(fid))
             for i, (fid, load) in enumerate(loaders)]
    results = parallel_map(diagnose_flight_task, tasks, desc="diagnose flights")
    if counts is not None:
        counts["skipped_current"] = sum(map(diagnosis_was_current, results))
    for task, (doc, why) in zip(tasks, results, strict=True):
        if doc is None:
            skipped[task.flight] = why or ""
        else:
            per[task.flight], dirs[task.flight] = doc, task.out_dir.name
    if not per:
        raise DiagnosisError(f"{out_dir}: no flight could be diagnosed against the satellite "
                             "scene (" + "; ".join(f"{k}: {v}" for k, v in skipped.items())
                             + "); give flights that overlap the satellite scene")
    ref = reference if reference in per else next(iter(per))
    return write_combined(per, out_dir, reference=ref, dirs=dirs, skipped=skipped, dpi=dpi)


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
        rs, cs = _central_window(svalid, MAX_SAT_PX)
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
              for p in _recorded_files(run.root, f"diagnosis/{d.get('dir')}/flight")}
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
