"""What the diagnosis cannot test at a given Q: blurs absorbed into Q.

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

**Measured on the scene** (round 11). That level is a property of the optics alone; whether
the scene resolves the difference depends on how well its transfer is measured (noise,
JPEG and moved objects lower the coherence) and on how much misfit other physics leaves
(the claim rule asks a relative gain of the χ²). So where the measured transfer is given
(:class:`MeasuredTransfer`), the blur's difference from the best wider optics is also
weighed by that measurement: the χ² it would add to the delivered model
(:func:`predicted_delta_chi2`, the transfer's own per-frequency variances) must reach what
the claim rule needs (:func:`needed_delta_chi2`: the held-out gain ``MIN_CV_GAIN`` of the
delivered χ² and ``MIN_DELTA_BIC``), times :data:`MEASURED_MARGIN`. The stated limit is the
stricter of the two.

**Anisotropic blurs** (round 15). A short motion smear or a weak off-nadir blur under a
wide optical PSF is absorbed the same way: its mean roll-off into Q, its anisotropy too
small for the measured transfer to resolve. Their limits are found alike, with the
evidence of the most favourable direction (:func:`blur_evidence`: the largest predicted χ²
gain over :data:`DIRECTIONS_DEG`) and the claim rule's need for a two-parameter effect
(length or σ, and direction), so a stated limit holds whatever the blur's direction ("a
smear shorter than L px is not testable in any direction"). Their margin
(:data:`ANISOTROPIC_MARGIN`) was set on the development half like the isotropic one. Where
one of them is claimed, the other's limit (as an additional blur beside it) is not shown in
the report: the data showed the family (:func:`limits_markdown`).

Pure numerics (no I/O); the blurs' transfers and parameter ranges are the diagnosis's own
effects (:mod:`geosim.diagnose.effects`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize_scalar

from geosim.diagnose.effects import ParamSpec, get_effect
from geosim.diagnose.fit import HANN_CORRELATION, SpectralData, model_transfer
from geosim.diagnose.resampling_limit import ABSORBED_WORDS as RESAMPLING_WORDS
from geosim.diagnose.resampling_limit import PITCHES as RESAMPLING_PITCHES
from geosim.diagnose.select import MIN_CV_GAIN, MIN_DELTA_BIC
from geosim.physics import otf

__all__ = ["DETECTABLE_DIFFERENCE", "DetectionLimit", "absorbed_difference",
           "absorbed_by", "detection_limit", "detection_limits", "detection_limits_json",
           "limits_markdown", "ISOTROPIC_LIMITS", "ANISOTROPIC_LIMITS", "MEASURED_MARGIN",
           "ANISOTROPIC_MARGIN", "DIRECTIONS_DEG", "MeasuredTransfer", "predicted_delta_chi2",
           "blur_evidence", "needed_delta_chi2", "measured_limit", "combine_limits",
           "family_claimed"]

#: largest |transfer − best g · OTF(Q')| over the band (fraction of unit transfer) that the
#: transfer fit does not resolve (set on the development half; see the module docstring)
DETECTABLE_DIFFERENCE = 0.01

#: how far the predicted χ² gain of a blur must exceed what the claim rule needs for the
#: blur to be called testable on the measured transfer. Set on the independent benchmark's
#: development half (seeds 1000-1351; docs/diagnosis.md, round 11) as the smallest of
#: 1, 1.5, 2, 3, 4, 6, 8 at which ≥ 90 % of the true isotropic blurs stated testable were
#: found (1: 0.67, 3: 0.86, 4: 0.92). The prediction assumes the other physics known and
#: scores in-sample; the rule's held-out folds and the joint fit ask more.
MEASURED_MARGIN = 4.0
#: the margin for the anisotropic blurs, set on the development half (seeds 1000-1479;
#: docs/diagnosis.md, round 15) by the same rule: the smallest of 1, 1.5, 2, 3, 4, 6, 8 at
#: which ≥ 90 % of the true anisotropic blurs stated testable were found (1: 0.89, 1.5:
#: 0.92, 4: 0.985; swaps, the family found under the other name, left out: a naming error,
#: not an untestable blur); at 1.5 no anisotropic blur that was claimed lies below its
#: limit (at 4: four)
ANISOTROPIC_MARGIN = 1.5
#: parameter values per blur at which the predicted χ² gain is reported
N_CURVE = 12
#: directions of an anisotropic blur (degrees clockwise from grid north) over which its
#: evidence is weighed (the most favourable one counts)
DIRECTIONS_DEG = (0.0, 30.0, 60.0, 90.0, 120.0, 150.0)

#: radial frequencies (cycles per 0.5 m pixel)
_F = np.linspace(0.0, 0.5, 201)[1:]


def _polar_grid(max_deg: float, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fy, fx, weight) on rays at ``n`` directions from 0 to ``max_deg`` degrees from the
    x axis; the least-squares weight ∝ f (the number of 2-D frequency bins at radius f)."""
    theta = np.deg2rad(np.linspace(0.0, max_deg, n))
    fy = _F[np.newaxis, :] * np.sin(theta)[:, np.newaxis]
    fx = _F[np.newaxis, :] * np.cos(theta)[:, np.newaxis]
    return fy, fx, np.broadcast_to(_F, fy.shape)


