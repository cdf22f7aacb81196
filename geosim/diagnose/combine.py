"""A combined verdict over several flights diagnosed against one satellite scene.

Each UAV flight is an independent simulation of the same satellite scene: the
satellite's physics (optics, blur, radiometry, noise, compression) is common to all
flights, while misregistration (each flight's own georeference or alignment error)
and scene change (each flight's own day, sun and cattle) belong to one flight.

Rule: **majority of flights.** A satellite effect is claimed when a strict majority of
the diagnosed flights claims it, each by its own evidence test (held-out blocks
predicted better, effect clearly away from its null). Effects that a flight reports as
indistinguishable from each other (e.g. ``motion_smear`` and ``off_nadir_anisotropy``)
vote together; the name claimed
most often wins and the others are reported as indistinguishable.

Why not a joint ΔBIC summed over flights? The flights are not independent data: every
flight is compared with the *same* satellite pixels, so the satellite's noise and any
misfit of the model to it enter every flight's ΔBIC alike. Summing would count that
evidence once per flight and make a flight-count-dependent claim out of one noisy scene;
one flight with strong local trouble (a big scene change) could also carry a sum on its
own. A majority of separate, individually conservative tests is robust to one odd
flight and does not inflate the evidence. The combined ΔBIC reported is the median of
the claiming flights' values (not a sum).

Parameters: the median over the flights that claimed the effect (circular, period
180°, for directions); uncertainty: the between-flight spread (sample standard
deviation, not divided by √n, because the flights share the satellite scene and are
not independent), or the single flight's statistical σ when only one flight claimed
it. The median statistical σ is kept as ``uncertainty_statistical``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from geosim.diagnose.detection_limits import combine_limits
from geosim.diagnose.effects import get_effect
from geosim.diagnose.select import BLUR_FAMILY, bic_evidence

__all__ = ["combine_flights", "combine_values", "PER_FLIGHT_EFFECTS"]

#: effects that belong to one flight (geometry of its georeference, its own scene)
PER_FLIGHT_EFFECTS = ("misregistration", "scene_change", "exposure_seam")


def _median(values: Sequence[float]) -> float:
    v = [float(x) for x in values if x is not None and np.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def _finite_median(values: Sequence[Any]) -> float | None:
    m = _median(values)
    return m if np.isfinite(m) else None


def _listed(claims: Mapping[str, Mapping[str, Any]], claimed: str, alt: str, key: str
            ) -> list[Any]:
    """``key`` of ``alt`` in every flight that listed it as ``claimed``'s alternative."""
    return [x.get(key) for by_name in claims.values()
            for x in by_name.get(claimed, {}).get("alternatives", []) if x.get("name") == alt]


def _spread(values: Sequence[float]) -> float:
    v = np.asarray([float(x) for x in values if x is not None and np.isfinite(x)])
    return float(np.std(v, ddof=1)) if v.size >= 2 else float("nan")


def _circular(values: Sequence[float], period: float) -> tuple[float, float]:
    """Median and spread of angles with the given period (degrees)."""
    a = np.asarray(values, float) * (2 * np.pi / period)
    centre = np.angle(np.mean(np.exp(1j * a)))
    dev = np.angle(np.exp(1j * (a - centre))) * (period / (2 * np.pi))
    centre_deg = centre * period / (2 * np.pi)
    med = float(np.mod(centre_deg + np.median(dev), period))
    return med, (float(np.std(dev, ddof=1)) if dev.size >= 2 else float("nan"))


def combine_values(name: str, key: str, values: Sequence[Any]) -> tuple[Any, Any]:
    """Median and between-flight spread of one parameter (scalars, or lists element-wise)."""
    first = values[0]
    if isinstance(first, (list, tuple)):
        n = min(len(v) for v in values)
        pairs = [combine_values(name, key, [v[i] for v in values]) for i in range(n)]
        return [p[0] for p in pairs], [p[1] for p in pairs]
    if isinstance(first, bool) or not isinstance(first, (int, float, np.integer, np.floating)):
        return first, None
    periodic = None
    try:
        spec = {p.name: p for p in get_effect(name).params}.get(key)
        periodic = spec.periodic if spec is not None else None
    except KeyError:
        pass
    if periodic is None and key.endswith("_deg") and key != "rotation_deg":
        periodic = 180.0
    if periodic:
        return _circular([float(v) for v in values], periodic)
    med = _median([float(v) for v in values])
    if isinstance(first, (int, np.integer)) and float(med).is_integer():
        med = int(med)
    return med, _spread([float(v) for v in values])


