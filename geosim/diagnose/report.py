"""Writing a diagnosis: GeoTIFFs, regions.geojson, diagnosis.json, plots and report.md."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import Diagnosis
from geosim.diagnose.spectra import directional_profiles, radial_profile
from geosim.io.atomic import atomic_path, write_json, write_text
from geosim.io.raster import provenance_tags, write_geotiff

__all__ = ["write_diagnosis", "FILES", "compare_with_truth", "format_truth_comparison"]

FILES = {"satellite": "satellite_on_grid.tif", "baseline": "sim_baseline.tif",
         "refined": "sim_refined.tif"}
MAPS = {"residual_energy": "map_residual_energy.tif", "blur_ratio": "map_blur_ratio.tif",
        "gain": "map_gain.tif", "offset": "map_offset.tif"}


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


def _plots(diag: Diagnosis, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = diag.plots
    fy, fx = p["fy"], p["fx"]
    n_rad = max(4, min(16, fy.shape[0] // 2 - 1))  # no finer than the block's FFT grid
    written = []
    # transfer functions, radial and by direction
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, lab, st in (("t_real", "real scene", "k-"),
                         ("t_base", "baseline (paper model)", "C0--"),
                         ("t_refined", "refined model", "C3-")):
        f, m = radial_profile(p[key], fy, fx, n_bins=n_rad)
        axes[0].plot(f, m, st, label=lab)
    f, c = radial_profile(p["coherence_base"], fy, fx, n_bins=n_rad)
    axes[0].plot(f, c, "C2:", label="coherence real vs baseline")
    axes[0].set_xlabel("spatial frequency (cycles per 0.5 m pixel)")
    axes[0].set_ylabel(f"|transfer| relative to paper model at Q={p['q_ref']:.2f}")
    axes[0].legend(fontsize=8)
    axes[0].set_title("Radial transfer function")
    n_dir = max(4, n_rad * 3 // 4)
    f, ang, mr = directional_profiles(p["t_real"], fy, fx, n_sectors=4, n_bins=n_dir)
    _, _, mf = directional_profiles(p["t_refined"], fy, fx, n_sectors=4, n_bins=n_dir)
    for i, a in enumerate(ang):
        axes[1].plot(f, mr[i], f"C{i}-", label=f"real, {a:.0f}° from north")
        axes[1].plot(f, mf[i], f"C{i}--")
    axes[1].set_xlabel("spatial frequency (cycles per pixel)")
    axes[1].set_title("By direction (solid real, dashed refined)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(out / "transfer_function.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    written.append("transfer_function.png")
    # noise vs brightness
    fig, ax = plt.subplots(figsize=(5.5, 4))
    if len(p["noise_brightness"]):
        ax.plot(p["noise_brightness"], p["noise_variance"], "ko", label="residual (high-pass)")
        s = np.linspace(0, max(p["noise_brightness"]) * 1.05, 50)
        a, b = p["noise_model"]
        ax.plot(s, a * s + b, "C3-", label=f"fit var = {a:.3g}·s + {b:.3g}")
    ax.set_xlabel("brightness (DN)")
    ax.set_ylabel("noise variance (DN²)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(out / "noise_vs_brightness.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    written.append("noise_vs_brightness.png")
    # maps
    fig, axes = plt.subplots(1, 4, figsize=(16, 4))
    for ax, (k, title) in zip(axes, (("residual_energy", "residual energy (DN²)"),
                                     ("blur_ratio", "LV real / LV baseline"),
                                     ("gain", "local gain"), ("offset", "local offset (DN)")),
                              strict=True):
        im = ax.imshow(diag.maps[k], cmap="magma" if k == "residual_energy" else "viridis")
        ax.set_title(title)
        ax.set_axis_off()
        fig.colorbar(im, ax=ax, fraction=0.046)
    for r in diag.regions[:20]:
        r0, c0, r1, c1 = r.bbox
        axes[0].add_patch(plt.Rectangle((c0 - 0.5, r0 - 0.5), c1 - c0, r1 - r0, fill=False,
                                        ec="cyan" if r.kind == "scene_change" else "white"))
    fig.tight_layout()
    with atomic_path(out / "mismatch_maps.png") as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    written.append("mismatch_maps.png")
    return written


def _markdown(s: dict[str, Any]) -> str:
    b, rf = s["baseline"], s["refined"]
    lines = ["# Diagnosis: where the paper's model and the real satellite scene differ", ""]
    lines.append(f"The baseline (the paper's model) matched the real scene's Laplacian variance "
                 f"({b['lv_satellite']:.3g}) with Q = {b['q']:.2f}; its RMSE is {b['rmse']:.2f} DN "
                 f"and its spectral error {b['spectral_error']:.3f} (RMS of log10 power ratio).")
    lines.append("")
    if not s["effects"]:
        lines.append("**No missing physics was found**: no effect improved the fit by enough "
                     "(ΔBIC ≥ 10 and better on held-out data) to be claimed.")
    else:
        lines.append("## Physics the model left out (in the order they were added)")
        lines.append("")
        for e in s["effects"]:
            params = ", ".join(f"{k} = {_f(v)}" for k, v in e["params"].items())
            lines.append(f"- **{e['name']}** ({params}). {e['explanation'].split(' Fitted:')[0]} "
                         f"Evidence: ΔBIC = {_f(e['delta_bic'])}; after adding it the RMSE is "
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
        lines.append("\nWeak evidence, not claimed (ΔBIC ≥ 2 but < 10, or not confirmed on "
                     "held-out data): "
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
                    sources: list[str] | None = None, extra: dict[str, Any] | None = None
                    ) -> dict[str, Any]:
    """Write all outputs of a diagnosis into ``out_dir``; returns the diagnosis.json dict."""
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
    plots = _plots(diag, out)
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
    write_json(out / "diagnosis.json", _jsonable(doc))
    write_text(out / "report.md", _markdown(summary))
    return doc


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, (np.floating, float)):
        v = float(o)
        return v if np.isfinite(v) else None
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


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
