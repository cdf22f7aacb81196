"""``report.md`` of one flight's diagnosis and of the combined verdict over flights."""

from __future__ import annotations

from typing import Any

from geosim.diagnose.detection_limits import limits_markdown
from geosim.diagnose.report_figures import COMBINED_PLOT

__all__ = ["diagnosis_markdown", "combined_markdown", "fmt"]


def diagnosis_markdown(s: dict[str, Any]) -> str:
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
            lines.extend(_effect_lines(e))
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
    lines += limits_markdown(s.get("detection_limits", {}), claimed)
    n_sc = sum(1 for e in s["effects"] if e["name"] == "scene_change")
    lines.append("\n## Where\n")
    lines.append(f"{s.get('n_regions', 0)} regions of significant mismatch are in "
                 f"`regions.geojson` (ranked; kind `scene_change` = object-sized local change, "
                 f"excluded from the physics fit; `global` = large areas). "
                 + ("Scene changes were found." if n_sc else "No object-sized scene change."))
    objs = s.get("refined", {}).get("moved_objects", [])
    if objs:
        left = sum(1 for o in objs if o.get("change") == "left")
        ref = s["refined"]
        lines.append(f"\nThe refined simulation models the change as {len(objs)} compact "
                     f"objects seen through the fitted optics ({len(objs) - left} appeared, "
                     f"{left} left; ellipses in `moved_objects.geojson`): spectral error over "
                     f"the whole scene "
                     f"{s['baseline'].get('spectral_error_whole', float('nan')):.3f} (baseline)"
                     f" → {ref.get('spectral_error_whole', float('nan')):.3f}.")
    lines += _refit_markdown(s.get("scene_change_refit", {}))
    lines.append("\nMaps: `map_residual_energy.tif`, `map_blur_ratio.tif`, `map_gain.tif`, "
                 "`map_offset.tif`; plots: `transfer_function.png`, `noise_vs_brightness.png`, "
                 "`mismatch_maps.png`.")
    lines.append("\n## Figures\n")   # embedded, so the report reads on its own
    lines += [f"![{name}]({name}.png)\n" for name in
              ("mismatch_maps", "transfer_function", "noise_vs_brightness")]
    return "\n".join(lines) + "\n"


def _effect_lines(e: dict[str, Any]) -> list[str]:
    """The report's lines for one claimed effect (an entry of ``effects``)."""
    lines = []
    params = ", ".join(f"{k} = {fmt(v)}" for k, v in e["params"].items())
    lines.append(f"- **{e['name']}** ({params}). {e['explanation'].split(' Fitted:')[0]} "
                 + ("Evidence: quantisation lattice, 2 Δ log-likelihood = "
                    if e["name"] == "compression" else "Evidence: ΔBIC = ")
                 + fmt(e["delta_bic"])
                 + (f", held-out χ² {100 * e['heldout_gain']:.0f} % lower"
                    if e.get("heldout_gain") is not None else "")
                 + "; after adding it the RMSE is "
                 f"{e['rmse_after']:.2f} DN and the spectral error "
                 f"{e['spectral_error_after']:.3f}.")
    t = e.get("test") or {}
    renamed_from = t.get("transfer_named") if e["name"] != "compression" else None
    # a member renamed in the pixels lists the transfer's as its alternative (flights vote
    # together); the pixels told them apart, so that one is not a caution
    alts = [a for a in e.get("indistinguishable_from") or [] if a != renamed_from]
    if alts:
        lines.append(f"  - Caution: on these data it cannot be told apart from "
                     f"{', '.join(alts)}.")
    if renamed_from:
        lines.append(f"  - Named in the pixels: the transfer named "
                     f"{renamed_from}; fitted in its place on each half of a "
                     f"checkerboard, this one lowered the other half's residual by "
                     + " and ".join(f"{v:.0f}" for v in t["naming_dchi2"])
                     + f" (residual variances per pixel; at least {fmt(t['min_dchi2'])} "
                     "needed on both).")
    return lines


def _refit_markdown(refit: dict[str, Any]) -> list[str]:
    """The second pass with the moved objects painted into the UAV ground, in words."""
    again = (["\nThe pixel test for a lone isotropic blur, left to a second pass on the "
              "painted ground, ran on the first pass again: no second pass was kept."]
             if refit.get("lone_isotropic_retested") else [])
    if not refit.get("ran"):
        return again
    pairs = refit.get("spectral_error_whole") or []
    errs = ", ".join(f"{a:.3f} → {b:.3f} on {px} px blocks"
                     for (a, b), px in zip(pairs, refit.get("block_px", []), strict=True))
    first = ", ".join(f"`{n}`" for n in refit.get("first_pass_effects", [])) or "nothing"
    if refit.get("kept"):
        return [f"\nThe blurs were measured again with the {refit['n_objects_painted']} moved "
                f"objects painted into the UAV ground (whole scene, no blocks lost to the "
                f"change); that second pass fits better over every valid block ({errs}) and "
                f"its claims stand (the first pass claimed {first})."]
    why = f"it fit no better ({errs})" if errs else "too few whole blocks to judge it"
    return [f"\nA second pass with the {refit['n_objects_painted']} moved objects painted "
            f"into the UAV ground was not kept: {why}."] + again


def fmt(v: Any) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {fmt(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def combined_markdown(doc: dict[str, Any], per: dict[str, dict[str, Any]],
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
            params = ", ".join(f"{k} = {fmt(v)}" for k, v in e["params"].items())
            unc = ", ".join(f"{k} ± {fmt(v)}" for k, v in e["uncertainty"].items()
                            if v is not None)
            lines.append(f"- **{e['name']}** ({params}; {unc}, {e['uncertainty_kind']}). "
                         f"{e['explanation'].split(' Fitted:')[0]} Claimed in "
                         f"{e['votes']} flights ({', '.join(e['flights_claimed'])}); median "
                         f"ΔBIC {fmt(e['delta_bic'])}.")
            lines.append("  - Per flight: " + "; ".join(
                f"{f}: " + ", ".join(f"{k} = {fmt(v)}" for k, v in pp.items())
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
    lines += limits_markdown(doc.get("detection_limits", {}), [e["name"] for e in sat])
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
                     + "; ".join(f"{f}: {fmt(p)}" for f, p in by.items()) + ".")
    lines.append("\nThe top-level GeoTIFFs, maps and plots are the reference flight's; every "
                 "flight's full diagnosis (report, maps, plots, regions) is in its folder: "
                 + ", ".join(f"`{dirs[f]}/`" for f in ids) + ". `regions.geojson` and "
                 "`moved_objects.geojson` hold the regions and the modelled moved objects of "
                 "all flights (attribute `flight`).")
    for f in ids:
        sub = diagnosis_markdown(per[f]).split("\n", 2)[2]  # drop the title
        sub = sub.replace("\n## ", "\n#### ").replace("](", f"]({dirs[f]}/")  # its own figures
        lines.append(f"\n### Flight {f}\n\n{sub}")
    return "\n".join(lines) + "\n"