def _groups(claims: Mapping[str, Mapping[str, dict[str, Any]]]) -> list[set[str]]:
    """Connected components of claimed names linked by "indistinguishable_from"."""
    parent: dict[str, str] = {}

    def find(x: str) -> str:
        parent.setdefault(x, x)
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for eff in claims.values():
        for name, e in eff.items():
            if name in PER_FLIGHT_EFFECTS:
                continue
            find(name)
            for alt in e.get("indistinguishable_from", []) or []:
                parent[find(alt)] = find(name)
    comps: dict[str, set[str]] = {}
    for x in list(parent):
        comps.setdefault(find(x), set()).add(x)
    return list(comps.values())


def _stat_sigma(entries: Sequence[dict[str, Any]], key: str) -> Any:
    vals = [e.get("uncertainty", {}).get(key) for e in entries]
    vals = [v for v in vals if v is not None]
    if not vals:
        return None
    if isinstance(vals[0], (list, tuple)):
        n = min(len(v) for v in vals)
        return [_median([v[i] for v in vals]) for i in range(n)]
    try:
        return _median([float(v) for v in vals])
    except (TypeError, ValueError):
        return None


def _combined_entry(name: str, flights: Sequence[str], entries: Sequence[dict[str, Any]],
                    n_flights: int, all_dbic: Mapping[str, Any]) -> dict[str, Any]:
    keys = list(entries[0]["params"])
    params: dict[str, Any] = {}
    spread: dict[str, Any] = {}
    stat: dict[str, Any] = {}
    for k in keys:
        vals = [e["params"][k] for e in entries if k in e["params"]]
        params[k], sp = combine_values(name, k, vals)
        s1 = _stat_sigma(entries, k)
        stat[k] = s1
        if len(entries) >= 2:
            spread[k] = sp
        else:
            spread[k] = s1
    return {
        "name": name, "params": params, "uncertainty": spread,
        "uncertainty_kind": ("between-flight spread (sample std over the claiming flights)"
                             if len(entries) >= 2 else "statistical (one flight)"),
        "uncertainty_statistical": stat,
        "explanation": get_effect(name).describe(params),
        "signature": get_effect(name).signature,
        "delta_bic": _median([e["delta_bic"] for e in entries]),
        "delta_bic_by_flight": dict(all_dbic),
        "rmse_after": _median([e["rmse_after"] for e in entries]),
        "spectral_error_after": _median([e["spectral_error_after"] for e in entries]),
        "scope": "satellite", "flights_claimed": list(flights),
        "votes": f"{len(flights)}/{n_flights}",
        "params_by_flight": {f: e["params"] for f, e in zip(flights, entries, strict=True)},
    }


