"""The diagnosis's figures: transfer functions and spectra, noise vs brightness, the
mismatch maps in map coordinates (with a scale bar), and every flight beside the combined
verdict. PNGs are written atomically and carry their title."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine
from rasterio.crs import CRS

from geosim.diagnose.engine import Diagnosis
from geosim.diagnose.fit import HANN_CORRELATION
from geosim.diagnose.spectra import directional_profiles, polar_bin_mean, radial_profile
from geosim.io.atomic import atomic_path

__all__ = ["save_png", "diagnosis_plots", "mismatch_maps_figure", "map_extent",
           "scale_bar_length", "draw_scale_bar", "flights_figure", "DEFAULT_DPI",
           "COMBINED_PLOT"]

DEFAULT_DPI = 100
COMBINED_PLOT = "flights_combined.png"


def save_png(fig: Any, path: Path, *, dpi: int, tight: bool = True) -> str:
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


def diagnosis_plots(diag: Diagnosis, out: Path, *, transform: Affine, crs: CRS, flight: str | None,
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
    written.append(save_png(fig, out / "transfer_function.png", dpi=dpi, tight=True))
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
    written.append(save_png(fig, out / "noise_vs_brightness.png", dpi=dpi, tight=True))
    # 3. maps
    fig = mismatch_maps_figure(diag, transform=transform, crs=crs, flight=flight)
    written.append(save_png(fig, out / "mismatch_maps.png", dpi=dpi, tight=False))
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
