"""Make the sample site: world, three flights, labels, a satellite scene, truth.

``make_sample_site(out_dir, seed=0)`` writes::

    flights/PA1.tif, PA2.tif, PA3.tif   0.05 m RGB orthomosaics, EPSG:28356
    satellite/satellite.tif             0.5 m RGB scene, EPSG:32756
    labels/PA1/PA1.txt, classes.txt     YOLO (LabelImg layout), likewise PA2
    labels/PA3.geojson                  boxes in PA3's stated georeference (RFC 7946)
    paddocks.geojson                    paddock polygons with "name" (RFC 7946)
    truth.json                          everything true about the site
    site.toml                           the site file for ``geosim run``
    README.md                           how it was made and what is in it
    checksums.json                      decoded-pixel and file checksums

Every random choice comes from generators derived from ``seed`` and a fixed
name per component, so one component's draws do not shift another's.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import math
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import rasterio
import shapely
from pyproj import Transformer
from rasterio.enums import ColorInterp
from shapely.geometry import Point, Polygon

from geosim.io.atomic import write_json, write_text
from geosim.io.raster import create_geotiff, provenance_tags, read_valid_mask, write_geotiff
from geosim.log import get_logger
from geosim.samples import cattle as cattle_mod
from geosim.samples import flights as flights_mod
from geosim.samples import labels as labels_mod
from geosim.samples import satellite as sat_mod
from geosim.samples.illumination import Illumination
from geosim.samples.render import World, build_world, render
from geosim.samples.sun import SunPosition, sun_for

CENTRE_XY = (255140.0, 6184870.0)          # EPSG:28356, west of Mittagong, Southern Highlands NSW
WORLD_CRS = "EPSG:28356"
AEST = dt.timezone(dt.timedelta(hours=10))
FLIGHTS = (  # id, local time, offset of the planned centre from the site centre (m), encoding
    ("PA1", dt.datetime(2021, 7, 15, 11, 0, tzinfo=AEST), (-1.5, 1.0), "alpha"),
    ("PA2", dt.datetime(2021, 7, 15, 13, 0, tzinfo=AEST), (2.0, -1.5), "nodata"),
    ("PA3", dt.datetime(2021, 7, 15, 15, 0, tzinfo=AEST), (-0.5, 2.5), "internal_mask"),
)
SATELLITE_TIME = dt.datetime(2021, 9, 21, 9, 56, tzinfo=AEST)
HERD_SIZE = 38
FENCE_CLEARANCE_M = 3.0
FOOTPRINT_CLEARANCE_M = 3.0
COMMAND = "geosim samples make --out data/samples --seed {seed}"

OUTPUT_FILES = (
    "flights/PA1.tif", "flights/PA2.tif", "flights/PA3.tif", "satellite/satellite.tif",
    "labels/PA1/PA1.txt", "labels/PA1/classes.txt", "labels/PA2/PA2.txt",
    "labels/PA2/classes.txt", "labels/PA3.geojson", "paddocks.geojson", "truth.json",
    "site.toml", "README.md",
)


def component_rng(seed: int, name: str) -> np.random.Generator:
    """The generator of one named component, derived from the site seed."""
    return np.random.default_rng([int(seed), zlib.crc32(name.encode())])


def _r(v: float, nd: int = 4) -> float:
    return round(float(v), nd)


def _xy(p: tuple[float, float] | np.ndarray, nd: int = 4) -> list[float]:
    return [_r(p[0], nd), _r(p[1], nd)]


# ---------------------------------------------------------------------- cattle


def _allowed_region(world: World, inside: shapely.Geometry,
                    footprints: list[Polygon], warp_discs: list[Polygon]) -> shapely.Geometry:
    """Where an animal's centre may stand: ≥ 3 m from fences and footprint edges,
    clear of the dam, trough, tree crowns and stitching warps."""
    lay = world.layout
    interiors = shapely.union_all([p.buffer(-FENCE_CLEARANCE_M) for p in lay.paddocks.values()])
    region = interiors.intersection(inside)
    holes = [lay.dam.buffer(3.0),
             Point(lay.trough.x, lay.trough.y).buffer(lay.trough.length_m / 2 + 2.5)]
    holes += [Point(t.x, t.y).buffer(1.25 * t.crown_radius_m + 1.0) for t in lay.trees]
    holes += [fp.exterior.buffer(FOOTPRINT_CLEARANCE_M) for fp in footprints]
    holes += warp_discs
    return region.difference(shapely.union_all(holes))


def _sample_point(rng: np.random.Generator, region: shapely.Geometry) -> np.ndarray:
    minx, miny, maxx, maxy = region.bounds
    shapely.prepare(region)
    for _ in range(10000):
        x, y = rng.uniform(minx, maxx), rng.uniform(miny, maxy)
        if shapely.contains_xy(region, x, y):
            return np.array([x, y])
    raise RuntimeError("could not sample a point in the region")


def _flight_day_herd(rng: np.random.Generator, herd: list[cattle_mod.Animal],
                     allowed: shapely.Geometry, core: shapely.Geometry,
                     paddocks: dict[str, Polygon], n_flights: int
                     ) -> list[list[cattle_mod.Cow]]:
    """Poses at each flight of one day: groups that graze and drift, a few animals
    moved between groups (and paddocks) by the farmer, some standing still."""
    order = rng.permutation(len(herd))
    sizes = [13, 11, 7]
    groups: dict[int, int] = {}
    pos = 0
    for g, n in enumerate(sizes):
        for i in order[pos:pos + n]:
            groups[herd[i].id] = g
        pos += n
    strays = [herd[i] for i in order[pos:]]
    centres: dict[int, np.ndarray] = {}
    for g, name in enumerate(sorted(paddocks)):  # one grazing group per paddock
        region = core.intersection(paddocks[name])
        if region.area < 300.0:
            region = allowed.intersection(paddocks[name]).buffer(-4.0)
        centres[g] = _sample_point(rng, region if region.area > 100.0 else core)
    poses: list[cattle_mod.Cow] = []
    for g in range(len(sizes)):
        members = [a for a in herd if groups.get(a.id) == g]
        poses += cattle_mod.place_group(rng, members, centres[g], 7.0, allowed, poses)
    # Strays: some where only one or two flights see them.
    edge = allowed.difference(core.buffer(10.0))
    for k, a in enumerate(strays):
        region = edge if (k % 2 == 0 and edge.area > 50.0) else allowed
        poses += cattle_mod.place_group(rng, [a], _sample_point(rng, region), 0.5, allowed,
                                        poses)
        groups[a.id] = -a.id
        centres[-a.id] = np.array([poses[-1].x, poses[-1].y])
    by_id = {c.animal.id: c for c in poses}
    result = [[by_id[a.id] for a in herd]]
    for _ in range(1, n_flights):
        for g in range(len(sizes)):
            for _try in range(100):
                step = rng.uniform(5.0, 18.0)
                ang = rng.uniform(0, 2 * math.pi)
                cand = centres[g] + step * np.array([math.sin(ang), math.cos(ang)])
                if shapely.contains_xy(core, *cand):
                    centres[g] = cand
                    break
        for a in rng.choice(np.array([a.id for a in herd if groups[a.id] >= 0]), 3,
                            replace=False):
            groups[int(a)] = int((groups[int(a)] + 1 + rng.integers(0, 2)) % len(sizes))
        result.append(cattle_mod.move_herd(rng, result[-1], groups, centres, allowed))
    return result


def _satellite_day_herd(rng: np.random.Generator, herd: list[cattle_mod.Animal],
                        allowed: shapely.Geometry) -> list[cattle_mod.Cow]:
    poses: list[cattle_mod.Cow] = []
    order = rng.permutation(len(herd))
    for chunk in np.array_split(order, 3):
        centre = _sample_point(rng, allowed.buffer(-8.0))
        poses += cattle_mod.place_group(rng, [herd[i] for i in chunk], centre, 9.0, allowed,
                                        poses)
    return sorted(poses, key=lambda c: c.animal.id)


# ---------------------------------------------------------------------- writing


def _write_flight(path: Path, img: np.ndarray, mask: np.ndarray, spec: flights_mod.FlightSpec,
                  seed: int) -> None:
    tags = provenance_tags("samples", {"seed": seed, "flight": spec.id,
                                       "mask_encoding": spec.mask_encoding})
    tags["TIFFTAG_DATETIME"] = spec.acquired.strftime("%Y:%m:%d %H:%M:%S")
    desc = ["red", "green", "blue"]
    if spec.mask_encoding == "alpha":
        with create_geotiff(path, width=spec.width, height=spec.height, count=4, dtype="uint8",
                            crs=WORLD_CRS, transform=spec.stated_transform,
                            band_descriptions=[*desc, "alpha"], tags=tags) as dst:
            dst.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue,
                               ColorInterp.alpha]
            dst.write(img, [1, 2, 3])
            dst.write(mask.astype(np.uint8) * 255, 4)
    elif spec.mask_encoding == "nodata":
        write_geotiff(path, img, transform=spec.stated_transform, crs=WORLD_CRS, nodata=0,
                      band_descriptions=desc, tags=tags)
    elif spec.mask_encoding == "internal_mask":
        write_geotiff(path, img, transform=spec.stated_transform, crs=WORLD_CRS, mask=mask,
                      band_descriptions=desc, tags=tags)
    else:
        raise ValueError(f"unknown mask encoding {spec.mask_encoding!r}")


def raster_checksums(path: Path) -> dict[str, Any]:
    """Checksums of a raster's decoded pixels and valid mask (not of its bytes).

    File bytes may differ between GDAL versions (compression, metadata order);
    decoded pixels do not.
    """
    with rasterio.open(path) as ds:
        data = ds.read()
        mask = read_valid_mask(ds)
        t = ds.transform
        return {"pixels_sha256": hashlib.sha256(np.ascontiguousarray(data).tobytes()).hexdigest(),
                "mask_sha256": hashlib.sha256(np.ascontiguousarray(mask).tobytes()).hexdigest(),
                "shape": list(data.shape), "dtype": str(data.dtype),
                "crs": ds.crs.to_string() if ds.crs else None,
                "transform": [t.a, t.b, t.c, t.d, t.e, t.f]}


def site_checksums(out_dir: str | Path) -> dict[str, Any]:
    """Checksums of every generated file: GeoTIFFs by decoded pixels and mask,
    text and JSON files by their bytes."""
    out = Path(out_dir)
    files: dict[str, Any] = {}
    for rel in OUTPUT_FILES:
        p = out / rel
        if rel.endswith(".tif"):
            files[rel] = raster_checksums(p)
        else:
            files[rel] = {"sha256": hashlib.sha256(p.read_bytes()).hexdigest()}
    return files


def _site_toml() -> str:
    lines = [
        "# The bundled sample site (synthetic; see README.md and truth.json).",
        f"# Regenerate: {COMMAND.format(seed=0)}",
        "",
        "[site]",
        'name = "Southern Highlands sample"',
        'crs = "auto"',
        'reference_flight = "PA1"',
        "",
        "[parameters]",
        "tile_px = 500",
        "align_window_px = 1024",
        "",
    ]
    label_paths = {"PA1": "labels/PA1", "PA2": "labels/PA2", "PA3": "labels/PA3.geojson"}
    for fid, when, _, _ in FLIGHTS:
        lines += ["[[flights]]", f'id = "{fid}"', f'image = "flights/{fid}.tif"',
                  f'acquired = "{when.isoformat()}"', f'labels = "{label_paths[fid]}"', ""]
    lines += ["[satellite]", 'image = "satellite/satellite.tif"',
              f'acquired = "{SATELLITE_TIME.isoformat()}"', "", "[paddocks]",
              'path = "paddocks.geojson"', ""]
    return "\n".join(lines)


def _sun_dict(sun: SunPosition) -> dict[str, float]:
    return {"azimuth_deg": _r(sun.azimuth_deg, 4), "grid_azimuth_deg": _r(sun.grid_azimuth_deg, 4),
            "elevation_deg": _r(sun.elevation_deg, 4)}


def _relative(spec: flights_mod.FlightSpec, ref: flights_mod.FlightSpec) -> dict[str, Any]:
    """This flight's stated frame → the reference flight's stated frame."""
    m = (~ref.stated_to_true) @ spec.stated_to_true
    c = spec.centre_stated
    moved = m @ c
    return {"reference": ref.id,
            "stated_to_reference_stated": [[_r(m.a, 12), _r(m.b, 12), _r(m.c, 6)],
                                           [_r(m.d, 12), _r(m.e, 12), _r(m.f, 6)]],
            "rotation_deg": _r(math.degrees(math.atan2(m.d, m.a)), 6),
            "scale": _r(math.hypot(m.a, m.d), 9),
            "shift_m_at_image_centre": [_r(moved[0] - c[0], 4), _r(moved[1] - c[1], 4)]}


# ---------------------------------------------------------------------- main


def _flight_cattle(in_flight: list[Any], spec: Any, prev_pose: dict[int, Any] | None,
                   world: Any) -> tuple[list[dict[str, Any]], list[Any]]:
    """Truth entries and label boxes (image px) of the cattle in one flight."""
    to_stated = ~spec.stated_to_true
    entries, boxes = [], []
    for c in in_flight:
        centre = c.centre_xy()
        b = labels_mod.box_in_image(c.outline(), to_stated, spec.stated_transform)
        boxes.append(b)
        sb = labels_mod.stated_boxes([b], spec.stated_transform)[0].bounds
        moved = None
        if prev_pose is not None:
            p = prev_pose[c.animal.id]
            moved = (p.x, p.y, p.heading_deg) != (c.x, c.y, c.heading_deg)
        entries.append({
            "id": c.animal.id, "coat": c.animal.coat,
            "length_m": _r(c.animal.length_m, 4), "width_m": _r(c.animal.width_m, 4),
            "heading_deg": _r(c.heading_deg, 3), "head_turn_deg": _r(c.head_turn_deg, 3),
            "grazing": c.grazing,
            "centre_xy": _xy(centre), "body_xy": _xy((c.x, c.y)),
            "centre_stated_xy": _xy(to_stated @ centre),
            "box_px": [_r(v, 3) for v in b],
            "box_stated": [_r(v, 4) for v in sb],
            "paddock": world.layout.paddock_of(*centre),
            "moved_since_previous_flight": moved,
        })
    return entries, boxes


#: Conventions of truth.json, written into it.
TRUTH_CONVENTIONS: dict[str, str] = {
        "map_units": "metres; x = easting, y = northing",
        "pixel_coordinates": "(col, row) of the pixel's outer corner (rasterio); "
                             "pixel centres at +0.5",
        "transform": "rasterio Affine coefficients [a, b, c, d, e, f]: "
                     "x = a*col + b*row + c, y = d*col + e*row + f",
        "georef_error": "stated_to_true maps coordinates in a flight's stated frame (the "
                        "file's transform) to true coordinates: p_true = c + shift_m + "
                        "scale * R(rotation_deg) * (p_stated - c), c = about_stated_xy (the "
                        "image centre), R counter-clockwise positive in the east-north "
                        "plane. As matrix [[a, b, c], [d, e, f]]: x_true = a*x + b*y + c, "
                        "y_true = d*x + e*y + f. true_transform = stated_to_true * "
                        "stated_transform. A pixel shows the ground at true_transform * "
                        "(col, row) (plus local warps).",
        "relative_to_reference": "maps this flight's stated frame to the reference "
                                 "flight's stated frame (what an alignment to PA1 "
                                 "should recover)",
        "heading_deg": "direction the animal's head points, clockwise from grid north",
        "cattle_centre": "centre_xy = centre of the animal's outline's axis-aligned box "
                         "in EPSG:28356 (true position); centre_stated_xy = the same "
                         "point in the flight's stated frame; box_px = the label box "
                         "(col_min, row_min, col_max, row_max) in the flight image; "
                         "body_xy = body-axis mid-point",
        "local_warp": "the pixel at p shows what the undistorted image shows at p + d(p), "
                      "d = g*(amplitude_px*(cos a, sin a) + swirl_px*(p-c)perp/sigma_px), "
                      "g = exp(-|p-c|^2/(2 sigma_px^2)), pixel units",
        "exposure_seam": "pixels left of the directed line p0 -> p1 (image axes, row "
                         "down) are multiplied by gain_left",
        "radiometry": "scene radiance in DN where sunlit flat ground equals its albedo; "
                      "flights multiply by exposure_gain * white_balance_rgb; the "
                      "satellite chain's haze applies to the same radiance",
        "cattle_rules": "every animal is >= 3 m from fences and from every flight "
                        "footprint edge, clear of the dam, trough, tree crowns and warps",
    }


def _satellite_scene(out: Path, seed: int, world: Any, herd: Any, reference: Any,
                     lonlat: tuple[float, float], steps: Any) -> dict[str, Any]:
    """Render and write the satellite scene; its truth (truth.json ``satellite``)."""
    lon, lat = lonlat
    rng_sat = component_rng(seed, "satellite")
    sat = sat_mod.make_satellite_spec(rng_sat, SATELLITE_TIME, CENTRE_XY)
    fine = sat.fine_grid()
    corners = np.array([fine.pixel_to_map @ (c, r) for c, r in
                        ((0, 0), (fine.width, 0), (fine.width, fine.height), (0, fine.height))])
    sat_fp = Polygon(corners)
    sat_allowed = _allowed_region(world, sat_fp.buffer(-5.0), [], [])
    sat_poses = _satellite_day_herd(component_rng(seed, "satellite-cattle"), herd, sat_allowed)
    sat_sun = sun_for(SATELLITE_TIME, lon, lat, WORLD_CRS)
    radiance = render(world, fine, Illumination(sat_sun), sat_poses)
    steps.update()
    sat_img = sat_mod.apply_chain(radiance, sat.chain, component_rng(seed, "satellite-noise"))
    del radiance
    write_geotiff(out / "satellite" / "satellite.tif", sat_img, transform=sat.transform,
                  crs=sat_mod.SAT_CRS, band_descriptions=["red", "green", "blue"],
                  tags={**provenance_tags("samples", {"seed": seed, "scene": "satellite"}),
                        "TIFFTAG_DATETIME": SATELLITE_TIME.strftime("%Y:%m:%d %H:%M:%S")})
    steps.update()
    to_sat = Transformer.from_crs(WORLD_CRS, sat_mod.SAT_CRS, always_xy=True)
    sat_entries = []
    for c in sat_poses:
        centre = c.centre_xy()
        col, row = sat.world_to_pixel(np.array(centre[0]), np.array(centre[1]))
        sat_entries.append({
            "id": c.animal.id, "coat": c.animal.coat, "length_m": _r(c.animal.length_m, 4),
            "width_m": _r(c.animal.width_m, 4), "heading_deg": _r(c.heading_deg, 3),
            "centre_xy": _xy(centre), "centre_epsg32756_xy": _xy(to_sat.transform(*centre)),
            "pixel_colrow": [_r(col, 3), _r(row, 3)],
            "paddock": world.layout.paddock_of(*centre)})
    sat_truth = sat_mod.satellite_truth(sat)
    ref_inv = ~reference.stated_to_true
    in_ref = ref_inv @ CENTRE_XY
    sat_shift = sat.chain.shift_m
    sat_truth.update({
        "misregistration_vs_reference_flight": {
            "reference": reference.id,
            "shift_m_at_site_centre": [
                _r(CENTRE_XY[0] + sat_shift[0] - in_ref[0], 4),
                _r(CENTRE_XY[1] + sat_shift[1] - in_ref[1], 4)],
            "note": "a feature at true p appears in the satellite file at p + shift_m and in "
                    "the reference flight's stated frame at true_to_stated(p); this is the "
                    "satellite-minus-reference offset at the site centre; away from the centre "
                    "it changes with the reference flight's rotation and scale error, by "
                    "about |rotation in radians| × distance (7.6 cm per 10 m for 0.43°)"},
        "sun": _sun_dict(sat_sun),
        "n_cattle": len(sat_entries),
        "paddock_counts": {name: sum(e["paddock"] == name for e in sat_entries)
                           for name in world.layout.paddocks},
        "cattle": sat_entries,
    })
    return sat_truth


def _truth_document(seed: int, lonlat: tuple[float, float], world: Any, herd: Any,
                    truth_flights: dict[str, Any], sat_truth: dict[str, Any]) -> dict[str, Any]:
    """The content of truth.json."""
    lon, lat = lonlat
    lay = world.layout
    truth = {
        "about": "Ground truth of the synthetic sample site made by geosim.samples",
        "seed": seed,
        "command": COMMAND.format(seed=seed),
        "crs": {"world": WORLD_CRS, "flights": WORLD_CRS, "satellite": sat_mod.SAT_CRS,
                "geojson": "EPSG:4326 (RFC 7946)"},
        "site": {"name": "Southern Highlands sample", "centre_xy": list(CENTRE_XY),
                 "centre_lonlat": [_r(lon, 6), _r(lat, 6)], "bounds": list(lay.bounds)},
        "conventions": TRUTH_CONVENTIONS,
        "world": {
            "paddocks": {n: {"area_m2": _r(p.area, 1)} for n, p in lay.paddocks.items()},
            "fences": [[_xy(p, 3) for p in f] for f in lay.fences],
            "posts": len(lay.posts), "star_pickets": len(lay.pickets),
            "trees": [{"id": t.id, "xy": _xy((t.x, t.y), 3),
                       "crown_radius_m": _r(t.crown_radius_m, 3), "height_m": _r(t.height_m, 3),
                       "crown_base_m": _r(t.crown_base_m, 3)} for t in lay.trees],
            "dam": {"centroid_xy": _xy((lay.dam.centroid.x, lay.dam.centroid.y), 3),
                    "area_m2": _r(lay.dam.area, 1)},
            "trough": {"xy": _xy((lay.trough.x, lay.trough.y), 3),
                       "heading_deg": _r(lay.trough.heading_deg, 3),
                       "length_m": lay.trough.length_m, "width_m": lay.trough.width_m},
            "track_centreline": [_xy(p, 2) for p in lay.track[::20]],
        },
        "herd": [{"id": a.id, "coat": a.coat, "length_m": _r(a.length_m, 4),
                  "width_m": _r(a.width_m, 4)} for a in herd],
        "flights": truth_flights,
        "satellite": sat_truth,
    }
    return truth


def make_sample_site(out_dir: str | Path, *, seed: int = 0) -> dict[str, Any]:
    """Generate the sample site into ``out_dir``.

    Parameters
    ----------
    out_dir
        Output folder (created; existing files of the same names are replaced).
    seed
        Seed of every random choice. Seed 0 is the committed ``data/samples``.

    Returns
    -------
    dict
        Summary: files written, cattle per flight, satellite chain, seconds taken.
        Progress lines (one per flight) go to the ``geosim.samples`` logger at INFO.
    """
    from tqdm import tqdm

    t_start = time.perf_counter()
    out = Path(out_dir)
    say = get_logger("geosim.samples").info
    to_lonlat = Transformer.from_crs(WORLD_CRS, "EPSG:4326", always_xy=True)
    lon, lat = to_lonlat.transform(*CENTRE_XY)

    steps = tqdm(total=9, desc="sample site", unit="step", disable=None, leave=False)
    world = build_world({k: component_rng(seed, k) for k in ("layout", "ground", "trees")},
                        CENTRE_XY)
    steps.update()

    # Flights: footprints, errors, artefacts.
    specs: list[flights_mod.FlightSpec] = []
    tree_xyr = [(t.x, t.y, t.crown_radius_m) for t in world.layout.trees]
    for fid, when, (dx, dy), encoding in FLIGHTS:
        rng = component_rng(seed, f"flight-{fid}")
        spec = flights_mod.make_flight_spec(rng, fid, when, (CENTRE_XY[0] + dx, CENTRE_XY[1] + dy),
                                            mask_encoding=encoding)
        specs.append(flights_mod.add_artefacts(rng, spec, tree_xyr))
    footprints = [s.footprint_true() for s in specs]
    warp_discs = []
    for s in specs:
        for w in s.warps:
            x, y = s.true_transform @ w.centre_px
            warp_discs.append(Point(x, y).buffer(3.2 * w.sigma_px * flights_mod.UAV_GSD_M + 1.5))
    union = shapely.union_all(footprints)
    core = shapely.intersection_all(footprints).buffer(-12.0)

    # Cattle.
    rng_cattle = component_rng(seed, "cattle")
    herd = cattle_mod.make_herd(rng_cattle, HERD_SIZE)
    allowed = _allowed_region(world, union, footprints, warp_discs)
    for _attempt in range(20):
        day = _flight_day_herd(rng_cattle, herd, allowed, core.intersection(allowed),
                               world.layout.paddocks, len(specs))
        counts = [sum(fp.contains(Point(*c.centre_xy())) for c in poses)
                  for fp, poses in zip(footprints, day, strict=True)]
        if all(20 <= n <= 40 for n in counts):
            break
    else:
        raise RuntimeError(f"could not place 20–40 cattle in every flight (last: {counts})")
    steps.update()

    # Render and write the flights.
    truth_flights: dict[str, Any] = {}
    label_boxes: dict[str, list[tuple[float, float, float, float]]] = {}
    prev_pose: dict[int, cattle_mod.Cow] | None = None
    for spec, poses in zip(specs, day, strict=True):
        rng = component_rng(seed, f"render-{spec.id}")
        sun = sun_for(spec.acquired, lon, lat, WORLD_CRS)
        fp = spec.footprint_true()
        in_flight = [c for c in poses if fp.contains(Point(*c.centre_xy()))]
        radiance = render(world, spec.render_grid(), Illumination(sun), in_flight)
        mask = flights_mod.valid_mask(rng, spec)
        img = flights_mod.camera(radiance, spec, mask, rng)
        del radiance
        _write_flight(out / "flights" / f"{spec.id}.tif", img, mask, spec, seed)
        del img

        entries, boxes = _flight_cattle(in_flight, spec, prev_pose, world)
        label_boxes[spec.id] = boxes
        counts = {name: sum(e["paddock"] == name for e in entries)
                  for name in world.layout.paddocks}
        ft = flights_mod.flight_truth(spec)
        ft.update({
            "sun": _sun_dict(sun),
            "valid_pixels": int(mask.sum()),
            "footprint_true_area_m2": _r(fp.area, 2),
            "relative_to_reference": _relative(spec, specs[0]),
            "n_cattle": len(entries),
            "paddock_counts": counts,
            "cattle": entries,
        })
        truth_flights[spec.id] = ft
        prev_pose = {c.animal.id: c for c in poses}
        steps.update()
        say(f"{spec.id}: {spec.width}×{spec.height} px, {len(entries)} cattle, "
            f"sun el {sun.elevation_deg:.1f}°")

    sat_truth = _satellite_scene(out, seed, world, herd, specs[0], (lon, lat), steps)

    # Labels and paddocks.
    for spec in specs[:2]:
        labels_mod.write_yolo_folder(out / "labels" / spec.id, spec.id, label_boxes[spec.id],
                                     spec.width, spec.height)
    pa3 = specs[2]
    labels_mod.write_box_geojson(out / "labels" / f"{pa3.id}.geojson",
                                 labels_mod.stated_boxes(label_boxes[pa3.id],
                                                         pa3.stated_transform), WORLD_CRS)
    labels_mod.write_paddocks(out / "paddocks.geojson", world.layout.paddocks, WORLD_CRS)
    steps.update()

    truth = _truth_document(seed, (lon, lat), world, herd, truth_flights, sat_truth)
    write_json(out / "truth.json", truth)
    write_text(out / "site.toml", _site_toml())
    write_text(out / "README.md", _readme(truth, seed))
    checks = site_checksums(out)
    write_json(out / "checksums.json", {
        "about": "sha256 of decoded pixel arrays (all bands, bands-first, C order) and of the "
                 "valid mask (bool) of each GeoTIFF, and of the bytes of every other file. "
                 "GeoTIFF file bytes may differ between GDAL versions; decoded pixels do not.",
        "seed": seed, "files": checks})
    steps.update()
    steps.close()
    seconds = time.perf_counter() - t_start
    return {"out_dir": str(out), "seed": seed, "files": [*OUTPUT_FILES, "checksums.json"],
            "cattle_per_flight": {k: v["n_cattle"] for k, v in truth_flights.items()},
            "satellite_cattle": sat_truth["n_cattle"],
            "satellite_effects": sat_truth["effects"], "seconds": round(seconds, 1)}


def _readme(truth: dict[str, Any], seed: int) -> str:
    fl = truth["flights"]
    sat = truth["satellite"]
    eff = sat["effects"]
    rows = []
    for fid, f in fl.items():
        e = f["georef_error"]
        rows.append(
            f"| {fid} | {f['acquired'][11:16]} | {f['width']}×{f['height']} | "
            f"{f['mask_encoding']} | ({e['shift_m'][0]:+.3f}, {e['shift_m'][1]:+.3f}) | "
            f"{e['rotation_deg']:+.3f} | {e['scale']:.4f} | "
            f"{f['sun']['elevation_deg']:.1f}° / {f['sun']['azimuth_deg']:.1f}° | "
            f"{f['n_cattle']} | "
            + ", ".join(f"{k} {v}" for k, v in f["paddock_counts"].items()) + " |")
    table = "\n".join(rows)
    header = ("| flight | time | size px | nodata as | shift (x, y) m | rotation ° | scale "
              "| sun elev / az | cattle | per paddock |\n|---|---|---|---|---|---|---|---|---|---|")
    ms, hz, sn = eff["motion_smear"], eff["haze"], eff["sensor_noise"]
    chain_table = "\n".join([
        "| effect | parameters (satellite px, DN) |",
        "|---|---|",
        f"| optics (circular aperture) | q = {eff['optics']['q']} |",
        f"| atmospheric_blur | f0 = {eff['atmospheric_blur']['f0_cyc_per_px']} cycles/px |",
        f"| motion_smear | length {ms['length_px']} px, direction {ms['direction_deg']}° |",
        f"| detector_integration | pitch {eff['detector_integration']['pitch_px']} px (box) |",
        f"| haze | transmission {hz['transmission']}, path radiance "
        f"{hz['path_radiance_dn']} DN |",
        f"| sensor_noise | variance = {sn['gain_dn']} · signal + {sn['read_var_dn2']} DN² |",
        f"| misregistration | shift {eff['misregistration']['shift_m']} m (east, north) |",
    ])
    return f"""# Sample site (synthetic)

