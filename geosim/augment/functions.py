"""The paper's twelve pair-augmentation functions (its augmentation table).

Each function is split in two steps so that a pair stays consistent and every
output is reproducible from its record:

``draw(rng, length_scale=...)``
    Draws the random parameters from an explicit generator and returns them as
    a JSON-able dict (the record). Functions whose effect is a random *image*
    (noise, local warp) draw a seed, so the record still determines the output.
``ops(draw, shape)``
    Turns a record into one operation per image of the pair, ``(op_a, op_b)``;
    ``None`` means "leave this image alone". The same record gives the same
    operation to both images except where the function's purpose is to treat
    them differently (alignment; independent local warp; photometric functions
    with ``independent = true``).

Operations are :class:`AffineOp` (a 3 × 3 forward matrix in pixel-edge
coordinates, see :mod:`geosim.augment.geometry`), :class:`WarpOp` (a
displacement field) or :class:`PixelOp` (a photometric kernel). Geometric
operations move the labels with the pixels; photometric ones leave them alone.

Lengths (``sigma_px``, ``max_px``, ``filter_sigma_px``) are in pixels of a
reference resolution and multiplied by ``length_scale`` (reference GSD / image
GSD) when drawn, so one configuration means the same ground distances on UAV
tiles and on 0.5 m tiles; records hold the pixels actually used.
"""

from __future__ import annotations

import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from geosim.augment import geometry as geo
from geosim.augment import photometric as photo
from geosim.augment.warp import DisplacementField, smooth_field
from geosim.errors import ConfigError

__all__ = [
    "FUNCTIONS",
    "AffineOp",
    "Alignment",
    "AugmentFunction",
    "Colour",
    "Hue",
    "LocalWarp",
    "Mirror",
    "Noise",
    "Op",
    "PixelOp",
    "Rotate",
    "Saturation",
    "Scale",
    "Shear",
    "Shift",
    "Value",
    "WarpOp",
    "hsv_op",
]

_SEED_MAX = 2**63 - 1


# ----------------------------------------------------------------------------- operations


@dataclass(frozen=True, eq=False)
class AffineOp:
    """Resample through a forward affine matrix (3 × 3, pixel-edge coordinates)."""

    matrix: np.ndarray


@dataclass(frozen=True, eq=False)
class WarpOp:
    """Resample through a backward displacement field."""

    field: DisplacementField


@dataclass(frozen=True, eq=False)
class PixelOp:
    """A photometric kernel on float32 DN images.

    Attributes
    ----------
    name
        Function name.
    func
        ``func(work, dn_max, rng) -> work``: ``work`` is a float32
        pixel-interleaved ``(rows, cols, bands)`` block of the image (the pipeline
        processes images in row blocks), ``dn_max`` the full-scale value, ``rng``
        the generator made from :attr:`seed` once per image (``None`` if no seed).
    seed
        Seed of the operation's own generator (noise), or ``None``.
    hsv
        ``(hue_deg, saturation_dn, value_dn)`` for HSV shifts, so that consecutive
        HSV shifts of different channels share one colour-space round trip.
    colour_dn
        ``(r, g, b)`` shifts (8-bit DN) of a colour shift, so that the pipeline can
        apply it as a look-up table (the same values as ``func``).
    noise_sigma_dn
        Standard deviation (8-bit DN) of a noise op, so that the pipeline can add the
        noise and round to the image dtype in one pass (the same values as ``func``).
    """

    name: str
    func: Callable[[np.ndarray, float, np.random.Generator | None], np.ndarray]
    seed: int | None = None
    hsv: tuple[float, float, float] | None = None
    colour_dn: tuple[float, float, float] | None = None
    noise_sigma_dn: float | None = None


def hsv_op(name: str, hue_deg: float = 0.0, saturation_dn: float = 0.0,
           value_dn: float = 0.0) -> PixelOp:
    """A :class:`PixelOp` shifting hue (degrees), saturation and value (8-bit units)."""
    return PixelOp(name, lambda w, dn_max, _rng: photo.hsv_shift(
        w, hue_deg=hue_deg, saturation_dn=saturation_dn, value_dn=value_dn, dn_max=dn_max),
        hsv=(hue_deg, saturation_dn, value_dn))