#: the isotropic blurs have square or circular symmetry: one octant holds every direction
_OCTANT = _polar_grid(45.0, 7)
#: an anisotropic blur at direction 0 against every frequency direction (a half plane)
_HALF_PLANE = _polar_grid(180.0, 25)


@dataclass(frozen=True)
class _Blur:
    """A blur with a detection limit: which end of its size parameter's physical range is
    the weaker blur (the side that is absorbed), and that side in words. Its parameters,
    range and transfer are the diagnosis's own (:func:`geosim.diagnose.effects.get_effect`);
    its size parameter is the effect's first."""

    name: str
    weaker_is_low: bool
    #: the absorbed side in words, ``{v}`` the limit
    absorbed_words: str
    #: an anisotropic blur's direction parameter (None: isotropic)
    direction: str | None = None
    #: how far the predicted evidence must exceed the claim rule's need
    margin: float = MEASURED_MARGIN

    @property
    def spec(self) -> ParamSpec:
        return get_effect(self.name).params[0]

    @property
    def n_params(self) -> int:
        return len(get_effect(self.name).params)

    def params(self, value: float, direction_deg: float = 0.0) -> dict[str, float]:
        """The effect's parameters at size ``value`` (and direction, if it has one)."""
        p = {self.spec.name: float(value)}
        if self.direction is not None:
            p[self.direction] = float(direction_deg)
        return p

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frequencies on which its difference from the optics is weighed."""
        return _OCTANT if self.direction is None else _HALF_PLANE

    def transfer(self, value: float) -> np.ndarray:
        fy, fx, _ = self.grid
        return get_effect(self.name).transfer(fy, fx, **self.params(value))


#: the isotropic blurs the transfer fit claims by name (resampling is found by its
#: aliasing as well, so a transfer limit does not bound it)
ISOTROPIC_LIMITS = (
    _Blur("detector_integration", weaker_is_low=True,
          absorbed_words="a detector box (detector_integration) narrower than {v:.2f} px"),
    _Blur("atmospheric_blur", weaker_is_low=False,
          absorbed_words="an atmospheric blur (atmospheric_blur) with f0 above {v:.2f} "
                         "cycles/px"),
)
#: the anisotropic blurs (one family: where one is claimed, the report shows neither's line)
ANISOTROPIC_LIMITS = (
    _Blur("motion_smear", weaker_is_low=True, direction="direction_deg",
          margin=ANISOTROPIC_MARGIN,
          absorbed_words="a motion smear (motion_smear) shorter than {v:.2f} px, in any "
                         "direction,"),
    _Blur("off_nadir_anisotropy", weaker_is_low=True, direction="azimuth_deg",
          margin=ANISOTROPIC_MARGIN,
          absorbed_words="an off-nadir blur (off_nadir_anisotropy) with σ below {v:.2f} px, "
                         "in any direction,"),
)


@dataclass(frozen=True)
class MeasuredTransfer:
    """The scene's measured transfer and the delivered model's fit to it: what a
    detection limit measured on the scene is weighed against.

    Attributes
    ----------
    data
        The measured transfer (all Welch blocks used by the fit), with its per-frequency
        variances.
    q, gain
        The delivered Q and the broadband gain that fits it best.
    effects
        The delivered blur effects ({name: {param: value}}).
    chi2
        χ² of that model on ``data``.
    """

    data: SpectralData
    q: float
    gain: float
    effects: dict[str, dict[str, float]]
    chi2: float

    @classmethod
    def of(cls, data: SpectralData, q: float,
           effects: dict[str, dict[str, float]]) -> MeasuredTransfer:
        """The delivered model (Q, blur effects) on ``data``, its gain fitted."""
        gain, chi2 = _best_gain(data, model_transfer(data, q=q, gain=1.0, effects=effects),
                                data.t_real)
        return cls(data, float(q), gain, dict(effects), chi2)


def _weighted_gain(w: np.ndarray, unit: np.ndarray, target: np.ndarray
                   ) -> tuple[float, np.ndarray]:
    """The real g minimising Σ w |target − g · unit|², and the residual target − g · unit
    (real or complex transfers)."""
    g = float(np.real(np.sum(w * target * np.conj(unit)))
              / max(float(np.real(np.sum(w * unit * np.conj(unit)))), 1e-300))
    return g, target - g * unit


def _best_gain(data: SpectralData, unit: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """(g, χ²) of ``target`` against g · ``unit`` with the transfer's variances (g real)."""
    w = 1.0 / data.var
    g, r = _weighted_gain(w, unit, target)
    return g, float(np.sum(w * np.abs(r) ** 2))