A small, physically reasoned synthetic site for trying and testing geosim: three
UAV flights of cattle paddocks on one winter day and a satellite scene of the same
ground two months later, with everything that is true about them in `truth.json`.
It is **synthetic**: no real imagery is contained or copied.

Made with (seed {seed}; the files here are exactly what this writes):

```
{truth['command']}
```

`tests/test_samples.py` regenerates it and compares `checksums.json` (decoded
pixel arrays and masks of the GeoTIFFs — file bytes may differ between GDAL
versions — and the bytes of every text and JSON file).

## The world

A paddock west of Mittagong, Southern Highlands, New South Wales, centred at
E {truth['site']['centre_xy'][0]:.0f} m, N {truth['site']['centre_xy'][1]:.0f} m in
GDA94 / MGA zone 56 (EPSG:28356), lon/lat {truth['site']['centre_lonlat'][0]:.4f},
{truth['site']['centre_lonlat'][1]:.4f}. It is procedural in map coordinates: a
ground albedo raster (pasture with texture at 25 m, 6 m, 1.5 m, 0.4 m and blade
scale, tussocks, bare patches, dung, cattle pads, a two-rut dirt track, a farm dam
with a muddy margin and an earth wall, long grass under the fences), plus fences
(wire, timber posts every 10 m, star pickets every 2.5 m), a concrete trough,
{len(truth['world']['trees'])} eucalypts and the cattle, rendered with the sun of
each acquisition (shadows of trees, trunks, posts, pickets, trough and cattle;
skylight makes shadows bluer). Three paddocks: {", ".join(truth['world']['paddocks'])}
(`paddocks.geojson`).

