"""One cow, one feature: duplicates of one flight merge, other flights never do."""

from __future__ import annotations

import geopandas as gpd
import numpy as np
import pytest
import shapely

from geosim.errors import ConfigError
from geosim.labels.dedupe import dedupe_labels, duplicate_pairs

CRS = "EPSG:32756"


def frame(rows):
    flights, geoms = zip(*rows, strict=True)
    n = len(rows)
    return gpd.GeoDataFrame({"flight": list(flights),
                             "source_file": [f"f{i}.txt" for i in range(n)],
                             "source_line": np.arange(1, n + 1)},
                            geometry=list(geoms), crs=CRS)


def cow(x, y, w=2.0, h=1.0):
    return shapely.box(x, y, x + w, y + h)


def test_same_cow_in_two_patches_becomes_one_feature():
    # Same cow, boxes drawn 5 cm apart in two overlapping patches (IoU ~ 0.93), plus a
    # partial box cut by a patch edge (70 % of the cow, IoU 0.7).
    labels = frame([("PA1", cow(100.0, 200.0)), ("PA1", cow(100.05, 200.02)),
                    ("PA1", cow(100.0, 200.0, w=1.4)), ("PA1", cow(110.0, 200.0))])
    out = dedupe_labels(labels, iou_threshold=0.5)
    assert len(out) == 2
    merged = out[out["n_merged"] > 1].iloc[0]
    assert merged["n_merged"] == 3
    assert merged["merged_from"] == "f0.txt:1;f1.txt:2;f2.txt:3"
    # The most complete box (largest area) is kept; first in input order on a tie.
    assert merged.geometry.area == pytest.approx(2.0)
    assert merged["source_line"] in (1, 2)
    assert out[out["n_merged"] == 1].iloc[0]["merged_from"] == ""


def test_different_flights_are_never_merged():
    labels = frame([("PA1", cow(0.0, 0.0)), ("PA2", cow(0.0, 0.0))])
    assert len(dedupe_labels(labels)) == 2


def test_neighbours_below_threshold_stay_apart():
    # Two cattle side by side, overlapping boxes with IoU = 0.6/3.4 = 0.18.
    labels = frame([("PA1", cow(0.0, 0.0)), ("PA1", cow(1.4, 0.0))])
    assert len(dedupe_labels(labels, iou_threshold=0.5)) == 2
    assert len(dedupe_labels(labels, iou_threshold=0.15)) == 1


def test_iou_pairs_known_answer():
    a, b = cow(0, 0), cow(1.0, 0.0)      # intersection 1, union 3 -> IoU 1/3
    assert duplicate_pairs(np.array([a, b]), iou_threshold=0.33).tolist() == [[0, 1]]
    assert duplicate_pairs(np.array([a, b]), iou_threshold=0.34).size == 0


def test_duplicates_chain_transitively():
    labels = frame([("PA1", cow(0.0, 0.0)), ("PA1", cow(0.5, 0.0)), ("PA1", cow(1.0, 0.0))])
    # IoU(0,1) = IoU(1,2) = 0.6, IoU(0,2) = 1/3: one group through the middle box.
    assert len(dedupe_labels(labels, iou_threshold=0.5)) == 1


def test_order_and_empty():
    labels = frame([("PA2", cow(5, 5)), ("PA1", cow(0, 0))])
    out = dedupe_labels(labels)
    assert out["flight"].tolist() == ["PA2", "PA1"]
    assert len(dedupe_labels(labels.iloc[:0])) == 0
    with pytest.raises(ConfigError):
        dedupe_labels(labels, iou_threshold=0.0)