def predicted_delta_chi2(m: MeasuredTransfer, name: str, value: float,
                         direction_deg: float = 0.0) -> float:
    """The χ² evidence the scene's measured transfer would hold for a blur.

    Suppose the satellite had the blur ``name`` with parameter ``value``: the scene would
    then look like the delivered model with a sharper optics, ``g_t · G(Q_t) · H(value)``
    (other delivered blurs kept), the Q_t and g_t that match the delivered model best. The
    model without the blur can only move Q (within the fit's Q grid) and the gain; the χ²
    of its best fit to that transfer, with the measured per-frequency variances, is the
    evidence the data would hold for the blur.

    Parameters
    ----------
    m
        The measured transfer and the delivered fit.
    name, value
        The blur (``detector_integration``: pitch, px; ``atmospheric_blur``: f0,
        cycles/px; ``motion_smear``: length, px; ``off_nadir_anisotropy``: σ, px) and its
        size parameter.
    direction_deg
        An anisotropic blur's direction (degrees clockwise from grid north).
    """
    blur = _blur(name)
    other = {k: v for k, v in m.effects.items() if k != name}
    delivered = model_transfer(m.data, q=m.q, gain=m.gain, effects=other)
    with_blur = {**other, name: blur.params(value, direction_deg)}
    bounds = (float(np.log(m.data.q_grid[0])), float(np.log(m.data.q_grid[-1])))

    def best(target: np.ndarray, effects: dict[str, dict[str, float]]
             ) -> tuple[float, np.ndarray]:
        def unit(log_q: float) -> np.ndarray:
            return model_transfer(m.data, q=float(np.exp(log_q)), gain=1.0, effects=effects)

        res = minimize_scalar(lambda lq: _best_gain(m.data, unit(lq), target)[1],
                              bounds=bounds, method="bounded", options={"xatol": 1e-4})
        u = unit(float(res.x))
        g, chi2 = _best_gain(m.data, u, target)
        return chi2, g * u

    _, scene = best(delivered, with_blur)       # the scene as it would be with the blur
    return best(scene, other)[0]


