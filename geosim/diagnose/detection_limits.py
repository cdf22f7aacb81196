"""What the diagnosis cannot test at a given Q: isotropic blurs absorbed into Q.

An isotropic blur under a wide optical PSF changes the in-band transfer almost exactly as
a slightly larger Q (and a broadband gain) would. The transfer fit then cannot tell the
blur from Q: it is not claimed, and the refitted Q includes it. "Not claimed" is then no
evidence that it is absent. For each isotropic blur this module finds, at the delivered
Q, the parameter beyond which the blur's transfer differs from the best wider optical
transfer g · OTF(Q') by more than :data:`DETECTABLE_DIFFERENCE` somewhere in the band
(0–0.5 cycles per 0.5 m pixel): the *detection limit*. A blur on the absorbed side of it
is below what the diagnosis resolves.

The level (1 % of the transfer) was set on the independent benchmark's development half
(``benchmarks/diagnose_independent.py``, seeds 1000–1255): every true detector box the
diagnosis found differed from a wider PSF by ≥ 1.1 %, every one it missed with no other
effect beside it by < 0.9 % (docs/diagnosis.md, round 9).

Pure numerics (no I/O); the blurs' transfers and parameter ranges are the diagnosis's own
effects (:mod:`geosim.diagnose.effects`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from geosim.diagnose.effects import ParamSpec, get_effect
from geosim.physics import otf

__all__ = ["DETECTABLE_DIFFERENCE", "DetectionLimit", "absorbed_difference",
           "absorbed_by", "detection_limit", "detection_limits", "detection_limits_json",
           "limits_markdown", "ISOTROPIC_LIMITS"]

#: largest |transfer − best g · OTF(Q')| over the band (fraction of unit transfer) that the
#: transfer fit does not resolve (set on the development half; see the module docstring)
DETECTABLE_DIFFERENCE = 0.01

#: radial frequencies (cycles per 0.5 m pixel) and directions (degrees from the x axis;
#: the blurs here have square or circular symmetry, so one octant holds every direction)
_F = np.linspace(0.0, 0.5, 201)[1:]
_THETA = np.deg2rad(np.linspace(0.0, 45.0, 7))
_FY = _F[np.newaxis, :] * np.sin(_THETA)[:, np.newaxis]
_FX = _F[np.newaxis, :] * np.cos(_THETA)[:, np.newaxis]
#: least-squares weight ∝ f: the number of 2-D frequency bins at radius f
_W = np.broadcast_to(_F, _FY.shape)


@dataclass(frozen=True)
class _Blur:
    """An isotropic blur: which end of its parameter's physical range is the weaker blur
    (the side that is absorbed), and that side in words. Its parameter, range and transfer
    are the diagnosis's own (:func:`geosim.diagnose.effects.get_effect`)."""

    name: str
    weaker_is_low: bool
    #: the absorbed side in words, ``{v}`` the limit
    absorbed_words: str

    @property
    def spec(self) -> ParamSpec:
        (spec,) = get_effect(self.name).params
        return spec

    def transfer(self, value: float) -> np.ndarray:
        return get_effect(self.name).transfer(_FY, _FX, **{self.spec.name: value})


#: the isotropic blurs the transfer fit claims by name (resampling is found by its
#: aliasing as well, so a transfer limit does not bound it)
ISOTROPIC_LIMITS = (
    _Blur("detector_integration", weaker_is_low=True,
          absorbed_words="a detector box (detector_integration) narrower than {v:.2f} px"),
    _Blur("atmospheric_blur", weaker_is_low=False,
          absorbed_words="an atmospheric blur (atmospheric_blur) with f0 above {v:.2f} "
                         "cycles/px"),
)


@dataclass(frozen=True)
class DetectionLimit:
    """The detection limit of one isotropic blur at one Q.

    Attributes
    ----------
    name, param
        The effect and its parameter (``pitch_px``: detector width in 0.5 m pixels;
        ``f0_cyc_per_px``: 1/e frequency of the atmospheric MTF, cycles per pixel).
    limit
        The parameter at which the blur first differs by :data:`DETECTABLE_DIFFERENCE`
        from a wider optical PSF; None when no value in the search range does (the
        blur is never testable at this Q).
    absorbed_side
        ``"below"`` (a narrower detector) or ``"above"`` (a higher f0): the side of
        ``limit`` on which the blur is absorbed into Q.
    q
        The Q the limit holds for.
    """

    name: str
    param: str
    limit: float | None
    absorbed_side: str
    q: float

    def absorbs(self, value: float) -> bool:
        """Whether a blur with parameter ``value`` is absorbed into Q (not testable)."""
        return _absorbed(self.limit, self.absorbed_side, value)

    def to_json(self) -> dict[str, Any]:
        level = f"{100 * DETECTABLE_DIFFERENCE:g} %"
        if self.limit is None:
            note = (f"At Q {self.q:.2f} no {self.name} in its physical range differs from a "
                    f"slightly wider optical PSF by {level} of the transfer: it would be "
                    "absorbed into Q and is not tested")
        else:
            what = _blur(self.name).absorbed_words.format(v=self.limit)
            note = (f"At Q {self.q:.2f}, {what} differs from a slightly wider optical PSF "
                    f"by less than {level} of the transfer: it would be absorbed into Q (not "
                    "claimed, not excluded)")
        return {"param": self.param, "limit": self.limit, "absorbed_side": self.absorbed_side,
                "q": self.q, "max_difference": DETECTABLE_DIFFERENCE, "note": note}


