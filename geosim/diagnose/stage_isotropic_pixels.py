"""An isotropic blur beside a resampling or alone, by its trace in the pixels
(:func:`pixel_isotropic`).

Where a resampling is claimed, its aliasing fills the band above the native Nyquist with
power the transfer fit reads as incoherence, and an isotropic roll-off (a detector box, an
atmosphere) that acts below that band differs from a wider optical PSF by little the
transfer can weigh: on the development half (round 25's code) 6 of the 17 detectors and
atmospheres beside a claimed resampling (no JPEG) were ideally detectable (observer
Δχ² 3e3-4e4) and went into Q instead (Q fitted 21-70 % high).

In the pixels the resampled product is determined (the native grid's phase: the model's,
refined on the power spectrum, or one of its offsets by thirds of a cell, chosen on the
scene), so the model with the missing roll-off fits the scene pixel by pixel where a wider
PSF cannot. No Q below :data:`MIN_Q` is scanned with a member. Each member
of the isotropic family is scanned over its parameter (Q refitted on the transfer with
it and the other blurs held, then scanned by factors in the pixels); the member and
parameter are chosen on one half of the evaluation pixels (left / right of the middle
column) and must lower the other half's residual by at least
:data:`ISO_PIXEL_MIN_DCHI2` of that half's residual variance per pixel, against the model
without it (its Q scanned on the same half), both ways round. The member claimed is the
one of lowest residual over both halves that can be claimed (inside its scan, clearly
present, and the model with it fitting no worse than the baseline, as
:func:`~geosim.diagnose.stage_withdraw.never_worse` asks of the refined simulation; a
member after the first passing the test on its own: :func:`first_claimable`); the other
is listed as an alternative where it passes the same test. Once
the claim is decided, the resampling's pitch, Q and native phase are refined again on the
power spectrum with the chosen blur held (:data:`REFINE_ON_SPECTRUM`: the pixels chose Q
on a coarse scan and the phase on a grid).

Alone (round 43), with no blur in the model and no JPEG, a detector box or an atmosphere
at high Q differs from a wider optical PSF by little the transfer can weigh (development,
round 42's rows: 29 lone detectors and 11 lone atmospheres missed in this domain, ideal
observer Δχ² up to 1e4), while in the pixels the same scan separates it from Q alone. The
same test and threshold apply, and the scene must show no anisotropic trace: a smear's or
an elongation's misfit is partly taken up by a roll-off, and the anisotropic stage that
follows tests those (:func:`_lone_domain`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from geosim.diagnose.context import EvalContext
from geosim.diagnose.fit import fit_transfer
from geosim.diagnose.grey_render import grey_expected
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.select import (
    BLUR_FAMILY,
    Alternative,
    BlurSelection,
    clearly_present,
)
from geosim.diagnose.stage_aliasing import refined_from
from geosim.diagnose.stage_anisotropic_pixels import (
    SCREEN_MIN_DCHI2,
    anisotropy_screen,
    screen_splits,
)
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs
from geosim.diagnose.stage_noise import realisations
from geosim.diagnose.stage_resampling_coherent import (
    PHASE_STEPS,
    append_pixel_step,
    eval_halves,
    heldout_drop,
    heldout_gain,
    rss_on_halves,
)
from geosim.diagnose.stage_withdraw import Q_FLOOR_REL, no_worse_than_baseline

__all__ = ["pixel_isotropic", "lone_possible", "IsotropicScan", "isotropic_scan",
           "member_alternatives", "first_claimable", "ISO_PIXEL_MIN_DCHI2", "REFINE_ON_SPECTRUM",
           "MEMBER_SCAN", "Q_FACTORS", "BASE_Q_FACTORS", "MIN_Q"]

#: held-out drop of the residual sum of squares the isotropic blur must bring, in units of
#: the held-out half's residual variance per pixel, on each half. Set on the development
#: half (round 26, the 110 scenes of this stage's domain in round 25's rows, weaker half;
#: measured with the first version, whose phase came from a coarse grid alone and whose Q
#: went down to the floor):
#: of the 93 without an isotropic blur, one passed with a claimable value (c186, 384: a
#: smear claimed as off-nadir, whose misfit a 1.0 px detector takes up; c196, 444, left Q
#: at its floor), the next c276 at 90 (c461 189 and c172 92 at the end of the scan); of
#: the 17 with one: c552 741, c727 653, c154 582, c404 527, c16 190, c24 182 (a detector
#: named for an atmosphere), c102 140; c762 83 missed, c366's pitch at the end of the scan
ISO_PIXEL_MIN_DCHI2 = 100.0
#: (parameter, scanned values) of each member of the isotropic family; a value at an end
#: of its scan is not claimed (it stands in for a shape beyond it)
MEMBER_SCAN: dict[str, tuple[str, np.ndarray]] = {
    "detector_integration": ("pitch_px", np.round(np.arange(0.6, 2.0 + 1e-9, 0.1), 2)),
    "atmospheric_blur": ("f0_cyc_per_px", np.round(np.arange(0.15, 0.65 + 1e-9, 0.025), 3)),
}
#: lowest Q scanned with a member: below it the optics pass content beyond the product
#: grid's Nyquist, and what the model leaves of its aliases takes a box's or an
#: atmosphere's shape (the alias-cell weakness, ``docs/limitations.md``): a resampling alone
#: at Q 1.0 (``tests/test_diagnose_independent.py``, seed 31) reached a held-out Δχ² of
#: 133 with a 0.8 px detector at Q 0.94; development c196 (Q 0.93, none) 394
MIN_Q = 1.0
#: factors on the transfer-refitted Q scanned in the pixels for each scanned member
Q_FACTORS = (0.9, 0.95, 1.0, 1.05, 1.1)
#: factors on the model's Q scanned in the pixels for the model without the isotropic blur
#: (adding a roll-off lowers Q; the model without it is given the same room below)
BASE_Q_FACTORS = (0.85, 0.9, 0.95, 1.0, 1.05, 1.1)


@dataclass
class IsotropicScan:
    """Residual sums of squares of the scanned models on the two halves of the pixels.

    Attributes
    ----------
    halves
        Bool masks (rows, cols): the evaluation pixels left and right of the middle column.
    base
        The model without an isotropic blur (its native phase chosen) and its [RSS on each
        half, DN²] at each of :data:`BASE_Q_FACTORS`.
    scanned
        (member, parameter value, model with it at a scanned Q, [RSS on each half, DN²])
        for every member, value and Q factor (those that leave Q at or below
        ``Q_FLOOR_REL`` × the bottom of the Q grid left out: there
        :func:`~geosim.diagnose.stage_withdraw.blur_at_q_floor` withdraws the blur).
    """

    halves: list[np.ndarray]
    base: list[tuple[ForwardModel, list[float]]]
    scanned: list[tuple[str, float, ForwardModel, list[float]]]

    def heldout_dchi2(self, member: str | None = None) -> list[float]:
        """Held-out drop on each half (:func:`heldout_drop`) with the models chosen among
        every member's (or only ``member``'s)."""
        alt = [r for n, _, _, r in self.scanned if member is None or n == member]
        return heldout_drop(self.halves, [r for _, r in self.base], alt)

    def members(self) -> list[str]:
        """The members scanned, in order of their lowest RSS over both halves."""
        lowest: dict[str, float] = {}
        for n, _, _, r in self.scanned:
            lowest[n] = min(lowest.get(n, np.inf), sum(r))
        return sorted(lowest, key=lowest.__getitem__)

    def best(self, member: str | None = None) -> tuple[str, float, ForwardModel]:
        """(member, value, model) of lowest RSS over both halves."""
        n, v, m, _ = min((s for s in self.scanned if member is None or s[0] == member),
                         key=lambda s: sum(s[3]))
        return n, v, m


def _pinned(member: str, value: float) -> bool:
    """At an end of the member's scan (:data:`MEMBER_SCAN`)."""
    grid = MEMBER_SCAN[member][1]
    return bool(np.isclose(value, grid[0]) or np.isclose(value, grid[-1]))