def blur_evidence(m: MeasuredTransfer, name: str, value: float) -> float:
    """:func:`predicted_delta_chi2` of a blur; of an anisotropic one, in its most
    favourable direction of :data:`DIRECTIONS_DEG` (the evidence a limit that holds in
    any direction is weighed by)."""
    blur = _blur(name)
    if blur.direction is None:
        return predicted_delta_chi2(m, name, value)
    return max(predicted_delta_chi2(m, name, value, d) for d in DIRECTIONS_DEG)


def needed_delta_chi2(m: MeasuredTransfer, margin: float = MEASURED_MARGIN,
                      n_params: int = 1) -> float:
    """The χ² gain the claim rule needs for one more blur of ``n_params`` parameters,
    times ``margin``.

    The held-out gain ``MIN_CV_GAIN`` is relative to the χ² of the model without the blur
    (the delivered χ² plus the blur's own Δχ²), hence
    ``Δχ² ≥ MIN_CV_GAIN / (1 − MIN_CV_GAIN) · χ²``; ``MIN_DELTA_BIC`` is
    ``Δχ² / (scale · HANN_CORRELATION) − n_params · ln n_eff`` with the fit's variance
    scale (:func:`geosim.diagnose.select.delta_bic`)."""
    n_values = 2 * m.data.t_real.size
    scale = max(1.0, m.chi2 / max(n_values - 3, 1))
    by_gain = MIN_CV_GAIN / (1.0 - MIN_CV_GAIN) * m.chi2
    by_bic = (MIN_DELTA_BIC + n_params * np.log(m.data.n_eff)) * scale * HANN_CORRELATION
    return float(margin * max(by_gain, by_bic))


def measured_limit(m: MeasuredTransfer, name: str, *, margin: float | None = None
                   ) -> tuple[float | None, float, tuple[tuple[float, float], ...]]:
    """The detection limit of one blur on the measured transfer (bisection, 0.5 % of the
    parameter) with the χ² gain needed and the predicted gain at :data:`N_CURVE`
    parameters (log-spaced over the blur's range).

    ``margin``: default the blur's own (:data:`MEASURED_MARGIN`, :data:`ANISOTROPIC_MARGIN`).

    Returns
    -------
    limit, needed, curve
        The parameter at which :func:`blur_evidence` first reaches
        :func:`needed_delta_chi2` (None: nowhere in the range); the gain needed; the
        (parameter, predicted gain) pairs.
    """
    blur = _blur(name)
    need = needed_delta_chi2(m, blur.margin if margin is None else margin, blur.n_params)
    weak, strong = _ends(blur)
    curve = tuple((float(v), blur_evidence(m, name, float(v)))
                  for v in np.exp(np.linspace(np.log(weak), np.log(strong), N_CURVE)))
    return _bisect(lambda v: blur_evidence(m, name, v), need, weak, strong), need, curve


def _ends(blur: _Blur) -> tuple[float, float]:
    """(weakest, strongest) parameter of the blur's physical range."""
    lo, hi = blur.spec.lower, blur.spec.upper
    return (lo, hi) if blur.weaker_is_low else (hi, lo)


def _bisect(diff: Callable[[float], float], level: float, weak: float, strong: float
            ) -> float | None:
    """Where ``diff`` (growing from ``weak`` to ``strong``) crosses ``level``: bisection in
    log space (both parameters are scale parameters) to 0.5 %; None if it never does."""
    if diff(strong) < level:
        return None
    if diff(weak) >= level:
        return float(weak)
    a, b = np.log(weak), np.log(strong)
    while abs(b - a) > 0.005:
        mid = 0.5 * (a + b)
        if diff(float(np.exp(mid))) < level:
            a = mid
        else:
            b = mid
    return float(np.exp(0.5 * (a + b)))


