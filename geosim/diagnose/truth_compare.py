"""A diagnosis against a sample site's ``truth.json`` (for ``geosim demo`` and the
benchmarks): each effect, fitted vs true."""

from __future__ import annotations

from typing import Any

from geosim.diagnose.detection_limits import absorbed_by, family_claimed
from geosim.diagnose.report_markdown import fmt

__all__ = ["compare_with_truth", "format_truth_comparison"]


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
    limits = doc.get("detection_limits", {})
    for name in sorted(set(true_eff) | set(found)):
        row = {"effect": name, "fitted": found.get(name), "truth": true_eff.get(name)}
        if name in alt_of:
            row["note"] = f"indistinguishable on these data from the claimed {alt_of[name]}"
        elif (row["fitted"] is None and name in limits and row["truth"]
              and not family_claimed(name, found)):
            row["note"] = _limit_note(limits[name], row["truth"])
        rows.append(row)
    return rows


def _limit_note(lim: dict[str, Any], truth: dict[str, Any]) -> str | None:
    """Whether a missed effect's true value lies on the untestable side of the detection
    limit the diagnosis stated (``diagnosis.json``'s ``detection_limits``): a blur absorbed
    into Q (isotropic, or anisotropic in any direction), a resampling whose aliasing the
    spectrum does not resolve."""
    value = truth.get(lim["param"])
    if value is None:
        return None
    why = ("aliasing not resolved by the scene's spectrum" if lim["param"] ==
           "native_pitch_px" else "absorbed into Q")
    if lim["limit"] is None:
        return f"not testable at Q {lim['q']:.2f}: {why}"
    where = f"stated detection limit {lim['param']} {lim['limit']:.2f} at Q {lim['q']:.2f}"
    if absorbed_by(lim, value):
        return f"below the {where}: {why}"
    return f"missed, though beyond the {where}"


def format_truth_comparison(rows: list[dict[str, Any]]) -> str:
    """A plain-text list of :func:`compare_with_truth` rows: each effect, fitted vs truth.

    Values are never cut: each effect gets a ``fitted`` and a ``truth`` line.
    """
    lines = []
    for r in rows:
        fitted = "not claimed" if r["fitted"] is None else fmt(r["fitted"])
        if r.get("note"):
            fitted += f" ({r['note']})"
        truth = "not present" if r["truth"] is None else fmt(r["truth"])
        lines.append(f"{r['effect']}\n    fitted: {fitted}\n    truth:  {truth}")
    return "\n".join(lines)