def _sized(member: str, value: float) -> bool:
    """Clearly away from the member's null: :func:`~geosim.diagnose.select.clearly_present`
    on its scanned parameter."""
    return clearly_present(member, {MEMBER_SCAN[member][0]: value})


def isotropic_scan(inp: Inputs, model: ForwardModel, setup: SpectralSetup, ev: EvalContext,
                   members: list[str]) -> IsotropicScan | None:
    """The scan of :func:`pixel_isotropic`; None when a half holds no pixels."""
    halves = eval_halves(ev)
    if halves is None:
        return None

    def rss(m: ForwardModel) -> list[float]:
        return rss_on_halves(inp, halves, m)

    # the native grid's phase, on all the evaluation pixels: the models compared share it.
    # Offsets from the model's phase (refined on the power spectrum), which stays a
    # candidate: a coarse grid alone had replaced it at Q 1.0, and the aliases left by the
    # wrong phase read as a detector box
    if "resampling" in model.blur:
        pitch = float(model.blur["resampling"]["native_pitch_px"])
        steps = np.arange(PHASE_STEPS) * pitch / PHASE_STEPS
        r0, c0 = model.native_phase_px
        phases = [(float(r0 + a), float(c0 + b)) for a in steps for b in steps]
        model = model.without(native_phase_px=min(
            phases, key=lambda p: sum(rss(model.without(native_phase_px=p)))))
    base = []
    for f in BASE_Q_FACTORS:
        m = model.without(q=model.q * f)
        base.append((m, rss(m)))
    q_floor = max(Q_FLOOR_REL * float(setup.q_grid[0]), MIN_Q)
    scanned = []
    for name in members:
        key, grid = MEMBER_SCAN[name]
        for v in grid:
            held = {**model.blur, name: {key: float(v)}}
            fit = fit_transfer(setup.full, [], q_starts=(model.q,), fixed=held)
            m1 = model.without(q=fit.q, blur=dict(fit.effects))
            for f in Q_FACTORS:
                if fit.q * f <= q_floor:
                    continue   # Q at its bound or below MIN_Q
                m = m1.without(q=fit.q * f)
                scanned.append((name, float(v), m, rss(m)))
    return IsotropicScan(halves=halves, base=base, scanned=scanned) if scanned else None