@dataclass(frozen=True)
class DetectionLimit:
    """The detection limit of one blur at one Q.

    Attributes
    ----------
    name, param
        The effect and its size parameter (``pitch_px``: detector width in 0.5 m pixels;
        ``f0_cyc_per_px``: 1/e frequency of the atmospheric MTF, cycles per pixel;
        ``length_px``: smear length, 0.5 m pixels; ``sigma_px``: off-nadir Gaussian σ,
        0.5 m pixels; an anisotropic blur's limit holds in any direction).
    limit
        The stated limit: the stricter of ``transfer_limit`` and ``measured_limit``; None
        when no value in the search range is testable.
    absorbed_side
        ``"below"`` (a narrower detector, a shorter smear, a smaller σ) or ``"above"`` (a
        higher f0): the side of ``limit`` on which the blur is absorbed into Q.
    q
        The Q the limit holds for.
    transfer_limit
        The parameter at which the blur first differs by :data:`DETECTABLE_DIFFERENCE`
        from a wider optical PSF (the optics alone).
    measured
        Whether the scene's measured transfer was weighed (the fields below are set).
    measured_limit
        The parameter at which the blur's predicted χ² gain on the measured transfer
        reaches ``needed_delta_chi2``.
    needed_delta_chi2
        What the claim rule needs, times :data:`MEASURED_MARGIN`.
    curve
        (parameter, predicted χ² gain) at :data:`N_CURVE` parameters over the range.
    """

    name: str
    param: str
    limit: float | None
    absorbed_side: str
    q: float
    transfer_limit: float | None = None
    measured: bool = False
    measured_limit: float | None = None
    needed_delta_chi2: float = float("nan")
    curve: tuple[tuple[float, float], ...] = ()

    def absorbs(self, value: float) -> bool:
        """Whether a blur with parameter ``value`` is absorbed into Q (not testable)."""
        return _absorbed(self.limit, self.absorbed_side, value)

    def to_json(self) -> dict[str, Any]:
        level = f"{100 * DETECTABLE_DIFFERENCE:g} %"
        # which limit set the stated one (no limit at all: whichever found none)
        by_data = self.measured and (self.measured_limit is None or (
            self.transfer_limit is not None and self.limit == self.measured_limit))
        why = ("the scene's measured transfer does not resolve it from a slightly wider "
               "optical PSF (the χ² it would add is below what a claim needs)" if by_data
               else f"it differs from a slightly wider optical PSF by less than {level} of "
                    "the transfer")
        if self.limit is None:
            note = (f"At Q {self.q:.2f} no {self.name} in its physical range is testable: "
                    f"{why}; it would be absorbed into Q")
        else:
            what = _blur(self.name).absorbed_words.format(v=self.limit)
            note = (f"At Q {self.q:.2f}, {what} is not testable: {why}; it would be absorbed "
                    "into Q (not claimed, not excluded)")
        out: dict[str, Any] = {"param": self.param, "limit": self.limit,
                               "absorbed_side": self.absorbed_side, "q": self.q,
                               "max_difference": DETECTABLE_DIFFERENCE,
                               "transfer_limit": self.transfer_limit,
                               "basis": "measured_transfer" if by_data else "transfer_difference",
                               "note": note}
        if self.measured:
            out.update(measured_limit=self.measured_limit,
                       needed_delta_chi2=self.needed_delta_chi2,
                       predicted_delta_chi2=[list(c) for c in self.curve])
        return out


def _absorbed(limit: float | None, absorbed_side: str, value: float) -> bool:
    if limit is None:
        return True
    return value < limit if absorbed_side == "below" else value > limit


def absorbed_by(limit: dict[str, Any], value: float) -> bool:
    """Whether a blur with parameter ``value`` lies on the absorbed side of a stated limit
    (an entry of ``diagnosis.json``'s ``detection_limits``; a limit of None absorbs all)."""
    return _absorbed(limit["limit"], limit["absorbed_side"], value)


