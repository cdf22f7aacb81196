"""Movement of cattle between two flights of the same site (beyond the paper).

Each cow of flight A is matched to at most one cow of flight B and vice versa,
by centre distance in metres, within a gate radius: an optimal one-to-one
assignment (Hungarian algorithm, :func:`scipy.optimize.linear_sum_assignment`)
that first maximises the number of matches within the radius and then
minimises their total distance. To stay fast for large herds the assignment is
solved separately on each connected group of cattle that can reach each other
within the radius (a k-d tree finds the candidate pairs).

Categories
----------
stayed
    matched, centre moved at most ``stayed_within_m``
moved
    matched, centre moved more than ``stayed_within_m`` (and at most ``radius_m``)
gone
    in A, no match in B (left the surveyed area, hidden, or moved beyond the radius)
appeared
    in B, no match in A

Positions should be in the aligned frame (the labels step's output), so
georeferencing error does not look like movement.

Limitation: positions alone do not identify animals. Where cattle move further
than they stand apart (a grazing herd), a ``moved`` pair is the explanation with
the least total displacement, not necessarily the same animal; ``stayed`` is
reliable. On the sample site (PA1 -> PA2, 30 m) all 14 ``stayed`` are the
animals that stood still, while 4 of 21 ``moved`` lines join the same animal
(the grazing cattle moved a median 18 m while standing 4.3 m apart).
"""

from __future__ import annotations

import os
from pathlib import Path

import geopandas as gpd
import numpy as np
import pandas as pd
import shapely
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from geosim.errors import ConfigError, LabelError
from geosim.io.atomic import write_text
from geosim.io.vector import write_geojson
from geosim.labels.georef import linear_unit_m
from geosim.labels.paddocks import cattle_centres

CATEGORIES = ("stayed", "moved", "gone", "appeared")

MOVEMENT_COLUMNS = ("category", "flight_a", "flight_b", "id_a", "id_b", "x_a", "y_a", "x_b",
                    "y_b", "distance_m")


