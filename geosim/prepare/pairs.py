"""The patch-pair manifest ``pairs.csv``: every unordered pair of flights for every tile.

Columns (docs/outputs.md)::

    pair_id,tile_id,flight_a,flight_b,acquired_a,acquired_b,path_a,path_b,
    minx,miny,maxx,maxy,crs

``flight_a`` comes before ``flight_b`` in site order; ``pair_id`` is
``{tile_id}_{flight_a}_{flight_b}``; paths are relative to the run folder; bounds
are the tile's, in the site CRS (metres). Pixels are referenced, never copied.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import itertools
from collections.abc import Mapping, Sequence
from typing import Any

COLUMNS = ("pair_id", "tile_id", "flight_a", "flight_b", "acquired_a", "acquired_b",
           "path_a", "path_b", "minx", "miny", "maxx", "maxy", "crs")


def tile_path(flight: str, tid: str) -> str:
    """Path of a tile file relative to the run folder."""
    return f"tiles/{flight}/{tid}.tif"


def pair_rows(tiles: Sequence[Mapping[str, Any]], flights: Sequence[str],
              acquired: Mapping[str, dt.datetime | str | None]) -> list[dict[str, Any]]:
    """One row per tile per unordered pair of flights that both have that tile.

    Parameters
    ----------
    tiles
        Tile records with ``tile_id``, ``minx``…``maxy``, ``crs`` and ``flights``
        (comma-separated ids of the flights that have the tile file).
    flights
        Flight ids in site order.
    acquired
        Acquisition time of each flight.
    """
    def iso(v: dt.datetime | str | None) -> str:
        return "" if v is None else v.isoformat() if isinstance(v, dt.datetime) else str(v)

    rows = []
    for t in tiles:
        have = set(str(t["flights"]).split(",")) if t.get("flights") else set(flights)
        present = [f for f in flights if f in have]
        for a, b in itertools.combinations(present, 2):
            rows.append({
                "pair_id": f"{t['tile_id']}_{a}_{b}", "tile_id": t["tile_id"],
                "flight_a": a, "flight_b": b,
                "acquired_a": iso(acquired.get(a)), "acquired_b": iso(acquired.get(b)),
                "path_a": tile_path(a, t["tile_id"]), "path_b": tile_path(b, t["tile_id"]),
                "minx": t["minx"], "miny": t["miny"], "maxx": t["maxx"], "maxy": t["maxy"],
                "crs": t["crs"],
            })
    return rows


def pairs_csv_text(rows: Sequence[Mapping[str, Any]]) -> str:
    """CSV text with the header, floats written with full precision."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: (repr(float(v)) if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()