Op = AffineOp | WarpOp | PixelOp


# ----------------------------------------------------------------------------- base class


def _number(fn: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(f"augmentation function {fn!r}: {key} = {value!r} is not a number; "
                          f"give a number")
    v = float(value)
    if not np.isfinite(v):
        raise ConfigError(f"augmentation function {fn!r}: {key} = {value!r} is not finite")
    return v


def _at_least(fn: str, key: str, value: float, low: float) -> None:
    if value < low:
        raise ConfigError(f"augmentation function {fn!r}: {key} = {value} must be >= {low}")


def _probability(fn: str, key: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ConfigError(f"augmentation function {fn!r}: {key} = {value} must be a "
                          "probability in [0, 1]")


class AugmentFunction(ABC):
    """One of the paper's augmentation functions, with its tuning parameters.

    Subclasses are frozen dataclasses whose fields are the parameters (with
    units in their names); build them from a config table with
    :meth:`from_params`.
    """

    name: ClassVar[str]
    geometric: ClassVar[bool]
    #: Fields that are lengths in reference pixels (multiplied by ``length_scale``).
    length_fields: ClassVar[tuple[str, ...]] = ()
    #: Fields whose value is a choice among strings.
    choices: ClassVar[dict[str, tuple[str, ...]]] = {}

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> AugmentFunction:
        """Build from a config table, with errors naming the function and the key."""
        fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        unknown = sorted(set(params) - set(fields))
        if unknown:
            raise ConfigError(f"augmentation function {cls.name!r}: unknown parameter(s) "
                              f"{', '.join(unknown)}; known: {', '.join(fields) or 'none'}")
        kwargs: dict[str, Any] = {}
        for key, value in params.items():
            if key in cls.choices:
                if value not in cls.choices[key]:
                    raise ConfigError(f"augmentation function {cls.name!r}: {key} = {value!r}; "
                                      f"use one of {', '.join(map(repr, cls.choices[key]))}")
                kwargs[key] = value
            elif fields[key].type in ("bool", bool):
                if not isinstance(value, bool):
                    raise ConfigError(f"augmentation function {cls.name!r}: {key} = {value!r} "
                                      "must be true or false")
                kwargs[key] = value
            else:
                kwargs[key] = _number(cls.name, key, value)
        return cls(**kwargs)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:  # noqa: B027 - optional hook
        """Check parameter ranges; raise :class:`ConfigError`."""

    def params(self) -> dict[str, Any]:
        """The configured parameters (JSON-able)."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @abstractmethod
    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        """Draw the random parameters of one application (JSON-able record).

        Parameters
        ----------
        rng
            The only source of randomness.
        length_scale
            Image pixels per reference pixel (reference GSD / image GSD).
        """

    @abstractmethod
    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        """Operations for images a and b of a pair of ``shape`` (rows, cols) from a record."""


def _same(op: Op | None) -> tuple[Op | None, Op | None]:
    return op, op


# ----------------------------------------------------------------------------- geometric


@dataclass(frozen=True)
class Rotate(AugmentFunction):
    """Rotate the pair by an angle drawn uniformly from ``[min_deg, max_deg]``.

    Positive angles turn the content counter-clockwise as displayed, about the
    image centre.
    """

    min_deg: float = -10.0
    max_deg: float = 10.0
    name: ClassVar[str] = "rotate"
    geometric: ClassVar[bool] = True

    def validate(self) -> None:
        if self.min_deg > self.max_deg:
            raise ConfigError(f"augmentation function 'rotate': min_deg = {self.min_deg} > "
                              f"max_deg = {self.max_deg}; swap them")

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        return {"rotation_deg": float(rng.uniform(self.min_deg, self.max_deg))}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["rotation_deg"] == 0:
            return None, None
        return _same(AffineOp(geo.rotation_matrix(draw["rotation_deg"], shape)))


@dataclass(frozen=True)
class Alignment(AugmentFunction):
    """Shift only one image of the pair, to create misalignment.

    ``dx_px`` and ``dy_px`` are drawn from a zero-mean Gaussian of standard
    deviation ``sigma_px``; ``image`` says which image moves (``"random"``: a or
    b with equal chance).
    """

    sigma_px: float = 2.0
    image: str = "random"
    name: ClassVar[str] = "alignment"
    geometric: ClassVar[bool] = True
    length_fields: ClassVar[tuple[str, ...]] = ("sigma_px",)
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"image": ("a", "b", "random")}

    def validate(self) -> None:
        _at_least(self.name, "sigma_px", self.sigma_px, 0.0)

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        which = self.image if self.image != "random" else ("a" if rng.random() < 0.5 else "b")
        s = self.sigma_px * length_scale
        return {"image": which, "dx_px": float(rng.normal(0.0, s)),
                "dy_px": float(rng.normal(0.0, s))}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["dx_px"] == 0 and draw["dy_px"] == 0:
            return None, None
        op = AffineOp(geo.shift_matrix(draw["dx_px"], draw["dy_px"]))
        return (op, None) if draw["image"] == "a" else (None, op)


@dataclass(frozen=True)
class Shift(AugmentFunction):
    """Shift both images together by Gaussian ``dx_px``, ``dy_px`` (std ``sigma_px``)."""

    sigma_px: float = 20.0
    name: ClassVar[str] = "shift"
    geometric: ClassVar[bool] = True
    length_fields: ClassVar[tuple[str, ...]] = ("sigma_px",)

    def validate(self) -> None:
        _at_least(self.name, "sigma_px", self.sigma_px, 0.0)

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        s = self.sigma_px * length_scale
        return {"dx_px": float(rng.normal(0.0, s)), "dy_px": float(rng.normal(0.0, s))}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["dx_px"] == 0 and draw["dy_px"] == 0:
            return None, None
        return _same(AffineOp(geo.shift_matrix(draw["dx_px"], draw["dy_px"])))


@dataclass(frozen=True)
class Mirror(AugmentFunction):
    """Flip the pair up/down and left/right, each with its own Bernoulli probability."""

    p_ud: float = 0.5
    p_lr: float = 0.5
    name: ClassVar[str] = "mirror"
    geometric: ClassVar[bool] = True

    def validate(self) -> None:
        _probability(self.name, "p_ud", self.p_ud)
        _probability(self.name, "p_lr", self.p_lr)

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        return {"flip_ud": bool(rng.random() < self.p_ud),
                "flip_lr": bool(rng.random() < self.p_lr)}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if not (draw["flip_ud"] or draw["flip_lr"]):
            return None, None
        return _same(AffineOp(geo.mirror_matrix(draw["flip_ud"], draw["flip_lr"], shape)))


#: Smallest scale factor applied (a Gaussian ratio below -0.9 is limited to this).
MIN_SCALE_FACTOR = 0.1


@dataclass(frozen=True)
class Scale(AugmentFunction):
    """Scale the pair about its centre by ``factor = 1 + ratio``, ratio ~ N(0, sigma).

    The factor is limited to at least :data:`MIN_SCALE_FACTOR` (only reachable
    with unusually large ``sigma``); the record keeps both ``ratio`` and ``factor``.
    """

    sigma: float = 0.1
    name: ClassVar[str] = "scale"
    geometric: ClassVar[bool] = True

    def validate(self) -> None:
        _at_least(self.name, "sigma", self.sigma, 0.0)

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        ratio = float(rng.normal(0.0, self.sigma))
        return {"ratio": ratio, "factor": max(MIN_SCALE_FACTOR, 1.0 + ratio)}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["factor"] == 1.0:
            return None, None
        return _same(AffineOp(geo.scale_matrix(draw["factor"], shape)))


@dataclass(frozen=True)
class Shear(AugmentFunction):
    """Shear the pair about its centre: ``x' = x + shear_x·y``, ``y' = y + shear_y·x``.

    ``shear_x`` ~ N(0, sigma_x) and ``shear_y`` ~ N(0, sigma_y) are ratios
    (the paper's single shear is ``sigma_x``; ``sigma_y`` defaults to 0).
    """

    sigma_x: float = 0.05
    sigma_y: float = 0.0
    name: ClassVar[str] = "shear"
    geometric: ClassVar[bool] = True

    def validate(self) -> None:
        _at_least(self.name, "sigma_x", self.sigma_x, 0.0)
        _at_least(self.name, "sigma_y", self.sigma_y, 0.0)

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        return {"shear_x": float(rng.normal(0.0, self.sigma_x)),
                "shear_y": float(rng.normal(0.0, self.sigma_y))}

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["shear_x"] == 0 and draw["shear_y"] == 0:
            return None, None
        return _same(AffineOp(geo.shear_matrix(draw["shear_x"], draw["shear_y"], shape)))


@dataclass(frozen=True)
class LocalWarp(AugmentFunction):
    """Smooth random local warp (stitching artefacts), see :mod:`geosim.augment.warp`.

    ``max_px`` is the largest displacement in the field ("max surface height"),
    ``filter_sigma_px`` the width of the low-pass filter; ``mode`` warps both
    images with the same field (``"together"``) or each with its own
    (``"independent"``).
    """

    max_px: float = 10.0
    filter_sigma_px: float = 100.0
    mode: str = "together"
    name: ClassVar[str] = "local_warp"
    geometric: ClassVar[bool] = True
    length_fields: ClassVar[tuple[str, ...]] = ("max_px", "filter_sigma_px")
    choices: ClassVar[dict[str, tuple[str, ...]]] = {"mode": ("together", "independent")}

    def validate(self) -> None:
        _at_least(self.name, "max_px", self.max_px, 0.0)
        if self.filter_sigma_px <= 0:
            raise ConfigError(f"augmentation function 'local_warp': filter_sigma_px = "
                              f"{self.filter_sigma_px} must be > 0")
        if self.max_px > self.filter_sigma_px:
            raise ConfigError(f"augmentation function 'local_warp': max_px = {self.max_px} "
                              f"> filter_sigma_px = {self.filter_sigma_px} would fold the image "
                              "over itself; keep max_px below about filter_sigma_px / 2")

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        rec: dict[str, Any] = {"max_px": self.max_px * length_scale,
                               "filter_sigma_px": self.filter_sigma_px * length_scale,
                               "mode": self.mode}
        if self.mode == "together":
            rec["seed"] = int(rng.integers(0, _SEED_MAX))
        else:
            rec["seed_a"] = int(rng.integers(0, _SEED_MAX))
            rec["seed_b"] = int(rng.integers(0, _SEED_MAX))
        return rec

    def field(self, draw: Mapping[str, Any], shape: tuple[int, int], seed: int
              ) -> DisplacementField:
        """The displacement field of a record for an image of ``shape`` (rows, cols)."""
        return smooth_field(shape, max_px=draw["max_px"], filter_sigma_px=draw["filter_sigma_px"],
                            rng=np.random.default_rng(seed))

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if draw["max_px"] == 0:
            return None, None
        if draw["mode"] == "together":
            return _same(WarpOp(self.field(draw, shape, draw["seed"])))
        return (WarpOp(self.field(draw, shape, draw["seed_a"])),
                WarpOp(self.field(draw, shape, draw["seed_b"])))


# ----------------------------------------------------------------------------- photometric


class _Photometric(AugmentFunction):
    """Shared logic: one record for the pair, or one per image when ``independent``."""

    geometric: ClassVar[bool] = False
    independent: bool

    @abstractmethod
    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]: ...

    @abstractmethod
    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None: ...

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0) -> dict[str, Any]:
        if self.independent:
            return {"a": self._draw_one(rng), "b": self._draw_one(rng)}
        return self._draw_one(rng)

    def ops(self, draw: Mapping[str, Any], shape: tuple[int, int]
            ) -> tuple[Op | None, Op | None]:
        if "a" in draw:
            return self._op(draw["a"]), self._op(draw["b"])
        return _same(self._op(draw))


def _clipped_normal(rng: np.random.Generator, sigma: float, limit: float) -> float:
    return float(np.clip(rng.normal(0.0, sigma), -limit, limit))


@dataclass(frozen=True)
class Colour(_Photometric):
    """Shift each of R, G, B by its own Gaussian amount, 8-bit DN in ``[-255, 255]``."""

    sigma_dn: float = 10.0
    independent: bool = False
    name: ClassVar[str] = "colour"

    def validate(self) -> None:
        _at_least(self.name, "sigma_dn", self.sigma_dn, 0.0)

    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]:
        return {f"shift_{c}_dn": _clipped_normal(rng, self.sigma_dn, 255.0) for c in "rgb"}

    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None:
        shifts = np.array([rec[f"shift_{c}_dn"] for c in "rgb"])
        if not shifts.any():
            return None
        return PixelOp(self.name,
                       lambda w, dn_max, _rng: photo.colour_shift(w, shifts, dn_max=dn_max),
                       colour_dn=(float(shifts[0]), float(shifts[1]), float(shifts[2])))


@dataclass(frozen=True)
class Hue(_Photometric):
    """Shift hue (HSV) by a Gaussian angle, degrees in ``[-180, 180]``, wrapped cyclically."""

    sigma_deg: float = 5.0
    independent: bool = False
    name: ClassVar[str] = "hue"

    def validate(self) -> None:
        _at_least(self.name, "sigma_deg", self.sigma_deg, 0.0)

    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"hue_deg": _clipped_normal(rng, self.sigma_deg, 180.0)}

    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None:
        h = rec["hue_deg"]
        if h == 0:
            return None
        return hsv_op(self.name, hue_deg=h)


@dataclass(frozen=True)
class Saturation(_Photometric):
    """Shift saturation (HSV) by a Gaussian amount, 8-bit units in ``[-255, 255]``."""

    sigma_dn: float = 10.0
    independent: bool = False
    name: ClassVar[str] = "saturation"

    def validate(self) -> None:
        _at_least(self.name, "sigma_dn", self.sigma_dn, 0.0)

    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"saturation_dn": _clipped_normal(rng, self.sigma_dn, 255.0)}

    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None:
        s = rec["saturation_dn"]
        if s == 0:
            return None
        return hsv_op(self.name, saturation_dn=s)


@dataclass(frozen=True)
class Value(_Photometric):
    """Shift value (HSV) by a Gaussian amount, 8-bit units in ``[-255, 255]``."""

    sigma_dn: float = 10.0
    independent: bool = False
    name: ClassVar[str] = "value"

    def validate(self) -> None:
        _at_least(self.name, "sigma_dn", self.sigma_dn, 0.0)

    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"value_dn": _clipped_normal(rng, self.sigma_dn, 255.0)}

    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None:
        v = rec["value_dn"]
        if v == 0:
            return None
        return hsv_op(self.name, value_dn=v)


@dataclass(frozen=True)
class Noise(_Photometric):
    """Add Gaussian noise of std ``sigma_dn`` (8-bit DN), independent per pixel and band.

    With ``independent = false`` (default) both images receive the same noise
    realisation (the pair stays consistent); ``true`` gives each its own.
    """

    sigma_dn: float = 3.0
    independent: bool = False
    name: ClassVar[str] = "noise"

    def validate(self) -> None:
        _at_least(self.name, "sigma_dn", self.sigma_dn, 0.0)

    def _draw_one(self, rng: np.random.Generator) -> dict[str, Any]:
        return {"sigma_dn": self.sigma_dn, "seed": int(rng.integers(0, _SEED_MAX))}

    def _op(self, rec: Mapping[str, Any]) -> PixelOp | None:
        sigma, seed = rec["sigma_dn"], rec["seed"]
        if sigma == 0:
            return None
        return PixelOp(self.name, lambda w, dn_max, rng: photo.add_noise(
            w, sigma_dn=sigma, rng=rng, dn_max=dn_max), seed=int(seed),
            noise_sigma_dn=float(sigma))


#: The functions by config name, in the paper's table order.
FUNCTIONS: dict[str, type[AugmentFunction]] = {
    cls.name: cls for cls in (Rotate, Alignment, Shift, Colour, Hue, Saturation, Value, Mirror,
                              Scale, Noise, Shear, LocalWarp)
}