#: refine the resampling's pitch, Q and phase on the power spectrum once the blur is
#: claimed (not before the baseline test: refined first, c692's false detector passed it).
#: Round 27, development (the 11 scenes where the stage claims): the benchmark's spectral
#: error of the refined simulation fell in 8 (c196 0.113 → 0.028, c833 0.043 → 0.030, c404
#: 0.032 → 0.022, c154 0.053 → 0.044, ...) and rose in 3 (c102 0.036 → 0.043, c762 0.041 →
#: 0.048, c24 0.060 → 0.062); claims unchanged
REFINE_ON_SPECTRUM = True


def member_alternatives(scan: IsotropicScan, claimed: str, members: list[str]
                        ) -> list[Alternative]:
    """The members other than ``claimed`` that pass the same held-out test
    (:data:`ISO_PIXEL_MIN_DCHI2` on both halves) with a best value inside their scan, each
    with its weaker half's gain and that value; a member with no scanned configuration
    (every Q below :data:`MIN_Q`) is not one (development c196), nor one whose best value
    sits at an end of its scan (it stands in for a shape beyond it: development c33's
    2.0 px detector beside the atmosphere claimed)."""
    out = []
    for other in members:
        if other == claimed or not any(n == other for n, _, _, _ in scan.scanned):
            continue
        d = scan.heldout_dchi2(other)
        _, v, _ = scan.best(other)
        if min(d) >= ISO_PIXEL_MIN_DCHI2 and not _pinned(other, v):
            out.append(Alternative(other, heldout_gain(scan.halves, d),
                                   {MEMBER_SCAN[other][0]: v}))
    return out


def _on_spectrum_held(inp: Inputs, setup: SpectralSetup, ev: EvalContext,
                      model: ForwardModel) -> ForwardModel:
    """``model``'s resampling pitch, Q and native phase refined together on the power
    spectrum with the isotropic blur held (:func:`~geosim.diagnose.stage_aliasing.refined_from`,
    which with ``model`` as its one start returns ``model`` itself unless a refinement
    scores strictly lower)."""
    def se_of(m: ForwardModel) -> float:
        return ev.spectral_error(realisations(inp, m, ev.noise_seed))

    return refined_from(setup, [model], se_of)[0]


def _lone_domain(inp: Inputs, model: ForwardModel, ev: EvalContext) -> bool:
    """Whether a lone isotropic blur is tested: the model holds no blur at all, and the
    residual shows no anisotropic trace (the checkerboard colours of
    :func:`~geosim.diagnose.stage_anisotropic_pixels.anisotropy_screen` both below
    :data:`~geosim.diagnose.stage_anisotropic_pixels.SCREEN_MIN_DCHI2`): there a
    roll-off would take up part of a smear's or an elongation's misfit, and the
    anisotropic stage that follows tests it (development c293, an off-nadir elongation
    at Q 4.47: a 1.6 px detector gained 122 and 296 on the halves, the screen 1250)."""
    if model.blur:
        return False
    splits = screen_splits(ev)
    if splits is None:
        return False
    rendered = grey_expected(inp, model)
    screen = anisotropy_screen(inp.grey - rendered, rendered, splits[:1])
    return min(screen.dchi2) < SCREEN_MIN_DCHI2