def combine_flights(docs: Mapping[str, Mapping[str, Any]], *, reference: str
                    ) -> dict[str, Any]:
    """Combined verdict over per-flight diagnoses (the dicts written as diagnosis.json).

    Parameters
    ----------
    docs
        {flight id: per-flight diagnosis dict} in site order.
    reference
        The flight whose misregistration and scene change head the combined effect list
        (the top-level GeoTIFFs are that flight's).

    Returns
    -------
    dict
        ``baseline``, ``effects``, ``refined``, ``ambiguities``, ``candidates_delta_bic``,
        ``detection_limits`` (testable in a majority of flights), ``per_flight_effects``,
        ``not_carried`` and ``combination`` (the rule), in the
        top-level schema of diagnosis.json.
    """
    ids = list(docs)
    n = len(ids)
    need = n // 2 + 1
    claims = {f: {e["name"]: e for e in docs[f]["effects"]} for f in ids}
    effects: list[dict[str, Any]] = []
    ambiguities: list[dict[str, Any]] = []
    not_carried: dict[str, Any] = {}
    for group in _groups(claims):
        voters = [f for f in ids if group & set(claims[f])]
        exact = {g: [f for f in ids if g in claims[f]] for g in group}
        exact = {g: fl for g, fl in exact.items() if fl}
        if len(voters) < need:
            for g, fl in exact.items():
                not_carried[g] = {"flights_claimed": fl, "votes": f"{len(fl)}/{n}",
                                  "rule": f"claimed in fewer than {need} of {n} flights"}
            continue

        rank = {g: (len(fl), _median([claims[f][g]["delta_bic"] for f in fl]))
                for g, fl in exact.items()}
        order = sorted(exact, key=rank.__getitem__, reverse=True)
        # never two of one blur family (they are one finding under two names)
        fam0 = BLUR_FAMILY.get(order[0], order[0])
        chosen = [order[0]] + [g for g in order[1:] if len(exact[g]) >= need
                               and BLUR_FAMILY.get(g, g) != fam0]
        for g in chosen:
            dbic = {f: (claims[f][g]["delta_bic"] if g in claims[f] else
                        docs[f].get("candidates_delta_bic", {}).get(g)) for f in ids}
            entry = _combined_entry(g, exact[g], [claims[f][g] for f in exact[g]], n, dbic)
            entry["votes"] = f"{len(voters)}/{n}" if len(chosen) == 1 else entry["votes"]
            alts = sorted(group - set(chosen))
            if alts:
                entry["indistinguishable_from"] = alts
                entry["alternatives"] = [
                    {"name": a, "votes": f"{len(exact.get(a, []))}/{n}",
                     "heldout_gain": _finite_median(
                         _listed(claims, g, a, "heldout_gain")
                         + [claims[f][a].get("heldout_gain") for f in exact.get(a, [])]),
                     # median over the flights whose exact duel named g over a
                     "delta_bic": _finite_median(_listed(claims, g, a, "delta_bic"))}
                    for a in alts]
                named = [x["delta_bic"] for x in entry["alternatives"]
                         if x["delta_bic"] is not None]
                ambiguities.append({"claimed": g, "alternatives": alts, "note": (
                    f"{g} and {', '.join(alts)} explain the measured transfer function about "
                    f"equally well in the flights that claimed them (votes: "
                    + ", ".join(f"{a} {len(exact.get(a, []))}/{n}" for a in [g, *alts])
                    + ("); the data cannot tell them apart" if not named else
                       f"); where a flight's fit on all blocks named {g}, it was better by a "
                       f"median ΔBIC {min(named):.1f}, evidence {bic_evidence(min(named))} "
                       "(Kass & Raftery)"))})
            effects.append(entry)
    # per-flight effects: the reference flight's values head the list
    per_flight: dict[str, dict[str, Any]] = {}
    for name in PER_FLIGHT_EFFECTS:
        by = {f: claims[f][name]["params"] for f in ids if name in claims[f]}
        if by:
            per_flight[name] = by
        if name in claims.get(reference, {}):
            e = dict(claims[reference][name])
            e.update(scope="per_flight", reference_flight=reference, params_by_flight=by,
                     flights_claimed=list(by), votes=f"{len(by)}/{n}")
            effects.append(e)
    ref_order = [e["name"] for e in docs[reference]["effects"]] if reference in docs else []
    effects.sort(key=lambda e: (ref_order.index(e["name"]) if e["name"] in ref_order
                                else len(ref_order)))
    base = {k: _median([docs[f]["baseline"][k] for f in ids])
            for k in ("q", "lv_satellite", "lv_simulated", "rmse", "spectral_error")}
    base["spectral_error_whole"] = _median([docs[f]["baseline"].get("spectral_error_whole")
                                            for f in ids])
    base["q_by_flight"] = {f: docs[f]["baseline"]["q"] for f in ids}
    q_ref = [docs[f]["refined"]["q"] for f in ids]
    q_stat = _median([docs[f]["refined"].get("q_sigma") for f in ids])
    q_sp = _spread(q_ref)
    rq = _median(q_ref)
    phys = docs[ids[0]]["refined"].get("physical_q_range", [0.5, 2.0])
    refined = {"q": rq, "q_sigma": q_sp if n >= 2 else q_stat,
               "q_sigma_kind": ("between-flight spread" if n >= 2 else "statistical"),
               "q_sigma_statistical": q_stat,
               "q_in_physical_range": bool(phys[0] <= rq <= phys[1]),
               "physical_q_range": list(phys),
               "rmse": _median([docs[f]["refined"]["rmse"] for f in ids]),
               "spectral_error": _median([docs[f]["refined"]["spectral_error"] for f in ids]),
               "spectral_error_whole": _median([docs[f]["refined"].get("spectral_error_whole")
                                                for f in ids]),
               "q_by_flight": dict(zip(ids, q_ref, strict=True))}
    cands = sorted({k for f in ids for k in docs[f].get("candidates_delta_bic", {})})
    cand = {k: _median([docs[f].get("candidates_delta_bic", {}).get(k) for f in ids])
            for k in cands}
    return {
        "baseline": base, "effects": effects, "refined": refined,
        "ambiguities": ambiguities, "candidates_delta_bic": cand,
        "detection_limits": combine_limits([docs[f].get("detection_limits", {}) for f in ids],
                                           need, rq),
        "per_flight_effects": per_flight, "not_carried": not_carried,
        "combination": {
            "rule": "majority", "flights": ids, "n_flights": n, "votes_needed": need,
            "note": ("a satellite effect is claimed when a strict majority of flights claims "
                     "it (indistinguishable effects vote together); parameters are medians "
                     "over the claiming flights, uncertainties the between-flight spread; "
                     "baseline/refined numbers are medians over flights (q_by_flight gives "
                     "each); misregistration and scene_change are per flight (the list shows "
                     "the reference flight's)")},
    }