def _best_wider_difference(target: np.ndarray, q: float,
                           grid: tuple[np.ndarray, np.ndarray, np.ndarray]) -> float:
    """max |target − g · OTF(Q')| over the band (``grid``: fy, fx, weight) for the
    least-squares best Q' and g."""
    fy, fx, w = grid

    def fit(qp: float) -> tuple[float, np.ndarray]:
        _, r = _weighted_gain(w, otf.optics_otf(fy, fx, q=qp), target)
        return float(np.sum(w * r * r)), r

    res = minimize_scalar(lambda qp: fit(qp)[0], bounds=(0.5 * q, 4.0 * q),
                          method="bounded", options={"xatol": 1e-5 * q})
    return float(np.max(np.abs(fit(float(res.x))[1])))


def absorbed_difference(q: float, name: str, value: float) -> float:
    """How far a blur at Q is from the best wider optical PSF.

    Parameters
    ----------
    q
        Q of the optics (cut-off 1/Q cycles per 0.5 m pixel).
    name, value
        The blur (one of :data:`ISOTROPIC_LIMITS` or :data:`ANISOTROPIC_LIMITS`) and its
        size parameter.

    Returns
    -------
    float
        The largest |OTF(Q) · blur − g · OTF(Q')| over 0–0.5 cycles per pixel (fraction of
        unit transfer; an anisotropic blur: over every frequency direction), for the
        (Q', g) that fits it best (least squares weighted by f).
    """
    blur = _blur(name)
    fy, fx, _ = blur.grid
    target = otf.optics_otf(fy, fx, q=q) * blur.transfer(value)
    return _best_wider_difference(target, q, blur.grid)


_LIMITED = ISOTROPIC_LIMITS + ANISOTROPIC_LIMITS


def _blur(name: str) -> _Blur:
    for b in _LIMITED:
        if b.name == name:
            return b
    raise ValueError(f"no detection limit for {name!r}; known: "
                     f"{', '.join(b.name for b in _LIMITED)}")


def detection_limit(q: float, name: str, *, level: float = DETECTABLE_DIFFERENCE,
                    measured: MeasuredTransfer | None = None) -> DetectionLimit:
    """The detection limit of one blur at Q (bisection on its size parameter).

    The difference grows monotonically from the weak end of the blur's range to the
    strong end; the transfer limit is where it crosses ``level`` (to 0.5 % of the
    parameter). With ``measured`` (at the same Q) the limit measured on the scene
    (:func:`measured_limit`) is found too and the stricter of the two is stated.
    """
    blur = _blur(name)
    weak, strong = _ends(blur)
    side = "below" if blur.weaker_is_low else "above"
    transfer = _bisect(lambda v: absorbed_difference(q, name, v), level, weak, strong)
    if measured is None:
        return DetectionLimit(name, blur.spec.name, transfer, side, float(q),
                              transfer_limit=transfer)
    on_data, need, curve = measured_limit(measured, name)
    if transfer is None or on_data is None:
        stated = None
    else:
        stated = max(transfer, on_data) if side == "below" else min(transfer, on_data)
    return DetectionLimit(name, blur.spec.name, stated, side, float(q), transfer_limit=transfer,
                          measured=True, measured_limit=on_data, needed_delta_chi2=need,
                          curve=curve)


def detection_limits(q: float, measured: MeasuredTransfer | None = None
                     ) -> list[DetectionLimit]:
    """The detection limits of every blur at Q (:data:`ISOTROPIC_LIMITS`,
    :data:`ANISOTROPIC_LIMITS`), on the scene's measured transfer too where it is given."""
    return [detection_limit(q, b.name, measured=measured) for b in _LIMITED]


def detection_limits_json(q: float, measured: MeasuredTransfer | None = None
                          ) -> dict[str, dict[str, Any]]:
    """``diagnosis.json``'s ``detection_limits``: {effect: :meth:`DetectionLimit.to_json`}
    at the delivered Q (and on the scene's measured transfer where it is given)."""
    return {lim.name: lim.to_json() for lim in detection_limits(q, measured)}