## Flights (`flights/`, 0.05 m, EPSG:28356, uint8 RGB, tiled, deflate)

Same day (2021-07-15, AEST), different times, each its own ragged footprint
(union of photo frames along a lawnmower pattern, some edge photos dropped),
nodata encoding, georeferencing error, exposure and white balance, one local
stitching warp near a tree at the edge and one diagonal exposure seam.

{header}
{table}

The georeferencing error is the map from a flight's stated frame to the truth
(`truth.json` → `flights.<id>.georef_error.stated_to_true`, with the convention
spelled out in `truth.json` → `conventions`). Cattle: 2.0–2.6 m × 0.7–1.0 m,
coats black Angus, black baldy, Hereford, red Angus, Murray Grey and brindle;
some stand still between flights, others graze on, a few are moved to another
group by the farmer. Every animal is ≥ 3 m from fences and from every footprint
edge, so per-paddock counts are unambiguous.

## Labels

- `labels/PA1/PA1.txt`, `labels/PA2/PA2.txt` (+ `classes.txt` = `cattle`): YOLO
  as LabelImg writes it, `0 cx cy w h` normalised to the flight image, 6 decimals;
  each box is the animal's outline as it appears in that image.
- `labels/PA3.geojson`: the same kind of boxes as polygons in PA3's *stated*
  georeference (what someone labelling in QGIS would draw), RFC 7946 lon/lat,
  `class = "cattle"`.

## Satellite scene (`satellite/satellite.tif`, 0.5 m, EPSG:32756)

{sat['width']}×{sat['height']} px, acquired {sat['acquired']} with its own sun
(elevation {sat['sun']['elevation_deg']:.1f}°) and its own cattle ({sat['n_cattle']}
animals). Rendered at 0.05 m on its own grid from the same world at the true
position of each pixel (EPSG:32756 → EPSG:28356 with pyproj), then a physics chain
richer than the paper's model:

{chain_table}

Noise raises the Laplacian variance and the extra blurs lower it, so the paper's
single blur metric, calibrated on this scene, returns one apparent Q that differs
from the optical one and says nothing about which physics it absorbed: the effects
are concealed from it. `truth.json` → `satellite.misregistration_vs_reference_flight`
gives the offset a comparison in PA1's (stated) frame should find.

## Files

`site.toml` (the site file for `geosim run data/samples/site.toml --out DIR`;
tiles of 500 px = 25 m so this small site yields several tiles),
`truth.json`, `checksums.json`, and the files above.
"""