def lone_possible(model: ForwardModel, candidates: tuple[str, ...]) -> bool:
    """Whether :func:`pixel_isotropic` would consider a lone blur on ``model`` (before
    its residual is screened): a member among ``candidates``, no blur and no JPEG."""
    return (any(n in candidates for n in MEMBER_SCAN) and not model.blur
            and model.compression is None)


def first_claimable(scan: IsotropicScan, ok: Callable[[ForwardModel], bool]
                    ) -> tuple[str, float, ForwardModel, list[float]] | None:
    """(member, value, model, held-out drops) claimed from a scan that passed: the members
    scanned, in order of their best residual over both halves (:meth:`IsotropicScan.members`),
    the first whose best value is inside its scan (:func:`_pinned`), clearly away from its
    null (:func:`_sized`) and accepted by ``ok`` (the engine's: its delivered simulation fits
    no worse than the baseline); a member after the first must pass the held-out test on its
    own. None when no member qualifies.

    A value at an end of its scan stands in for a shape beyond it, so there that member's
    shape is not the scene's; the other member, passing on its own, may be (development
    c33: an atmosphere whose best detector sat at 2.0 px, the atmosphere at 0.38 cycles/px
    passing 801 / 815). A member whose delivered simulation fits worse is not claimed:
    :func:`~geosim.diagnose.stage_withdraw.never_worse` would withdraw it and refit Q on
    the transfer, losing the Q the resampling's spectrum had put right (development c196:
    spectral error 0.027 → 0.103)."""
    for k, name in enumerate(scan.members()):
        dchi2 = scan.heldout_dchi2() if k == 0 else scan.heldout_dchi2(name)
        if min(dchi2) < ISO_PIXEL_MIN_DCHI2:
            continue
        _, value, chosen = scan.best(name)
        if not _pinned(name, value) and _sized(name, value) and ok(chosen):
            return name, value, chosen, dchi2
    return None


def pixel_isotropic(inp: Inputs, model: ForwardModel, sel: BlurSelection,
                    setup: SpectralSetup, ev: EvalContext,
                    candidates: tuple[str, ...], lone: bool = True) -> ForwardModel:
    """An isotropic blur claimed beside a resampling, or alone, by its trace in the pixels.

    Tested where the model holds no member of the isotropic family and no JPEG (whose
    quantisation is not independent of the image), and either a resampling or no blur at
    all with no anisotropic trace (:func:`_lone_domain`) where ``lone`` allows it (the
    engine leaves it to the painted second pass where moved objects are located). A lone
    blur is claimed from the scan's pixels as they chose it (no resampling to refine on
    the spectrum here; the engine refines its value and Q later,
    :func:`~geosim.diagnose.stage_isotropic_refine.refine_lone_isotropic`). The claim's
    step records ``heldout_gain`` as the weaker half's held-out drop of the residual sum
    of squares (fraction); its fit is the transfer fit with the
    chosen blur held (Q refitted), its uncertainty the scan's step."""
    members = [n for n in MEMBER_SCAN if n in candidates]
    if (not members or model.compression is not None
            or any(BLUR_FAMILY.get(n) == "isotropic" for n in model.blur)):
        return model
    alone = "resampling" not in model.blur
    if alone and not (lone and _lone_domain(inp, model, ev)):
        return model
    scan = isotropic_scan(inp, model, setup, ev, members)
    if scan is None:
        return model
    if min(scan.heldout_dchi2()) < ISO_PIXEL_MIN_DCHI2:
        return model
    picked = first_claimable(scan, no_worse_than_baseline(inp, ev))
    if picked is None:
        return model
    name, value, chosen, dchi2 = picked
    if REFINE_ON_SPECTRUM and not alone:
        # after the claim is decided: refined before it, development c692's false 1.0 px
        # detector (beside a resampling alone at Q 1.00, refined to Q 0.74) passed it
        chosen = _on_spectrum_held(inp, setup, ev, chosen)
    key, grid = MEMBER_SCAN[name]
    alternatives = member_alternatives(scan, name, members)
    # the transfer's χ² at the chosen Q (for the ΔBIC reported; the claim rests on the pixels)
    fit = fit_transfer(setup.full, [], fix_q=chosen.q, fixed=dict(chosen.blur))
    append_pixel_step(sel, setup, name, fit, {name: {key: float(grid[1] - grid[0])}}, 1,
                      heldout_gain(scan.halves, dchi2), alternatives)
    return chosen
