"""Site configuration: the TOML file that describes a site, validated on load.

A site file names its flights (id, image, acquisition time, optional labels),
the satellite scene, optional paddock polygons and processing parameters.
Paths are relative to the TOML file. Validation is strict: an unknown key, a
wrong type, a missing file or an image without a CRS is a :class:`ConfigError`
or :class:`InputFileError` whose message names the key or path and the fix.

Example
-------
.. code-block:: toml

    [site]
    name = "Southern Highlands sample"
    crs = "auto"
    reference_flight = "PA1"

    [parameters]
    tile_px = 500

    [[flights]]
    id = "PA1"
    image = "flights/PA1.tif"
    acquired = "2021-07-15T11:00:00+10:00"
    labels = "labels/PA1"

    [satellite]
    image = "satellite/satellite.tif"
    acquired = "2021-09-21T09:56:00+10:00"

    [paddocks]
    path = "paddocks.geojson"
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from geosim.errors import ConfigError, InputFileError
from geosim.io.atomic import to_jsonable
from geosim.io.paths import safe_name, unique_name

_FLIGHT_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

#: Allowed values of ``site.anchor``: the frame the aligned flights are put in.
#: ``reference_flight`` is the paper's behaviour (the reference flight's own
#: georeference); ``satellite`` also registers the reference flight to the
#: satellite scene so the aligned stack lands in the satellite's frame.
ANCHORS = ("reference_flight", "satellite")

#: Allowed values of ``parameters.align_model``: ``similarity`` (the paper's global
#: rotation + scale + translation) or ``local`` (the similarity, then a smooth local
#: displacement field, :mod:`geosim.align.field`).
ALIGN_MODELS = ("similarity", "local")
#: Allowed values of ``parameters.tile_compression`` (how ``geosim tile`` stores the UAV
#: tiles): ``deflate`` (default: DEFLATE level 1 + predictor, ≈ 45 MB per 5000 px RGB tile)
#: or ``none`` (uncompressed, ≈ 106 MB: 2.35× the disk, for a faster tile step and degrade
#: step; see docs/degradation.md). Both are read by GDAL, OpenCV and Pillow.
TILE_COMPRESSIONS = ("deflate", "none")


@dataclass(frozen=True)
class FlightConfig:
    """One UAV survey: an orthomosaic ("geo-image") and its optional labels.

    Attributes
    ----------
    id
        Short identifier used in file names (letters, digits, ``_ . -``).
    image
        Absolute path of the orthomosaic (any GDAL raster with a CRS).
    acquired
        Acquisition time (timezone-aware when the file gives an offset).
    labels
        Absolute path of a YOLO folder (LabelImg layout) or a GeoJSON/GPKG file.
    """

    id: str
    image: Path
    acquired: dt.datetime
    labels: Path | None = None


@dataclass(frozen=True)
class SatelliteConfig:
    """The real satellite scene used for calibration and diagnosis."""

    image: Path
    acquired: dt.datetime | None = None


@dataclass(frozen=True)
class Parameters:
    """Processing parameters, with the paper's values as defaults.

    Attributes
    ----------
    uav_gsd_m, sat_gsd_m
        Ground sample distances of the UAV and satellite grids, metres.
    tile_px
        Tile side on the UAV grid, pixels (the paper: 5000).
    keep_partial_tiles
        Keep tiles not fully covered by every flight (with their masks).
    align_window_px
        Side of the central window used for registration, UAV pixels.
    min_align_confidence
        Registration confidence below which alignment is refused.
    align_model
        ``"similarity"`` (default, the paper's) or ``"local"``: after the similarity, a
        smooth displacement field from phase correlation in a grid of windows corrects
        stitching warps (see ``docs/alignment.md``).
    q_min, q_max
        Search bracket for the calibrated Q (dimensionless).
    min_visible_fraction
        Labels clipped by a tile edge are dropped below this visible fraction.
    footprint_simplify_m
        Tolerance for simplifying traced footprints, metres.
    keep_intermediates
        Also write ``grid/<flight>.tif`` (each flight on the site grid). Off by default:
        flights are resampled once, straight from the original file onto the aligned
        grid, and registration reads them on the site grid on the fly.
    tile_compression
        How the UAV tiles are stored (one of :data:`TILE_COMPRESSIONS`): ``"deflate"``
        (default) or ``"none"`` (uncompressed: 2.35× the disk; the tiles step writes and the
        degrade step reads each 5000 px tile for ≈ 1 and ≈ 0.14 CPU-s less).
    q
        Fixed Q for the degradation (dimensionless). Unset (default): degrade with the
        mean Q calibrated against the satellite scene. Set it for a site without a
        satellite scene, or to simulate another camera; calibration still reports its Q.
    """

    uav_gsd_m: float = 0.05
    sat_gsd_m: float = 0.5
    tile_px: int = 5000
    keep_partial_tiles: bool = False
    align_window_px: int = 2000
    min_align_confidence: float = 0.1
    align_model: str = "similarity"
    q_min: float = 0.5
    q_max: float = 8.0
    min_visible_fraction: float = 0.5
    footprint_simplify_m: float = 0.5
    keep_intermediates: bool = False
    q: float | None = None
    tile_compression: str = "deflate"

    def __post_init__(self) -> None:
        positive = ("uav_gsd_m", "sat_gsd_m", "tile_px", "align_window_px", "q_min",
                    "q_max", "footprint_simplify_m")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"parameters.{name} = {getattr(self, name)!r} must be > 0")
        if self.q is not None and not (math.isfinite(self.q) and self.q > 0):
            raise ConfigError(f"parameters.q = {self.q!r} must be a positive number (e.g. 4.34)")
        if self.q_min >= self.q_max:
            raise ConfigError(f"parameters.q_min = {self.q_min} must be below q_max = {self.q_max}")
        if not 0.0 <= self.min_visible_fraction <= 1.0:
            raise ConfigError(f"parameters.min_visible_fraction = {self.min_visible_fraction} "
                              "must be in [0, 1]")
        if self.align_model not in ALIGN_MODELS:
            raise ConfigError(f"parameters.align_model = {self.align_model!r} is not allowed; "
                              f"use one of {', '.join(repr(m) for m in ALIGN_MODELS)}")
        if self.tile_compression not in TILE_COMPRESSIONS:
            raise ConfigError(f"parameters.tile_compression = {self.tile_compression!r} is not "
                              "allowed; use one of "
                              f"{', '.join(repr(m) for m in TILE_COMPRESSIONS)}")
        if not 0.0 <= self.min_align_confidence <= 1.0:
            raise ConfigError(f"parameters.min_align_confidence = {self.min_align_confidence} "
                              "must be in [0, 1]")
        ratio = self.sat_gsd_m / self.uav_gsd_m
        if abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 2:
            raise ConfigError(
                f"parameters: sat_gsd_m / uav_gsd_m = {self.sat_gsd_m} / {self.uav_gsd_m} = "
                f"{ratio:g} is not a whole number; choose GSDs so every satellite pixel is "
                "exactly φ×φ UAV pixels with φ ≥ 2 (e.g. 0.05 and 0.5); φ = 1 would "
                "compare the UAV imagery with itself")
        if self.tile_px % round(ratio):
            raise ConfigError(f"parameters.tile_px = {self.tile_px} is not a multiple of "
                              f"φ = {round(ratio)}; tiles must hold whole satellite pixels")

    @property
    def phi(self) -> int:
        """Satellite pixel size in UAV pixels (φ = sat_gsd_m / uav_gsd_m), a whole number."""
        return round(self.sat_gsd_m / self.uav_gsd_m)


@dataclass(frozen=True)
class SiteConfig:
    """A validated site: flights, satellite scene, paddocks and parameters.

    ``anchor`` (one of :data:`ANCHORS`) is the frame of the aligned flights:
    ``"reference_flight"`` (default, the paper's behaviour) or ``"satellite"``
    (the aligned stack is registered to the satellite scene; needs ``satellite``).
    """

    path: Path | None
    name: str
    crs: str
    reference_flight: str
    flights: tuple[FlightConfig, ...]
    satellite: SatelliteConfig | None = None
    paddocks: Path | None = None
    parameters: Parameters = field(default_factory=Parameters)
    anchor: str = "reference_flight"

    def __post_init__(self) -> None:
        if self.anchor not in ANCHORS:
            raise ConfigError(f"site.anchor = {self.anchor!r} is not allowed; use one of "
                              + ", ".join(f"'{a}'" for a in ANCHORS)
                              + " ('reference_flight' is the default)")
        if self.anchor == "satellite" and self.satellite is None:
            raise ConfigError("site.anchor = 'satellite' needs a satellite scene: add a "
                              "[satellite] table with the image path, or use "
                              "anchor = 'reference_flight'")

    def flight(self, flight_id: str) -> FlightConfig:
        """The flight with this id; ConfigError listing the known ids otherwise."""
        for f in self.flights:
            if f.id == flight_id:
                return f
        known = ", ".join(f.id for f in self.flights)
        raise ConfigError(f"no flight with id {flight_id!r} in this site (flights: {known})")

    @property
    def flight_ids(self) -> tuple[str, ...]:
        """Flight ids in site order."""
        return tuple(f.id for f in self.flights)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description (for run.json and provenance)."""
        out = to_jsonable(dataclasses.asdict(self))
        out["parameters"]["phi"] = self.parameters.phi
        return out


# --------------------------------------------------------------------------- loading

_TOP_KEYS = {"site", "parameters", "flights", "satellite", "paddocks"}
_SITE_KEYS = {"name", "crs", "reference_flight", "anchor"}
_FLIGHT_KEYS = {"id", "image", "acquired", "labels"}
_SATELLITE_KEYS = {"image", "acquired"}
_PADDOCK_KEYS = {"path"}


def _check_keys(table: Mapping[str, Any], allowed: set[str], where: str, src: Path) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ConfigError(f"{src}: unknown key '{where}{unknown[0]}'; allowed keys here: "
                          f"{', '.join(sorted(allowed))}")


def _table(value: Any, where: str, src: Path) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{src}: [{where}] must be a table, got {type(value).__name__}")
    return value


def _string(table: Mapping[str, Any], key: str, where: str, src: Path, *,
            required: bool = True, default: str | None = None) -> str | None:
    if key not in table:
        if required:
            raise ConfigError(f"{src}: missing required key {where}{key}")
        return default
    value = table[key]
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{src}: {where}{key} must be a non-empty string, got {value!r}")
    return value


def _time(table: Mapping[str, Any], key: str, where: str, src: Path, *,
          required: bool) -> dt.datetime | None:
    if key not in table:
        if required:
            raise ConfigError(f"{src}: missing required key {where}{key} (an ISO 8601 time, "
                              "e.g. 2021-07-15T13:10:00+10:00)")
        return None
    value = table[key]
    if isinstance(value, dt.datetime):
        return value
    if isinstance(value, dt.date):
        return dt.datetime(value.year, value.month, value.day)
    if isinstance(value, str):
        try:
            return dt.datetime.fromisoformat(value)
        except ValueError:
            pass
    raise ConfigError(f"{src}: {where}{key} = {value!r} is not a date-time; write ISO 8601, "
                      "e.g. 2021-07-15T13:10:00+10:00")


def _existing_path(base: Path, value: str, key: str, src: Path, *, kind: str) -> Path:
    p = (base / value).resolve() if not Path(value).is_absolute() else Path(value)
    if not p.exists():
        raise InputFileError(f"{src}: {key} = {value!r}: {p} does not exist; fix the path "
                             f"(relative paths are relative to the site file)")
    if kind == "file" and not p.is_file():
        raise InputFileError(f"{src}: {key} = {value!r}: {p} is not a file")
    return p


def _parameters(table: Mapping[str, Any], src: Path) -> Parameters:
    known = {f.name: f for f in fields(Parameters)}
    _check_keys(table, set(known), "parameters.", src)
    values: dict[str, Any] = {}
    for key, value in table.items():
        default = getattr(Parameters, key)
        if default is None:  # optional numbers (q)
            default = 0.0
        if isinstance(default, str):
            ok = isinstance(value, str)
        elif isinstance(default, bool):
            ok = isinstance(value, bool)
        elif isinstance(default, int):
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) \
                and math.isfinite(value)
        if not ok:
            raise ConfigError(f"{src}: parameters.{key} = {value!r} must be of type "
                              f"{type(default).__name__}")
        values[key] = float(value) if isinstance(default, float) else value
    try:
        return Parameters(**values)
    except ConfigError as exc:
        raise ConfigError(f"{src}: {exc}") from None


def _check_crs(value: str, src: Path) -> str:
    if value == "auto":
        return value
    from pyproj import CRS
    from pyproj.exceptions import CRSError as PyprojCRSError

    try:
        crs = CRS.from_user_input(value)
    except PyprojCRSError as exc:
        raise ConfigError(f"{src}: site.crs = {value!r} is not a CRS pyproj knows ({exc}); "
                          "use 'auto' or e.g. 'EPSG:28356'") from None
    if not crs.is_projected:
        raise ConfigError(f"{src}: site.crs = {value!r} is not a projected CRS; the shared grid "
                          "needs metres (use 'auto' for the UTM zone, or e.g. 'EPSG:28356')")
    return value


def _check_raster_has_crs(path: Path, key: str, src: Path) -> None:
    from geosim.io.bands import check_raster_bands
    from geosim.io.raster import open_raster

    with open_raster(path, what=f"{src}: {key}") as ds:
        check_raster_bands(ds, f"{src}: {key}")


def load_site(path: str | Path, *, check_rasters: bool = True) -> SiteConfig:
    """Load and validate a site file.

    Parameters
    ----------
    path
        The site TOML file.
    check_rasters
        Also open every image and refuse one without a CRS or georeference.

    Raises
    ------
    InputFileError
        The site file or a file it names does not exist.
    ConfigError
        Unknown key, wrong type, duplicate flight id, bad value.
    RasterError
        An image cannot be read or has no CRS.
    """
    src = Path(path).resolve()
    if not src.is_file():
        raise InputFileError(f"{path}: site file does not exist; give the path of a site TOML "
                             "(see data/samples/site.toml for an example)")
    try:
        doc = tomllib.loads(src.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{src}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{src}: not a text file; give a site TOML") from None
    base = src.parent
    _check_keys(doc, _TOP_KEYS, "", src)

    site = _table(doc.get("site", {}), "site", src)
    _check_keys(site, _SITE_KEYS, "site.", src)
    name = _string(site, "name", "site.", src, required=False, default=src.stem)
    crs = _check_crs(_string(site, "crs", "site.", src, required=False, default="auto"), src)

    raw_flights = doc.get("flights")
    if not isinstance(raw_flights, Sequence) or isinstance(raw_flights, str) or not raw_flights:
        raise ConfigError(f"{src}: no flights; add at least one [[flights]] table with id, "
                          "image and acquired")
    flights: list[FlightConfig] = []
    for i, raw in enumerate(raw_flights):
        where = f"flights[{i}]."
        raw = _table(raw, f"flights[{i}]", src)
        _check_keys(raw, _FLIGHT_KEYS, where, src)
        fid = _string(raw, "id", where, src)
        if not _FLIGHT_ID.match(fid):
            raise ConfigError(f"{src}: {where}id = {fid!r} must be 1–64 letters, digits, "
                              "'_', '.' or '-' (it is used in file names)")
        if fid in {f.id for f in flights}:
            raise ConfigError(f"{src}: duplicate flight id {fid!r}; ids must be unique")
        image = _existing_path(base, _string(raw, "image", where, src), f"{where}image", src,
                               kind="file")
        labels_value = _string(raw, "labels", where, src, required=False)
        labels = None if labels_value is None else _existing_path(
            base, labels_value, f"{where}labels", src, kind="any")
        flights.append(FlightConfig(id=fid, image=image,
                                    acquired=_time(raw, "acquired", where, src, required=True),
                                    labels=labels))

    satellite = None
    if "satellite" in doc:
        sat = _table(doc["satellite"], "satellite", src)
        _check_keys(sat, _SATELLITE_KEYS, "satellite.", src)
        satellite = SatelliteConfig(
            image=_existing_path(base, _string(sat, "image", "satellite.", src),
                                 "satellite.image", src, kind="file"),
            acquired=_time(sat, "acquired", "satellite.", src, required=False))

    paddocks = None
    if "paddocks" in doc:
        pad = _table(doc["paddocks"], "paddocks", src)
        _check_keys(pad, _PADDOCK_KEYS, "paddocks.", src)
        paddocks = _existing_path(base, _string(pad, "path", "paddocks.", src),
                                  "paddocks.path", src, kind="file")

    parameters = _parameters(_table(doc.get("parameters", {}), "parameters", src), src)
    ids = [f.id for f in flights]
    reference = _string(site, "reference_flight", "site.", src, required=False, default=ids[0])
    if reference not in ids:
        raise ConfigError(f"{src}: site.reference_flight = {reference!r} is not a flight id "
                          f"(flights: {', '.join(ids)})")

    anchor = site.get("anchor", "reference_flight")
    if not isinstance(anchor, str) or anchor not in ANCHORS:
        raise ConfigError(f"{src}: site.anchor = {anchor!r} is not allowed; use one of "
                          + ", ".join(f"'{a}'" for a in ANCHORS)
                          + " ('reference_flight' is the default)")

    if check_rasters:
        for i, f in enumerate(flights):
            _check_raster_has_crs(f.image, f"flights[{i}].image", src)
        if satellite is not None:
            _check_raster_has_crs(satellite.image, "satellite.image", src)

    try:
        return SiteConfig(path=src, name=name, crs=crs, reference_flight=reference,
                          flights=tuple(flights), satellite=satellite, paddocks=paddocks,
                          parameters=parameters, anchor=anchor)
    except ConfigError as exc:
        raise ConfigError(f"{src}: {exc}") from None


def site_from_images(uav_images: Sequence[str | Path], satellite: str | Path | None = None, *,
                     name: str = "images", crs: str = "auto", anchor: str = "reference_flight",
                     **parameters: Any) -> SiteConfig:
    """Build a site from image paths alone (for commands that take ``--uav``/``--satellite``).

    Flight ids are the file stems (made unique); acquisition times are unknown
    and set to the files' modification times. ``anchor`` is ``site.anchor``
    (:data:`ANCHORS`; ``"satellite"`` needs ``satellite``). Extra keyword
    arguments are :class:`Parameters` fields.
    """
    flights: list[FlightConfig] = []
    used: set[str] = set()
    for p in uav_images:
        path = Path(p).resolve()
        if not path.is_file():
            raise InputFileError(f"--uav {p}: file does not exist; check the path")
        fid = unique_name(safe_name(path.stem, default="flight"), used)
        _check_raster_has_crs(path, "--uav", path)
        mtime = dt.datetime.fromtimestamp(path.stat().st_mtime, tz=dt.UTC)
        flights.append(FlightConfig(id=fid, image=path, acquired=mtime))
    if not flights:
        raise ConfigError("no --uav images given; give at least one UAV orthomosaic")
    sat = None
    if satellite is not None:
        sp = Path(satellite).resolve()
        if not sp.is_file():
            raise InputFileError(f"--satellite {satellite}: file does not exist; check the path")
        _check_raster_has_crs(sp, "--satellite", sp)
        sat = SatelliteConfig(image=sp, acquired=None)
    unknown = set(parameters) - {f.name for f in fields(Parameters)}
    if unknown:
        raise ConfigError(f"unknown parameter {sorted(unknown)[0]!r}")
    return SiteConfig(path=None, name=name, crs=_check_crs(crs, Path("<arguments>")),
                      reference_flight=flights[0].id, flights=tuple(flights), satellite=sat,
                      paddocks=None, parameters=Parameters(**parameters), anchor=anchor)