def _absorbed(limit: float | None, absorbed_side: str, value: float) -> bool:
    if limit is None:
        return True
    return value < limit if absorbed_side == "below" else value > limit


def absorbed_by(limit: dict[str, Any], value: float) -> bool:
    """Whether a blur with parameter ``value`` lies on the absorbed side of a stated limit
    (an entry of ``diagnosis.json``'s ``detection_limits``; a limit of None absorbs all)."""
    return _absorbed(limit["limit"], limit["absorbed_side"], value)


def _best_wider_difference(target: np.ndarray, q: float) -> float:
    """max |target − g · OTF(Q')| over the band for the least-squares best Q' and g."""
    def fit(qp: float) -> tuple[float, np.ndarray]:
        a = otf.optics_otf(_FY, _FX, q=qp)
        g = float(np.sum(_W * target * a) / max(np.sum(_W * a * a), 1e-300))
        r = target - g * a
        return float(np.sum(_W * r * r)), r

    res = minimize_scalar(lambda qp: fit(qp)[0], bounds=(0.5 * q, 4.0 * q),
                          method="bounded", options={"xatol": 1e-5 * q})
    return float(np.max(np.abs(fit(float(res.x))[1])))


def absorbed_difference(q: float, name: str, value: float) -> float:
    """How far an isotropic blur at Q is from the best wider optical PSF.

    Parameters
    ----------
    q
        Q of the optics (cut-off 1/Q cycles per 0.5 m pixel).
    name, value
        The blur (``detector_integration`` or ``atmospheric_blur``) and its parameter.

    Returns
    -------
    float
        The largest |OTF(Q) · blur − g · OTF(Q')| over 0–0.5 cycles per pixel (fraction of
        unit transfer), for the (Q', g) that fits it best (least squares weighted by f).
    """
    blur = _blur(name)
    target = otf.optics_otf(_FY, _FX, q=q) * blur.transfer(value)
    return _best_wider_difference(target, q)


def _blur(name: str) -> _Blur:
    for b in ISOTROPIC_LIMITS:
        if b.name == name:
            return b
    raise ValueError(f"no detection limit for {name!r}; known: "
                     f"{', '.join(b.name for b in ISOTROPIC_LIMITS)}")


def detection_limit(q: float, name: str, *,
                    level: float = DETECTABLE_DIFFERENCE) -> DetectionLimit:
    """The detection limit of one isotropic blur at Q (bisection on its parameter).

    The difference grows monotonically from the weak end of the blur's range to the
    strong end; the limit is where it crosses ``level`` (to 0.5 % of the parameter).
    """
    blur = _blur(name)
    lo, hi = blur.spec.lower, blur.spec.upper
    weak, strong = (lo, hi) if blur.weaker_is_low else (hi, lo)
    side = "below" if blur.weaker_is_low else "above"

    def diff(v: float) -> float:
        return absorbed_difference(q, name, v)

    if diff(strong) < level:
        return DetectionLimit(name, blur.spec.name, None, side, float(q))
    if diff(weak) >= level:
        return DetectionLimit(name, blur.spec.name, float(weak), side, float(q))
    # bisect in log space: both parameters are scale parameters
    a, b = np.log(weak), np.log(strong)
    while abs(b - a) > 0.005:
        m = 0.5 * (a + b)
        if diff(float(np.exp(m))) < level:
            a = m
        else:
            b = m
    return DetectionLimit(name, blur.spec.name, float(np.exp(0.5 * (a + b))), side, float(q))


def detection_limits(q: float) -> list[DetectionLimit]:
    """The detection limits of every isotropic blur at Q (:data:`ISOTROPIC_LIMITS`)."""
    return [detection_limit(q, b.name) for b in ISOTROPIC_LIMITS]


def detection_limits_json(q: float) -> dict[str, dict[str, Any]]:
    """``diagnosis.json``'s ``detection_limits``: {effect: :meth:`DetectionLimit.to_json`}
    at the delivered Q."""
    return {lim.name: lim.to_json() for lim in detection_limits(q)}


def limits_markdown(limits: dict[str, dict[str, Any]],
                    claimed: Iterable[str] = ()) -> list[str]:
    """The report's lines on what the scene cannot test (from ``detection_limits``); a blur
    the diagnosis claimed is left out (the data showed it, whatever its fitted width)."""
    shown = [lim for name, lim in limits.items() if name not in set(claimed)]
    if not shown:
        return []
    return (["\n## What this scene cannot test\n"]
            + [f"- {lim['note']}." for lim in shown]
            + ["\nSuch a blur is not claimed whether or not the satellite has it; the "
               "refitted Q then includes it."])
