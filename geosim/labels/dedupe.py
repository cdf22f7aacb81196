"""One cow, one feature: merge duplicate labels of the same flight.

When a flight is labelled in overlapping patches, a cow in the overlap is
labelled twice (or a cow cut by a patch edge is labelled whole in one patch and
in part in the other). Two labels of the *same flight* are duplicates when
their intersection over union (IoU), measured on the polygons in map
coordinates, reaches a threshold. Duplicates are grouped transitively
(connected components of the "is a duplicate of" graph), and each group
becomes one feature: the member with the largest area (the most complete
box, as the labeller drew it), with ``n_merged`` and ``merged_from`` (every
member's ``source_file:source_line``) recording what was merged. Labels of
different flights are never merged: they are different moments.
"""

from __future__ import annotations

import geopandas as gpd
import numpy as np
import shapely
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from geosim.errors import ConfigError

#: Default IoU at which two labels of one flight are the same cow.
DEFAULT_IOU = 0.5


def duplicate_pairs(geoms: np.ndarray, *, iou_threshold: float) -> np.ndarray:
    """Index pairs ``(k, 2)`` (i < j) of polygons whose IoU is at least ``iou_threshold``.

    Candidate pairs come from an STR-tree query on bounding boxes, so this is
    close to linear in the number of labels.
    """
    geoms = np.asarray(geoms, dtype=object).reshape(-1)
    if geoms.size < 2:
        return np.zeros((0, 2), dtype=np.int64)
    tree = shapely.STRtree(geoms)
    left, right = tree.query(geoms, predicate="intersects")
    upper = left < right
    i, j = left[upper], right[upper]
    if i.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    inter = shapely.area(shapely.intersection(geoms[i], geoms[j]))
    union = shapely.area(geoms[i]) + shapely.area(geoms[j]) - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
    hit = iou >= iou_threshold
    return np.column_stack([i[hit], j[hit]]).astype(np.int64)


def group_duplicates(geoms: np.ndarray, *, iou_threshold: float = DEFAULT_IOU) -> np.ndarray:
    """Group label per polygon ``(n,)``: polygons in one group are one cow."""
    geoms = np.asarray(geoms, dtype=object).reshape(-1)
    n = geoms.size
    pairs = duplicate_pairs(geoms, iou_threshold=iou_threshold)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, groups = connected_components(graph, directed=False)
    return groups


def dedupe_labels(labels: gpd.GeoDataFrame, *, iou_threshold: float = DEFAULT_IOU,
                  flight_column: str = "flight") -> gpd.GeoDataFrame:
    """Merge duplicate labels of the same flight (IoU in map coordinates).

    Parameters
    ----------
    labels
        Label polygons in a projected CRS with a ``flight`` column; ``source_file``
        and ``source_line`` are used to record merges when present.
    iou_threshold
        Intersection over union (dimensionless, (0, 1]) at which two labels of one
        flight are the same cow.

    Returns
    -------
    geopandas.GeoDataFrame
        One row per cow, in input order of the kept member, with ``n_merged`` (int,
        1 for a label that had no duplicate) and ``merged_from`` (``;``-separated
        ``file:line`` of all members, empty when ``n_merged == 1``).
    """
    if not 0.0 < iou_threshold <= 1.0:
        raise ConfigError(f"IoU threshold {iou_threshold} must be in (0, 1]")
    out_rows: list[int] = []
    n_merged: dict[int, int] = {}
    merged_from: dict[int, str] = {}
    geoms = np.asarray(labels.geometry.values, dtype=object)
    area = shapely.area(geoms)
    has_src = {"source_file", "source_line"} <= set(labels.columns)
    src = ([f"{f}:{line}" for f, line in zip(labels["source_file"], labels["source_line"],
                                              strict=True)] if has_src else [])
    for _, pos in labels.groupby(flight_column, sort=False).indices.items():
        pos = np.asarray(pos)
        groups = group_duplicates(geoms[pos], iou_threshold=iou_threshold)
        # Per group, the largest area wins; ties go to the first in input order.
        order = np.lexsort((pos, -area[pos], groups))
        starts = np.flatnonzero(np.r_[True, groups[order][1:] != groups[order][:-1]])
        for members_k in np.split(order, starts[1:]):
            best = int(pos[members_k[0]])
            out_rows.append(best)
            n_merged[best] = int(members_k.size)
            if members_k.size > 1 and has_src:
                merged_from[best] = ";".join(src[m] for m in np.sort(pos[members_k]))
    out_rows.sort()
    out = labels.iloc[out_rows].copy()
    out["n_merged"] = [n_merged[r] for r in out_rows]
    out["merged_from"] = [merged_from.get(r, "") for r in out_rows]
    return out.reset_index(drop=True)