def match_points(xy_a: np.ndarray, xy_b: np.ndarray, *, radius_m: float,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one matching of two point sets within a radius.

    Parameters
    ----------
    xy_a, xy_b
        ``(n, 2)`` and ``(m, 2)`` positions in metres (a projected CRS).
    radius_m
        Gate: pairs farther apart than this are never matched, metres.

    Returns
    -------
    pairs
        ``(k, 2)`` int indices ``(i into a, j into b)``, sorted by ``i``.
    distance_m
        ``(k,)`` distances of the matched pairs, metres.

    Notes
    -----
    Within each connected group the cost of a pair is its distance, and a
    non-candidate pair costs more than any set of candidate pairs can, so the
    optimal assignment uses as few non-candidates as possible (maximum number of
    matches) and among those has the smallest total distance; non-candidates are
    then discarded.
    """
    if not radius_m > 0:
        raise ConfigError(f"radius_m = {radius_m} must be > 0 (metres)")
    a = np.asarray(xy_a, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(xy_b, dtype=np.float64).reshape(-1, 2)
    n, m = len(a), len(b)
    if n == 0 or m == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    cand = cKDTree(a).sparse_distance_matrix(cKDTree(b), radius_m, output_type="ndarray")
    if cand.size == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    ci, cj, cd = cand["i"].astype(np.int64), cand["j"].astype(np.int64), cand["v"]
    # Bipartite graph: nodes 0..n-1 are A, n..n+m-1 are B.
    graph = coo_matrix((np.ones(ci.size), (ci, cj + n)), shape=(n + m, n + m))
    _, comp = connected_components(graph, directed=False)
    comp_a, comp_b = comp[:n], comp[n:]
    pairs: list[tuple[int, int]] = []
    for c in np.unique(comp[ci]):
        ia = np.flatnonzero(comp_a == c)
        jb = np.flatnonzero(comp_b == c)
        sel = comp_a[ci] == c
        big = radius_m * (min(ia.size, jb.size) + 1) * 2.0
        cost = np.full((ia.size, jb.size), big)
        allowed = np.zeros((ia.size, jb.size), dtype=bool)
        ra = np.searchsorted(ia, ci[sel])
        rb = np.searchsorted(jb, cj[sel])
        cost[ra, rb] = cd[sel]
        allowed[ra, rb] = True
        rows, cols = linear_sum_assignment(cost)
        ok = allowed[rows, cols]
        pairs.extend(zip(ia[rows[ok]].tolist(), jb[cols[ok]].tolist(), strict=True))
    pairs_arr = np.array(sorted(pairs), dtype=np.int64).reshape(-1, 2)
    dist = np.hypot(*(a[pairs_arr[:, 0]] - b[pairs_arr[:, 1]]).T)
    return pairs_arr, dist


def cattle_movement(cattle: gpd.GeoDataFrame, flight_a: str, flight_b: str, *,
                    radius_m: float, stayed_within_m: float = 1.0,
                    id_column: str = "cattle_id") -> gpd.GeoDataFrame:
    """Match cattle between two flights and classify stayed / moved / gone / appeared.

    Parameters
    ----------
    cattle
        Cattle features (boxes or centres) with a ``flight`` column, in a
        projected CRS (metres); the labels step's ``cattle`` layer.
    flight_a, flight_b
        The earlier and the later flight ids.
    radius_m
        Largest distance a cow may have moved to be matched, metres.
    stayed_within_m
        A matched cow whose centre moved at most this far "stayed", metres
        (absorbs labelling and alignment noise; a cow turning on the spot moves
        its box centre by under a metre).
    id_column
        Column with a cow's feature id (the row index is used when absent).

    Returns
    -------
    geopandas.GeoDataFrame
        Columns :data:`MOVEMENT_COLUMNS`; geometry is a line from A to B for matched
        cattle, the A position for ``gone`` and the B position for ``appeared``.
        Rows: matched (by A order), then gone, then appeared.
    """
    if cattle.crs is None or not cattle.crs.is_projected:
        raise LabelError("cattle features must be in a projected CRS (metres) to measure "
                         "movement; use labels/cattle.gpkg (site CRS)")
    if not 0 <= stayed_within_m <= radius_m:
        raise ConfigError(f"stayed_within_m = {stayed_within_m} must be in [0, radius_m = "
                          f"{radius_m}]")
    unit = linear_unit_m(cattle.crs)
    flights = cattle["flight"].astype(str)
    for f in (flight_a, flight_b):
        if not (flights == f).any():
            known = ", ".join(dict.fromkeys(flights)) or "none"
            raise LabelError(f"no cattle of flight {f!r} in the labels (flights: {known})")
    centres = cattle_centres(cattle)
    xy = shapely.get_coordinates(centres.to_numpy()) * unit
    ids = (cattle[id_column].astype(str).to_numpy() if id_column in cattle.columns
           else cattle.index.astype(str).to_numpy())
    ia = np.flatnonzero((flights == flight_a).to_numpy())
    ib = np.flatnonzero((flights == flight_b).to_numpy())
    pairs, dist = match_points(xy[ia], xy[ib], radius_m=radius_m)

    rows: list[dict] = []
    geoms: list[shapely.Geometry] = []

    def row(cat: str, i: int | None, j: int | None, d: float) -> None:
        pa = xy[ia[i]] if i is not None else (np.nan, np.nan)
        pb = xy[ib[j]] if j is not None else (np.nan, np.nan)
        rows.append({"category": cat, "flight_a": flight_a, "flight_b": flight_b,
                     "id_a": ids[ia[i]] if i is not None else "",
                     "id_b": ids[ib[j]] if j is not None else "",
                     "x_a": pa[0] / unit, "y_a": pa[1] / unit,
                     "x_b": pb[0] / unit, "y_b": pb[1] / unit, "distance_m": d})
        if i is not None and j is not None:
            geoms.append(shapely.LineString([pa / unit, pb / unit]))
        else:
            geoms.append(shapely.Point((pa if i is not None else pb) / unit))

    for (i, j), d in zip(pairs, dist, strict=True):
        row("stayed" if d <= stayed_within_m else "moved", int(i), int(j), float(d))
    for i in np.setdiff1d(np.arange(ia.size), pairs[:, 0]):
        row("gone", int(i), None, np.nan)
    for j in np.setdiff1d(np.arange(ib.size), pairs[:, 1]):
        row("appeared", None, int(j), np.nan)
    table = pd.DataFrame(rows, columns=list(MOVEMENT_COLUMNS))
    return gpd.GeoDataFrame(table, geometry=geoms, crs=cattle.crs)


def movement_summary(movement: pd.DataFrame) -> dict[str, int]:
    """Count of each category (all four keys present)."""
    counts = movement["category"].value_counts()
    return {c: int(counts.get(c, 0)) for c in CATEGORIES}


def write_movement(movement: gpd.GeoDataFrame, out_dir: str | os.PathLike[str],
                   ) -> tuple[Path, Path]:
    """Write ``movement_<A>_<B>.geojson`` (RFC 7946 lines/points) and ``.csv``, atomically.

    Returns
    -------
    tuple of Path
        The GeoJSON and CSV paths.
    """
    out = Path(out_dir)
    if len(movement):
        a, b = movement["flight_a"].iat[0], movement["flight_b"].iat[0]
        stem = f"movement_{a}_{b}"
    else:
        stem = "movement"
    geojson = write_geojson(movement, out / f"{stem}.geojson")
    csv = write_text(out / f"{stem}.csv",
                     movement.drop(columns="geometry").to_csv(index=False, float_format="%.3f"))
    return geojson, csv