def combine_limits(per_flight: list[dict[str, dict[str, Any]]], need: int, q: float
                   ) -> dict[str, dict[str, Any]]:
    """The detection limits of a majority verdict over flights.

    An effect is claimed when ``need`` flights claim it, so it is testable in the
    combination where it is testable in ``need`` flights: the limit is the ``need``-th most
    sensitive of the flights' stated limits (None, never testable, the least sensitive).
    Flights without a blur's limit count as stating its transfer limit at ``q`` (the
    median refitted Q); resampling (its limit is measured on each scene's spectrum) is
    combined where some flight states it, the others counting as never testable."""
    at_q = detection_limits_json(q)
    out: dict[str, dict[str, Any]] = {}
    for b in _LIMITED:
        stated = [(d.get(b.name) or at_q[b.name])["limit"] for d in per_flight] or \
                 [at_q[b.name]["limit"]]
        limit = _majority(stated, need, most_sensitive_low=b.weaker_is_low)
        what = (b.absorbed_words.format(v=limit) if limit is not None
                else f"any {b.name} in its physical range")
        out[b.name] = _combined(at_q[b.name], stated, limit, need, q, what,
                                "it would be absorbed into Q")
    resampling = [d.get("resampling") for d in per_flight]
    first = next((r for r in resampling if r), None)
    if first is not None:
        stated = [r["limit"] if r else None for r in resampling]
        limit = _majority(stated, need, most_sensitive_low=True)
        what = (RESAMPLING_WORDS.format(v=limit) if limit is not None
                else "any resampling (resampling)")
        out["resampling"] = _combined(first, stated, limit, need, q, what,
                                      "below the range the diagnosis scans"
                                      if limit == RESAMPLING_PITCHES[0]
                                      else "its aliasing would not be resolved")
    return out


def _majority(stated: list[float | None], need: int, *, most_sensitive_low: bool
              ) -> float | None:
    """The ``need``-th most sensitive of the flights' limits (None: never testable)."""
    known = sorted((v for v in stated if v is not None), reverse=not most_sensitive_low)
    ordered = known + [None] * (len(stated) - len(known))
    return ordered[min(need, len(ordered)) - 1]


def _combined(template: dict[str, Any], stated: list[float | None], limit: float | None,
              need: int, q: float, what: str, consequence: str) -> dict[str, Any]:
    """A combined limit entry: ``template``'s fields with the majority's limit and note."""
    entry = dict(template)
    entry.update(limit=limit, q=q, basis="majority_of_flights", limit_by_flight=stated,
                 note=(f"At the median Q {q:.2f}, {what} is testable in fewer than {need} "
                       f"of {len(stated)} flights, the majority a claim needs: "
                       f"{consequence} (not claimed, not excluded)"))
    return entry


def family_claimed(name: str, claimed: Iterable[str]) -> bool:
    """Whether another anisotropic blur than ``name`` was claimed where ``name`` is one:
    the data then showed the family, and ``name``'s limit (as an additional blur beside
    the claimed one) does not say that the anisotropy was untestable."""
    family = {b.name for b in ANISOTROPIC_LIMITS}
    return name in family and bool((set(claimed) - {name}) & family)


def limits_markdown(limits: dict[str, dict[str, Any]],
                    claimed: Iterable[str] = ()) -> list[str]:
    """The report's lines on what the scene cannot test (from ``detection_limits``); an
    effect the diagnosis claimed is left out (the data showed it, whatever its fitted
    size), and both anisotropic blurs where one is claimed (:func:`family_claimed`)."""
    claimed = set(claimed)
    shown = [lim for name, lim in limits.items()
             if name not in claimed and not family_claimed(name, claimed)]
    if not shown:
        return []
    return (["\n## What this scene cannot test\n"]
            + [f"- {lim['note']}." for lim in shown]
            + ["\nSuch an effect is not claimed whether or not the satellite has it (for a "
               "blur, the refitted Q then includes it)."])
