"""The calibration figure (the paper's Fig. "LV vs Q"), drawn from calibration.json."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from geosim.degrade.calibrate import PLAUSIBLE_Q
from geosim.io.atomic import atomic_path


def plot_calibration(doc: Mapping[str, Any], path: str | os.PathLike[str]) -> Path:
    """Draw LV against Q for each flight, the satellite LV as a line, the solved Q.

    Parameters
    ----------
    doc
        The content of ``calibration.json`` (see :func:`geosim.degrade.steps.run_calibrate`).
    path
        PNG to write (atomically).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8), dpi=120)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    flights = [f for f in doc.get("flights", []) if f.get("curve")]
    sat_levels = {round(f["lv_satellite"], 9) for f in flights if f.get("lv_satellite")}
    lo, hi = PLAUSIBLE_Q
    ax.axvspan(lo, hi, color="0.92", zorder=0, label=f"real cameras (Q {lo:g}–{hi:g})")
    for i, f in enumerate(flights):
        c = colours[i % len(colours)]
        label = f"flight {f['flight']}"
        if f.get("status") == "ok":
            label += f": Q = {f['q']:.2f}"
        ax.plot(f["curve"]["q"], f["curve"]["lv"], "o-", ms=3.5, lw=1.4, color=c, label=label)
        if len(sat_levels) > 1 and f.get("lv_satellite"):
            ax.axhline(f["lv_satellite"], color=c, ls="--", lw=1.0)
        if f.get("status") == "ok":
            ax.plot([f["q"]], [f["lv_at_q"]], marker="*", ms=12, color=c, mec="k", mew=0.6,
                    zorder=5)
    if len(sat_levels) > 1:
        lo_lv, hi_lv = min(sat_levels), max(sat_levels)
        ax.plot([], [], color="0.3", ls="--", lw=1.0,
                label=f"satellite LV over each flight's extent ({lo_lv:.3g}–{hi_lv:.3g})")
    elif len(sat_levels) == 1:
        level = next(iter(sat_levels))
        ax.axhline(level, color="k", ls="--", lw=1.1, label=f"satellite LV {level:.3g}")
    mean_q = doc.get("mean_q")
    if mean_q is not None:
        ax.axvline(mean_q, color="k", ls=":", lw=1.0, label=f"mean Q = {mean_q:.2f}")
    ax.set_yscale("log")
    ax.set_xlabel("Q = λ f / (D p)")
    ax.set_ylabel("Laplacian variance of degraded UAV (grey levels²)")
    ax.set_title(f"Calibration of the degradation against the satellite scene"
                 f"{' — ' + doc['site'] if doc.get('site') else ''}", fontsize=10)
    ax.grid(True, which="both", lw=0.3, alpha=0.6)
    ax.legend(fontsize=7.5, loc="upper right")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return Path(path)
