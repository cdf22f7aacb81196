"""Writing a diagnosis: GeoTIFFs, regions.geojson, diagnosis.json, plots and report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import Diagnosis
from geosim.diagnose.fit import HANN_CORRELATION
from geosim.diagnose.spectra import directional_profiles, polar_bin_mean, radial_profile
from geosim.io.atomic import atomic_path, to_jsonable, write_json, write_text
from geosim.io.raster import provenance_tags, write_geotiff

__all__ = ["write_diagnosis", "write_combined", "FILES", "compare_with_truth",
           "format_truth_comparison", "mismatch_maps_figure", "map_extent", "scale_bar_length",
           "draw_scale_bar", "flights_figure", "DEFAULT_DPI"]

FILES = {"satellite": "satellite_on_grid.tif", "baseline": "sim_baseline.tif",
         "refined": "sim_refined.tif"}
MAPS = {"residual_energy": "map_residual_energy.tif", "blur_ratio": "map_blur_ratio.tif",
        "gain": "map_gain.tif", "offset": "map_offset.tif"}



DEFAULT_DPI = 100


def _save_png(fig: Any, path: Path, *, dpi: int, tight: bool = True) -> str:
    """Write a figure as PNG atomically, close it, and return the file name.

    The figure's title (its ``suptitle``) is also stored as the PNG's ``Title`` text
    chunk, so a reader of the file alone knows which flight it shows.
    """
    import matplotlib.pyplot as plt

    if tight:
        fig.tight_layout()
    title = fig._suptitle.get_text() if fig._suptitle is not None else ""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png", metadata={"Title": title} if title else None)
    plt.close(fig)
    return path.name


def map_extent(transform: Affine, shape: tuple[int, int]) -> tuple[float, float, float, float]:
    """``imshow`` extent (left, right, bottom, top) in map units of a north-up raster.

    Parameters
    ----------
    transform
        The raster's affine transform (no rotation).
    shape
        (rows, cols) of the raster.
    """
    rows, cols = shape
    x0, y0 = transform * (0, 0)
    x1, y1 = transform * (cols, rows)
    return (min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1))


def scale_bar_length(width_m: float) -> float:
    """A round length (1, 2 or 5 × 10^k metres) close to a fifth of ``width_m``."""
    if not np.isfinite(width_m) or width_m <= 0:
        raise ValueError(f"map width {width_m} m: needs a positive width")
    target = width_m / 5.0
    k = np.floor(np.log10(target))
    steps = np.array([1.0, 2.0, 5.0, 10.0]) * 10.0 ** k
    return float(steps[np.argmin(np.abs(np.log(steps / target)))])


def _format_m(length_m: float) -> str:
    return f"{length_m:g} m" if length_m < 1000 else f"{length_m / 1000:g} km"


def draw_scale_bar(ax: Any, extent: tuple[float, float, float, float]) -> tuple[float, str]:
    """Draw a scale bar in the lower left of a map axes; returns (length in m, label).

    The bar is a line in data (map) coordinates, so its length in map units is the
    labelled length.
    """
    left, right, bottom, top = extent
    length = scale_bar_length(right - left)
    x0 = left + 0.05 * (right - left)
    y0 = bottom + 0.06 * (top - bottom)
    label = _format_m(length)
    ax.plot([x0, x0 + length], [y0, y0], color="white", lw=4, solid_capstyle="butt",
            gid="scale_bar_halo")
    ax.plot([x0, x0 + length], [y0, y0], color="black", lw=2, solid_capstyle="butt",
            gid="scale_bar")
    ax.text(x0 + length / 2, y0 + 0.02 * (top - bottom), label, ha="center", va="bottom",
            fontsize=8, color="black", gid="scale_bar_label",
            bbox={"facecolor": "white", "alpha": 0.7, "lw": 0, "pad": 1})
    return length, label


def _crs_name(crs: CRS) -> str:
    """'WGS 84 / UTM zone 56S, EPSG:32756' (pyproj's name and the EPSG code when known)."""
    from pyproj import CRS as ProjCRS

    epsg = crs.to_epsg()
    name = ProjCRS.from_user_input(crs.to_wkt()).name
    return f"{name}, EPSG:{epsg}" if epsg is not None else name


def _flight_title(flight: str | None) -> str:
    return f"flight {flight}" if flight else "diagnosis"


def _regions_gdf(diag: Diagnosis, transform: Affine, crs: CRS):
    import geopandas as gpd
    from rasterio import features
    from shapely.geometry import shape

    rows = []
    if diag.labels is not None:
        by_label = {r.label: r for r in diag.regions}
        lab = diag.labels.astype(np.int32)
        for geom, val in features.shapes(lab, mask=lab > 0, transform=transform):
            reg = by_label.get(int(val))
            if reg is None:
                continue
            rows.append({"rank": reg.rank, "kind": reg.kind, "area_m2":
                         reg.area_px * abs(transform.a * transform.e),
                         "excess_energy_dn2": reg.excess_energy,
                         "mean_ratio": reg.mean_ratio, "geometry": shape(geom)})
    gdf = gpd.GeoDataFrame(rows, columns=["rank", "kind", "area_m2", "excess_energy_dn2",
                                          "mean_ratio", "geometry"], geometry="geometry", crs=crs)
    if len(gdf):
        gdf = gdf.dissolve(by="rank", as_index=False, aggfunc="first").sort_values("rank")
    return gdf


def _plots(diag: Diagnosis, out: Path, *, transform: Affine, crs: CRS, flight: str | None,
           dpi: int) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = diag.plots
    fy, fx = p["fy"], p["fx"]
    n_rad = max(4, min(16, fy.shape[0] // 2 - 1))  # no finer than the block's FFT grid
    written = []
    # 1. transfer functions: radial, by direction (relative to the baseline), power spectra
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    ax = axes[0]
    f, _, m_real, cnt = polar_bin_mean(p["t_real"], fy, fx, n_radial=n_rad)
    _, _, v_real, _ = polar_bin_mean(p["t_real_var"], fy, fx, n_radial=n_rad)
    # σ of a bin mean: var / (samples / Hann spread); both half-planes hold the same values
    sig = np.sqrt(v_real[0] * HANN_CORRELATION / np.maximum(cnt[0] / 2.0, 1.0))
    ax.fill_between(f, m_real[0] - sig, m_real[0] + sig, color="0.8", label="real ±1σ")
    ax.plot(f, m_real[0], "k-", label="real scene (cross-spectral H1)")
    for key, lab, st in (("t_base", f"baseline, Q={p['q_base']:.2f}, × g={p['gain_base']:.2f}",
                          "C0--"),
                         ("t_refined", f"refined, Q={p['q_refined']:.2f} + effects, "
                          f"× g={p['gain_refined']:.2f}", "C3-")):
        fb, mb = radial_profile(p[key], fy, fx, n_bins=n_rad)
        ax.plot(fb, mb, st, label=lab)
    fc, c = radial_profile(p["coherence_base"], fy, fx, n_bins=n_rad)
    ax.plot(fc, c, "C2:", label="coherence γ² (real vs simulation)")
    ax.set_xlabel("spatial frequency (cycles per 0.5 m pixel)")
    ax.set_ylabel(f"|transfer| relative to the paper model at Q={p['q_ref']:.2f}")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7)
    ax.set_title("Radial transfer function (models as fitted)", fontsize=10)
    ax = axes[1]
    n_dir = max(4, n_rad * 3 // 4)
    with np.errstate(invalid="ignore", divide="ignore"):
        rr = p["t_real"] / p["t_base"]
        rf = p["t_refined"] / p["t_base"]
    f, ang, mr = directional_profiles(rr, fy, fx, n_sectors=4, n_bins=n_dir)
    _, _, mf = directional_profiles(rf, fy, fx, n_sectors=4, n_bins=n_dir)
    for i, a in enumerate(ang):
        ax.plot(f, mr[i], f"C{i}-", label=f"real, wave vector {a:.0f}° from north")
        ax.plot(f, mf[i], f"C{i}--")
    ax.axhline(1.0, color="0.5", lw=0.8)
    ax.set_xlabel("spatial frequency (cycles per pixel)")
    ax.set_ylabel("|transfer| / baseline model")
    ax.set_title("By direction, relative to the baseline (solid real, dashed refined)",
                 fontsize=10)
    ax.legend(fontsize=7)
    ax = axes[2]
    se_b, se_r = p["spectral_error"]
    for key, lab, st in (("p_real", "real scene", "k-"),
                         ("p_base", f"baseline (spectral error {se_b:.3f})", "C0--"),
                         ("p_refined", f"refined, with noise (spectral error {se_r:.3f})",
                          "C3-")):
        fp_, mp = radial_profile(p[key], fy, fx, n_bins=n_rad)
        ax.semilogy(fp_, mp, st, label=lab)
    ax.set_xlabel("spatial frequency (cycles per pixel)")
    ax.set_ylabel("power spectrum (DN², grey level)")
    ax.set_title("Power spectra of the images as delivered", fontsize=10)
    ax.legend(fontsize=7)
    fig.suptitle(f"Transfer functions and spectra, {_flight_title(flight)}", fontsize=11)
    written.append(_save_png(fig, out / "transfer_function.png", dpi=dpi, tight=True))
    # 2. noise vs brightness
    fig, ax = plt.subplots(figsize=(5.5, 4))
    if len(p["noise_brightness"]):
        ax.plot(p["noise_brightness"], p["noise_variance"], "ko",
                label="residual variance (high-passed, per brightness bin)")
        s = np.linspace(0, max(p["noise_brightness"]) * 1.05, 50)
        a, b = p["noise_model"]
        extra = " (b includes 1/12 DN² of rounding)" if p.get("quantized") else ""
        ax.plot(s, a * s + b, "C3-", label=f"fit var = {a:.3g}·s + {b:.3g}{extra}")
    ax.set_xlim(left=0)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("model brightness s (DN, per band)")
    ax.set_ylabel("noise variance (DN²)")
    ax.set_title("sensor_noise " + ("claimed" if p.get("noise_claimed") else "not claimed"),
                 fontsize=10)
    fig.suptitle(f"Noise vs brightness, {_flight_title(flight)}", fontsize=11)
    ax.legend(fontsize=7)
    written.append(_save_png(fig, out / "noise_vs_brightness.png", dpi=dpi, tight=True))
    # 3. maps
    fig = mismatch_maps_figure(diag, transform=transform, crs=crs, flight=flight)
    written.append(_save_png(fig, out / "mismatch_maps.png", dpi=dpi, tight=False))
    return written


def mismatch_maps_figure(diag: Diagnosis, *, transform: Affine, crs: CRS,
                         flight: str | None = None) -> Any:
    """The four mismatch maps in map coordinates, with a scale bar; returns the Figure.

    Parameters
    ----------
    diag
        The diagnosis (its ``maps`` and ``regions`` are drawn).
    transform, crs
        The 0.5 m grid of the maps: axes are easting / northing in metres of ``crs``.
    flight
        Named in the title ("flight X").
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    extent = map_extent(transform, diag.maps["residual_energy"].shape[-2:])
    fig, axes = plt.subplots(1, 4, figsize=(16, 4.6))
    for ax, (k, title) in zip(axes, (("residual_energy", "residual energy after refit (DN², log)"),
                                     ("blur_ratio", "LV real / LV baseline (log)"),
                                     ("gain", "local gain real vs baseline"),
                                     ("offset", "local offset (DN)")), strict=True):
        img = diag.maps[k]
        fin = img[np.isfinite(img)]
        if k in ("residual_energy", "blur_ratio") and fin.size and np.any(fin > 0):
            pos = fin[fin > 0]
            lo, hi = np.percentile(pos, [1, 99.5])
            if k == "blur_ratio":  # symmetric about 1 on a log scale
                span = max(hi, 1.0 / max(lo, 1e-6), 1.01)
                lo, hi = 1.0 / span, span
            im = ax.imshow(np.where(img > 0, img, np.nan), extent=extent,
                           norm=LogNorm(vmin=max(lo, 1e-6), vmax=max(hi, lo * 1.01)),
                           cmap="magma" if k == "residual_energy" else "RdBu_r")
        else:
            lo, hi = (np.percentile(fin, [2, 98]) if fin.size else (0.0, 1.0))
            im = ax.imshow(img, extent=extent, cmap="viridis", vmin=lo, vmax=max(hi, lo + 1e-6))
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("easting (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.ticklabel_format(useOffset=False, style="plain")
        draw_scale_bar(ax, extent)
        fig.colorbar(im, ax=ax, fraction=0.046)
    axes[0].set_ylabel(f"northing (m)\n{_crs_name(crs)}", fontsize=8)
    for r in diag.regions[:20]:
        r0, c0, r1, c1 = r.bbox
        (xa, ya), (xb, yb) = transform * (c0, r0), transform * (c1, r1)
        axes[0].add_patch(plt.Rectangle((min(xa, xb), min(ya, yb)), abs(xb - xa), abs(yb - ya),
                                        fill=False,
                                        ec="cyan" if r.kind == "scene_change" else "white"))
    fig.suptitle(f"Mismatch maps, {_flight_title(flight)}", fontsize=11)
    fig.text(0.01, 0.01, "boxes: regions (cyan scene_change, white global); maps 2–4 in blocks "
             "of 16 px against the co-registered baseline (gain/offset blank where the block "
             "correlation < 0.5); colour limits at robust percentiles", fontsize=8)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    return fig


def _markdown(s: dict[str, Any]) -> str:
    b, rf = s["baseline"], s["refined"]
    lines = ["# Diagnosis: where the paper's model and the real satellite scene differ", ""]
    lines.append(f"The baseline (the paper's model) matched the real scene's Laplacian variance "
                 f"({b['lv_satellite']:.3g}) with Q = {b['q']:.2f}; its RMSE is {b['rmse']:.2f} DN "
                 f"and its spectral error {b['spectral_error']:.3f} (RMS of log10 power ratio).")
    lines.append("")
    if not s["effects"]:
        lines.append("**No missing physics was found**: no effect improved the prediction of "
                     "held-out blocks by enough (block cross-validation), with its parameter "
                     "clearly away from its null, to be claimed.")
    else:
        lines.append("## Physics the model left out (in the order they were added)")
        lines.append("")
        for e in s["effects"]:
            params = ", ".join(f"{k} = {_f(v)}" for k, v in e["params"].items())
            lines.append(f"- **{e['name']}** ({params}). {e['explanation'].split(' Fitted:')[0]} "
                         f"Evidence: ΔBIC = {_f(e['delta_bic'])}"
                         + (f", held-out χ² {100 * e['heldout_gain']:.0f} % lower"
                            if e.get("heldout_gain") is not None else "")
                         + "; after adding it the RMSE is "
                         f"{e['rmse_after']:.2f} DN and the spectral error "
                         f"{e['spectral_error_after']:.3f}.")
            if e.get("indistinguishable_from"):
                lines.append(f"  - Caution: on these data it cannot be told apart from "
                             f"{', '.join(e['indistinguishable_from'])}.")
    lines.append("")
    lines.append(f"## Refit\n\nWith these effects the refitted Q is {rf['q']:.2f} "
                 f"(± {rf['q_sigma']:.2f}); it is "
                 + ("**within**" if rf["q_in_physical_range"] else "**outside**")
                 + f" the physical range {rf['physical_q_range'][0]}–{rf['physical_q_range'][1]} "
                 f"of real cameras. RMSE {b['rmse']:.2f} → {rf['rmse']:.2f} DN; spectral error "
                 f"{b['spectral_error']:.3f} → {rf['spectral_error']:.3f}.")
    claimed = {e["name"] for e in s["effects"]}
    weak = {k: v for k, v in s.get("candidates_delta_bic", {}).items()
            if k not in claimed and v is not None and v >= 2.0}
    if weak:
        lines.append("\nWeak evidence, not claimed (ΔBIC ≥ 2 but < 10, too small, or not "
                     "confirmed on held-out blocks): "
                     + ", ".join(f"{k} (ΔBIC {v:.1f})" for k, v in weak.items())
                     + ". Part of their blur may be absorbed in the refitted Q.")
    if s.get("ambiguities"):
        lines.append("\n## What the data cannot decide\n")
        for a in s["ambiguities"]:
            lines.append(f"- {a['note']}.")
    n_sc = sum(1 for e in s["effects"] if e["name"] == "scene_change")
    lines.append("\n## Where\n")
    lines.append(f"{s.get('n_regions', 0)} regions of significant mismatch are in "
                 f"`regions.geojson` (ranked; kind `scene_change` = object-sized local change, "
                 f"excluded from the physics fit; `global` = large areas). "
                 + ("Scene changes were found." if n_sc else "No object-sized scene change."))
    lines.append("\nMaps: `map_residual_energy.tif`, `map_blur_ratio.tif`, `map_gain.tif`, "
                 "`map_offset.tif`; plots: `transfer_function.png`, `noise_vs_brightness.png`, "
                 "`mismatch_maps.png`.")
    lines.append("\n## Figures\n")   # embedded, so the report reads on its own
    lines += [f"![{name}]({name}.png)\n" for name in
              ("mismatch_maps", "transfer_function", "noise_vs_brightness")]
    return "\n".join(lines) + "\n"


def _f(v: Any) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_f(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_f(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def write_diagnosis(diag: Diagnosis, out_dir: str | Path, *, transform: Affine, crs: CRS | str,
                    sources: list[str] | None = None, extra: dict[str, Any] | None = None,
                    dpi: int = DEFAULT_DPI) -> dict[str, Any]:
    """Write all outputs of a diagnosis into ``out_dir``; returns the diagnosis.json dict.

    The figures name ``extra["flight"]`` when given and are rendered at ``dpi`` (dots per
    inch: the PNGs' pixel size scales with it).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    crs = CRS.from_user_input(crs)
    tags = provenance_tags("diagnose", {"q_base": diag.summary["baseline"]["q"]}, sources or [])
    names = ["red", "green", "blue"] if diag.real.shape[0] == 3 else None
    for key, arr in (("satellite", diag.real), ("baseline", diag.baseline),
                     ("refined", diag.refined)):
        write_geotiff(out / FILES[key], arr.astype(np.float32), transform=transform, crs=crs,
                      nodata=np.nan, mask=diag.valid, band_descriptions=names, tags=tags)
    for key, fname in MAPS.items():
        write_geotiff(out / fname, diag.maps[key].astype(np.float32), transform=transform,
                      crs=crs, nodata=np.nan, band_descriptions=[key], tags=tags)
    from geosim.io.vector import write_geojson, write_gpkg

    gdf = _regions_gdf(diag, transform, crs)
    write_geojson(gdf, out / "regions.geojson")
    if len(gdf):
        write_gpkg(gdf, out / "regions.gpkg", layer="regions")
    plots = _plots(diag, out, transform=transform, crs=crs, flight=(extra or {}).get("flight"),
                   dpi=dpi)
    summary = dict(diag.summary)
    summary["n_regions"] = len(diag.regions)
    doc: dict[str, Any] = {
        "grid": {"crs": crs.to_string(), "transform": list(transform)[:6],
                 "width": int(diag.real.shape[-1]), "height": int(diag.real.shape[-2])},
        **summary,
        "regions": "regions.geojson",
        "files": dict(FILES),
        "maps": dict(MAPS),
        "plots": plots,
        "report": "report.md",
    }
    if extra:
        doc.update(extra)
    write_json(out / "diagnosis.json", to_jsonable(doc, nan_to_null=True))
    write_text(out / "report.md", _markdown(summary))
    return doc


def compare_with_truth(doc: dict[str, Any], truth: dict[str, Any]) -> list[dict[str, Any]]:
    """Rows (effect, fitted params, true params) for a diagnosis and a sample ``truth.json``.

    ``truth["satellite"]["effects"]`` holds the effects the sample generator put into the
    satellite scene (``optics`` → compared with the refined Q). For ``geosim demo``.
    """
    true_eff = dict(truth.get("satellite", {}).get("effects", {}))
    found = {e["name"]: e["params"] for e in doc.get("effects", [])}
    rows: list[dict[str, Any]] = []
    if "optics" in true_eff:
        rows.append({"effect": "optics", "fitted": {"q": doc["refined"]["q"],
                                                    "q_baseline": doc["baseline"]["q"]},
                     "truth": true_eff.pop("optics")})
    alt_of = {a: e["name"] for e in doc.get("effects", [])
              for a in e.get("indistinguishable_from", []) or []}
    sat = truth.get("satellite", {})
    rel = sat.get("misregistration_vs_reference_flight")
    if rel is not None:
        # the simulation is in the reference flight's stated frame, so the shift to compare
        # is satellite-minus-reference, with the reference's own rotation and scale error
        ref_err = truth.get("flights", {}).get(rel.get("reference"), {}).get("georef_error", {})
        true_eff["misregistration"] = {
            "shift_m": rel.get("shift_m_at_site_centre"),
            "rotation_deg": ref_err.get("rotation_deg"), "scale": ref_err.get("scale"),
            "relative_to": f"reference flight {rel.get('reference')}"}
    ref_id = doc.get("reference_flight") or (rel or {}).get("reference")
    seam = truth.get("flights", {}).get(ref_id, {}).get("artefacts", {}).get("exposure_seam")
    if seam and seam.get("gain_left"):
        # the diagnosis reports the factor that brightens the darker side (≥ 1)
        gl = float(seam["gain_left"])
        true_eff["exposure_seam"] = {"factor": max(gl, 1.0 / gl), "flight": ref_id}
    if "acquired" in sat:
        # another acquisition day: the cattle and the shadows are elsewhere
        true_eff.setdefault("scene_change", {
            "acquired": sat["acquired"], "n_cattle": sat.get("n_cattle"),
            "sun_elevation_deg": sat.get("sun", {}).get("elevation_deg")})
    for name in sorted(set(true_eff) | set(found)):
        row = {"effect": name, "fitted": found.get(name), "truth": true_eff.get(name)}
        if name in alt_of:
            row["note"] = f"indistinguishable on these data from the claimed {alt_of[name]}"
        rows.append(row)
    return rows


def format_truth_comparison(rows: list[dict[str, Any]]) -> str:
    """A plain-text list of :func:`compare_with_truth` rows: each effect, fitted vs truth.

    Values are never cut: each effect gets a ``fitted`` and a ``truth`` line.
    """
    lines = []
    for r in rows:
        fitted = "not claimed" if r["fitted"] is None else _f(r["fitted"])
        if r.get("note"):
            fitted += f" ({r['note']})"
        truth = "not present" if r["truth"] is None else _f(r["truth"])
        lines.append(f"{r['effect']}\n    fitted: {fitted}\n    truth:  {truth}")
    return "\n".join(lines)


def _copy_atomic(src: Path, dst: Path) -> None:
    import shutil

    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)


def _combined_markdown(doc: dict[str, Any], per: dict[str, dict[str, Any]],
                       dirs: dict[str, str]) -> str:
    b, rf = doc["baseline"], doc["refined"]
    comb = doc["combination"]
    ids = comb["flights"]
    lines = ["# Diagnosis: where the paper's model and the real satellite scene differ", ""]
    lines.append(f"{len(ids)} flight(s) were diagnosed against the satellite scene "
                 f"({', '.join(ids)}; reference {doc['reference_flight']}). Each flight is an "
                 "independent simulation of the same scene: the satellite's physics is "
                 f"claimed when a majority of flights ({comb['votes_needed']} of {len(ids)}) "
                 "claims it; misregistration and scene change belong to each flight.")
    if doc.get("flights_skipped"):
        lines.append("")
        for f, why in doc["flights_skipped"].items():
            lines.append(f"- Flight {f} was not diagnosed: {why}")
    lines.append("")
    lines.append(f"The baselines (the paper's model, Q by Laplacian variance; median Q "
                 f"{b['q']:.2f}) have a median RMSE of {b['rmse']:.2f} DN and spectral error "
                 f"{b['spectral_error']:.3f}.")
    sat = [e for e in doc["effects"] if e.get("scope") == "satellite"]
    lines.append("")
    if not sat:
        lines.append("**No missing satellite physics was found**: no effect was claimed by a "
                     "majority of flights.")
    else:
        lines.append("## Physics the model left out (combined over flights)")
        lines.append("")
        for e in sat:
            params = ", ".join(f"{k} = {_f(v)}" for k, v in e["params"].items())
            unc = ", ".join(f"{k} ± {_f(v)}" for k, v in e["uncertainty"].items()
                            if v is not None)
            lines.append(f"- **{e['name']}** ({params}; {unc}, {e['uncertainty_kind']}). "
                         f"{e['explanation'].split(' Fitted:')[0]} Claimed in "
                         f"{e['votes']} flights ({', '.join(e['flights_claimed'])}); median "
                         f"ΔBIC {_f(e['delta_bic'])}.")
            lines.append("  - Per flight: " + "; ".join(
                f"{f}: " + ", ".join(f"{k} = {_f(v)}" for k, v in pp.items())
                for f, pp in e["params_by_flight"].items()) + ".")
            if e.get("indistinguishable_from"):
                lines.append(f"  - Caution: it cannot be told apart from "
                             f"{', '.join(e['indistinguishable_from'])} on these data.")
    if doc.get("not_carried"):
        lines.append("\nClaimed in some flights but not carried by the majority (not claimed "
                     "for the satellite): "
                     + ", ".join(f"{k} ({v['votes']}: {', '.join(v['flights_claimed'])})"
                                 for k, v in doc["not_carried"].items()) + ".")
    lines.append(f"\n## Refit\n\nThe refitted Q is {rf['q']:.2f} ± {rf['q_sigma']:.2f} "
                 f"({rf['q_sigma_kind']}; per flight "
                 + ", ".join(f"{f} {q:.2f}" for f, q in rf["q_by_flight"].items()) + "); it is "
                 + ("**within**" if rf["q_in_physical_range"] else "**outside**")
                 + f" the physical range {rf['physical_q_range'][0]}–"
                 f"{rf['physical_q_range'][1]} of real cameras. Median RMSE {b['rmse']:.2f} → "
                 f"{rf['rmse']:.2f} DN; median spectral error {b['spectral_error']:.3f} → "
                 f"{rf['spectral_error']:.3f}.")
    lines.append(f"\n![{COMBINED_PLOT}]({COMBINED_PLOT})\n")
    lines.append("\n## Per flight\n")
    lines.append("| flight | baseline Q → refined Q | claimed | RMSE DN | spectral error |")
    lines.append("|---|---|---|---|---|")
    for f in ids:
        d = per[f]
        lines.append(f"| {f} | {d['baseline']['q']:.2f} → {d['refined']['q']:.2f} | "
                     + (", ".join(e["name"] for e in d["effects"]) or "—")
                     + f" | {d['baseline']['rmse']:.2f} → {d['refined']['rmse']:.2f} | "
                     f"{d['baseline']['spectral_error']:.3f} → "
                     f"{d['refined']['spectral_error']:.3f} |")
    for name, by in doc.get("per_flight_effects", {}).items():
        lines.append(f"\n{name} (per flight): "
                     + "; ".join(f"{f}: {_f(p)}" for f, p in by.items()) + ".")
    lines.append("\nThe top-level GeoTIFFs, maps and plots are the reference flight's; every "
                 "flight's full diagnosis (report, maps, plots, regions) is in its folder: "
                 + ", ".join(f"`{dirs[f]}/`" for f in ids) + ". `regions.geojson` holds the "
                 "regions of all flights (attribute `flight`).")
    for f in ids:
        sub = _markdown(per[f]).split("\n", 2)[2]  # drop the title
        sub = sub.replace("\n## ", "\n#### ").replace("](", f"]({dirs[f]}/")  # its own figures
        lines.append(f"\n### Flight {f}\n\n{sub}")
    return "\n".join(lines) + "\n"


COMBINED_PLOT = "flights_combined.png"


def flights_figure(per: dict[str, dict[str, Any]], comb: dict[str, Any]) -> Any:
    """Baseline and refined Q and RMSE of every flight beside the combined verdict.

    Parameters
    ----------
    per
        Each flight's diagnosis dict.
    comb
        The combined verdict (:func:`geosim.diagnose.combine.combine_flights`).

    Returns
    -------
    matplotlib.figure.Figure
        Titled "All flights (combined)" with the flight ids.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ids = list(per)
    x = np.arange(len(ids))
    fig, axes = plt.subplots(1, 2, figsize=(max(7.0, 1.2 * len(ids) + 4), 3.8))
    for ax, key, unit in ((axes[0], "q", "Q"), (axes[1], "rmse", "RMSE (DN)")):
        base = [per[f]["baseline"][key] for f in ids]
        ref = [per[f]["refined"][key] for f in ids]
        ax.bar(x - 0.2, base, 0.4, color="C0", label="baseline (paper's model)")
        ax.bar(x + 0.2, ref, 0.4, color="C3", label="refined (with the flight's effects)")
        ax.axhline(comb["refined"][key], color="k", ls="--", lw=1,
                   label="combined refined (median)")
        ax.set_xticks(x, ids, fontsize=8)
        ax.set_xlabel("flight")
        ax.set_ylabel(unit)
        ax.legend(fontsize=7)
    fig.suptitle(f"All flights (combined): {', '.join(ids)}", fontsize=11)
    return fig


def write_combined(per: dict[str, dict[str, Any]], out_dir: str | Path, *, reference: str,
                   dirs: dict[str, str], skipped: dict[str, str] | None = None,
                   extra: dict[str, Any] | None = None, dpi: int = DEFAULT_DPI
                   ) -> dict[str, Any]:
    """Write the combined diagnosis of several flights into ``out_dir``.

    ``per`` holds each flight's diagnosis dict (as returned by :func:`write_diagnosis`,
    written to ``out_dir/dirs[flight]``). Writes ``diagnosis.json`` (the issue's schema
    for the combined verdict, plus ``flights``), ``report.md``, ``regions.geojson`` (all
    flights' regions, attribute ``flight``) and copies of the reference flight's
    GeoTIFFs, maps and plots (titled with the reference flight), so that ``files``
    resolves at the top level, and ``flights_combined.png`` (every flight's Q and RMSE
    beside the combined verdict, titled "All flights (combined)") at ``dpi``.
    """
    import geopandas as gpd
    import pandas as pd

    from geosim.diagnose.combine import combine_flights
    from geosim.io.vector import write_geojson, write_gpkg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ref_dir = out / dirs[reference]
    ref = per[reference]
    for name in [*FILES.values(), *MAPS.values(), *ref.get("plots", [])]:
        _copy_atomic(ref_dir / name, out / name)
    frames = []
    crs = None
    for f in per:
        path = out / dirs[f] / "regions.geojson"
        g = gpd.read_file(path)
        crs = crs or CRS.from_user_input(ref["grid"]["crs"])
        if len(g):
            g = g.to_crs(crs)
            g.insert(0, "flight", f)
            frames.append(g)
    if frames:
        gdf = gpd.GeoDataFrame(pd.concat(frames, ignore_index=True), geometry="geometry",
                               crs=crs)
    else:
        gdf = gpd.GeoDataFrame({"flight": [], "rank": [], "kind": []}, geometry=[], crs=crs)
    write_geojson(gdf, out / "regions.geojson")
    if len(gdf):
        write_gpkg(gdf, out / "regions.gpkg", layer="regions")
    comb = combine_flights(per, reference=reference)
    plots = [*ref.get("plots", []),
             _save_png(flights_figure(per, comb), out / COMBINED_PLOT, dpi=dpi)]
    flights = {f: {**to_jsonable(d, nan_to_null=True), "dir": dirs[f]} for f, d in per.items()}
    doc: dict[str, Any] = {
        "grid": ref["grid"], **comb,
        "regions": "regions.geojson",
        "files": dict(FILES), "maps": dict(MAPS), "plots": plots,
        "report": "report.md", "reference_flight": reference,
        "flights": flights, "flights_skipped": dict(skipped or {}),
        "n_regions": int(len(gdf)),
    }
    if extra:
        doc.update(extra)
    write_json(out / "diagnosis.json", to_jsonable(doc, nan_to_null=True))
    write_text(out / "report.md", _combined_markdown(doc, per, dirs))
    return doc
