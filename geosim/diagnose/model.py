"""Typed results of the diagnosis stages: the extended forward model and the claims.

:class:`Registration` moves a simulation onto the real scene, :class:`CompressionFit`
re-encodes it, :class:`ForwardModel` holds everything the refit found (Q, blur,
seam, radiometry, noise) and renders the refined simulation; :class:`Claim` is one
named effect with its evidence, as written to ``diagnosis.json``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from geosim.diagnose.coregister import AffineEstimate, ShiftEstimate, warp_by_field
from geosim.diagnose.effects import NON_LSI, get_effect, lsi_transfers
from geosim.diagnose.seam import GainStep
from geosim.diagnose.stage_objects import SceneObjects
from geosim.physics import otf
from geosim.physics.geometry import fourier_shift
from geosim.physics.radiometry import apply_gain_offset, per_band_values

__all__ = ["Registration", "CompressionFit", "RadiometryChoice", "NoiseEstimate",
           "ForwardModel", "Claim", "blur_apply", "NON_LSI"]

def blur_apply(img: np.ndarray, effects: dict[str, dict[str, float]]) -> np.ndarray:
    """Apply blur effects (on the 0.5 m grid) to a bands-first image."""
    out = np.asarray(img, float)
    lsi = lsi_transfers(effects)
    if lsi:
        out = otf.apply_transfer(out, otf.compose(*lsi))
    for n, p in effects.items():
        if n in NON_LSI:
            out = get_effect(n).apply(out, **p)
    return out


@dataclass
class Registration:
    """How the simulation is moved onto the real scene (pixels of the 0.5 m grid)."""

    estimate: ShiftEstimate
    affine: AffineEstimate
    applied: bool
    shift_px: tuple[float, float]
    whole_px: tuple[float, float]
    field_px: tuple[np.ndarray, np.ndarray] | None = None
    fill_idx: np.ndarray | None = None
    #: ``presampled(q)``: the paper's model at q of the UAV image moved on the fine grid,
    #: before optics and sampling (where a real misregistration acts), by ``shift_px`` or,
    #: with a field, by the field (then a simulator that keeps the moved image:
    #: :meth:`geosim.diagnose.simulate.QSimulator.warped`); used instead of moving the
    #: sampled simulation when given
    presampled: Callable[[float], np.ndarray] | None = None

    @property
    def before_sampling(self) -> bool:
        """Whether the move is made on the fine grid, before the optics and sampling."""
        return self.applied and self.presampled is not None

    def fine_source(self, simulate: Any) -> tuple[Any, tuple[float, float]]:
        """(simulator, shift_px): where renders made on the fine grid (blur variants, native
        resamplings, alias parts) come out moved onto the real scene. A field's warped
        simulator with no further shift; ``simulate`` with the global shift; ``simulate``
        unmoved where the move is made after sampling (:meth:`move`)."""
        if not self.before_sampling:
            return simulate, (0.0, 0.0)
        if self.field_px is not None:
            return self.presampled, (0.0, 0.0)
        return simulate, self.shift_px

    def simulation(self, simulate: Callable[[float], np.ndarray], q: float) -> np.ndarray:
        """The paper's model at ``q`` moved onto the real scene: moved before sampling when
        :attr:`presampled` is available, else the sampled simulation moved (:meth:`move`)."""
        if self.before_sampling and q >= getattr(self.presampled, "q_min", 0.0):
            s = np.asarray(self.presampled(q), float)
            return self.fill(s[np.newaxis] if s.ndim == 2 else s)
        return self.move(simulate(q))

    def fill(self, sim: np.ndarray) -> np.ndarray:
        """``sim`` (…, rows, cols) with each invalid pixel taking its nearest valid pixel's
        value (:attr:`fill_idx`); as it is where every pixel is valid."""
        return sim[..., self.fill_idx[0], self.fill_idx[1]] if self.fill_idx is not None \
            else sim

    def onto_scene(self, sampled: np.ndarray) -> np.ndarray:
        """A bands-first render sampled from the UAV image as it lies on the real scene:
        filled (:meth:`fill`), and moved (:meth:`move`) unless the move was made on the
        fine grid before sampling (:attr:`before_sampling`: the render is of the moved
        image)."""
        return self.fill(sampled) if self.before_sampling else self.move(sampled)

    def move(self, sim: np.ndarray) -> np.ndarray:
        """A bands-first simulation, invalid pixels filled from the nearest valid, moved."""
        s = np.asarray(sim, float)
        s = self.fill(s[np.newaxis] if s.ndim == 2 else s)
        if self.field_px is not None:
            return warp_by_field(s, *self.field_px)
        return fourier_shift(s, self.shift_px) if self.applied else s

    def params(self, gsd_m: float) -> dict[str, Any]:
        """``misregistration`` parameters for diagnosis.json."""
        if self.field_px is not None:
            a = self.affine
            d = (a.shift_px[0] + self.whole_px[0], a.shift_px[1] + self.whole_px[1])
            return {"shift_px": [d[0], d[1]], "shift_m": [d[0] * gsd_m, -d[1] * gsd_m],
                    "rotation_deg": a.rotation_deg, "scale": a.scale,
                    "local_residual_px": a.residual_px, "at_px": list(a.centre_px)}
        d = self.estimate.shift_px
        return {"shift_px": [d[0], d[1]], "shift_m": list(self.estimate.shift_m(gsd_m))}


@dataclass
class CompressionFit:
    """JPEG re-encoding found from its quantisation lattice in the scene."""

    quality: int
    #: (row, col), px: where the 16 px minimum coded units start, mod 16 (the 8×8 luma
    #: blocks at the same phase mod 8; :func:`geosim.diagnose.stage_jpeg.mcu_grid`)
    offset_px: tuple[int, int]
    test: dict[str, float]

    def apply(self, img: np.ndarray) -> np.ndarray:
        return get_effect("compression").apply(img, quality=self.quality,
                                               block_offset_px=self.offset_px)


@dataclass(frozen=True)
class RadiometryChoice:
    """``haze`` or ``colour_response`` (or neither) with parameters and evidence.

    Returned by :func:`geosim.diagnose.select.select_radiometry`.

    Attributes
    ----------
    name : str or None
        ``"haze"``, ``"colour_response"`` or None (no radiometric effect claimed).
    params : dict of str to list of float
        Per-band parameters of ``name``: ``transmission`` (unitless) and
        ``path_radiance_dn`` (DN) for haze; ``gain`` (unitless) and optionally
        ``offset_dn`` (DN) for a colour response; empty when ``name`` is None.
    sigmas : dict of str to list of float
        Standard errors of ``params``, same keys and units; empty when ``name`` is None.
    delta_bic : float
        BIC of the identity minus that of the claimed model (of the better model
        when nothing is claimed); positive favours the effect.
    bic : dict of str to float
        BIC of the ``"identity"``, ``"gain"`` (per-band gain) and ``"affine"`` (gain and
        offset) models.
    alternatives : list of dict
        The other radiometric name where both describe the data equally (``name``,
        ``params``, ``delta_bic``), listed, never claimed.
    """

    name: str | None
    params: dict[str, list[float]]
    sigmas: dict[str, list[float]]
    delta_bic: float
    bic: dict[str, float]
    alternatives: list[dict[str, Any]] = field(default_factory=list)

    def apply(self, img: np.ndarray) -> np.ndarray:
        """``img`` (bands first, DN) with the claimed effect applied; unchanged if none."""
        if self.name not in ("haze", "colour_response"):
            return img
        gain, offset = self.gain_offset(img.shape[0])
        return apply_gain_offset(img, gain=gain, offset_dn=offset)

    def gain_offset(self, n_bands: int) -> tuple[np.ndarray, np.ndarray]:
        """(gain, offset DN) per band of ``n_bands``: :meth:`apply` is ``gain · x + offset``
        (haze: transmission and path radiance; a colour response's offset 0 unless fitted)."""
        gain_key, offset_key = (("transmission", "path_radiance_dn") if self.name == "haze"
                                else ("gain", "offset_dn"))
        gain = self.params.get(gain_key, 1.0) if self.name is not None else 1.0
        offset = self.params.get(offset_key, 0.0) if self.name is not None else 0.0
        return (per_band_values(gain, n_bands, gain_key),
                per_band_values(offset, n_bands, offset_key))


@dataclass
class NoiseEstimate:
    """Noise variance a·s + b (per band, DN²) and the evidence for it.

    ``white_var_dn2`` is the per-band variance of the white, incoherent part of the
    residual at high frequencies (rounding removed); ``whiteness`` the ratio of the
    incoherent power at mid to high frequencies (1 for white noise). ``estimator``:
    ``"spectral_floor"`` (that) or, under JPEG, ``"jpeg_dct_censored"`` (the variance
    from the quantised DCT coefficients; whiteness then the ratio of the low- and
    high-frequency coefficients' estimates).
    """

    gain_dn: float
    read_var_dn2: float
    gain_sigma: float
    read_sigma: float
    white_var_dn2: float
    whiteness: float
    claimed: bool
    quantization_dn2: float
    brightness_dn: np.ndarray = field(default_factory=lambda: np.zeros(0))
    variance_dn2: np.ndarray = field(default_factory=lambda: np.zeros(0))
    mean_variance_sigma: float = float("inf")
    delta_bic: float = 0.0
    estimator: str = "spectral_floor"


@dataclass
class ForwardModel:
    """The extended forward model the diagnosis refits."""

    q: float
    blur: dict[str, dict[str, float]]
    registration: Registration
    compression: CompressionFit | None = None
    seam: GainStep | None = None
    radiometry: RadiometryChoice | None = None
    noise: NoiseEstimate | None = None
    #: (row, col), product pixels: where an edge of a resampling's native grid lies
    #: against the product grid (taken modulo the native pitch; 0: the grids' first edges
    #: coincide). A real grid's phase is unknown: fitted where its aliasing shows
    #: (:mod:`geosim.diagnose.stage_aliasing`); see also
    #: :func:`geosim.diagnose.stage_change.resampling_phase_dn2`
    native_phase_px: tuple[float, float] = (0.0, 0.0)
    #: moved objects (scene change) added to the product before noise and compression
    #: (:mod:`geosim.diagnose.stage_objects`); None: the ground as the UAV saw it
    objects: SceneObjects | None = None

    @property
    def n_objects(self) -> int:
        """How many moved objects the model holds (0 without any)."""
        return len(self.objects.objects) if self.objects is not None else 0

    def gain_offset(self, n_bands: int) -> tuple[np.ndarray, np.ndarray]:
        """(gain, offset DN) per band of the model's radiometry
        (:meth:`RadiometryChoice.gain_offset`); 1 and 0 without one."""
        if self.radiometry is None:
            return np.ones(n_bands), np.zeros(n_bands)
        return self.radiometry.gain_offset(n_bands)

    def sim_at(self, simulate: Callable[[float], np.ndarray], q: float | None = None, *,
               compressed: bool = True) -> np.ndarray:
        """Paper's model at ``q`` (default: the model's), moved and (unless ``compressed``
        is False) compressed."""
        s = self.registration.simulation(simulate, self.q if q is None else q)
        if compressed and self.compression is not None:
            return self.compression.apply(s)
        return s

    def blurred(self, simulate: Callable[[float], np.ndarray]) -> np.ndarray:
        """With the blur effects and the seam correction (no radiometry, no compression).

        Shift-invariant blurs act on the UAV image before the optics and the sampling when
        the simulator can render that (``simulate.variant``, e.g.
        :meth:`geosim.diagnose.simulate.QSimulator.variant`), as the real physics acts;
        otherwise, and for ``resampling``, on the sampled simulation."""
        m, rest = self._presampled_blur(simulate)
        m = blur_apply(m, rest)
        if self.seam is not None:
            m = m * np.where(self.seam.side, self.seam.factor, 1.0)
        return m

    def _presampled_blur(self, simulate: Callable[[float], np.ndarray]
                         ) -> tuple[np.ndarray, dict[str, dict[str, float]]]:
        """(the moved simulation, the blur effects still to apply to it): the
        shift-invariant blurs are applied on the fine grid, before sampling, when the
        simulator can."""
        lsi = {n: p for n, p in self.blur.items() if n not in NON_LSI}
        rest = {n: p for n, p in self.blur.items() if n in NON_LSI}
        reg = self.registration
        source, shift = reg.fine_source(simulate)
        variant = getattr(source, "variant", None)
        native = getattr(source, "native", None)
        resampled = "resampling" in rest and callable(native)
        if (not lsi and not resampled) or not callable(variant) \
                or self.q < getattr(simulate, "q_min", 0.0):
            return self.sim_at(simulate, compressed=False), self.blur
        key = tuple(sorted((n, tuple(sorted(p.items()))) for n, p in lsi.items()))
        tr = otf.compose(*lsi_transfers(lsi)) if lsi else None
        s = None
        if resampled:
            # resampling rendered from the fine grid (native sampling of the optics' image)
            s = native(self.q, **rest["resampling"], shift_px=shift, transfer=tr, key=key,
                       phase_px=self.native_phase_px)
            if s is not None:
                rest = {n: p for n, p in rest.items() if n != "resampling"}
        if s is None:
            v = variant(shift_px=shift, transfer=tr, key=key) if lsi else None
            if v is None:
                return self.sim_at(simulate, compressed=False), self.blur
            s = np.asarray(v(self.q), float)
        return reg.onto_scene(s[np.newaxis] if s.ndim == 2 else s), rest

    def _before_compression(self, simulate: Callable[[float], np.ndarray]) -> np.ndarray:
        m = self.blurred(simulate)
        m = self.radiometry.apply(m) if self.radiometry is not None else m
        return self.objects.apply(m) if self.objects is not None else m

    def deterministic(self, simulate: Callable[[float], np.ndarray]) -> np.ndarray:
        """The expected refined image (no noise realisation). Compression acts last, on
        the product as delivered (after blur, sampling and radiometry), as in a camera."""
        m = self._before_compression(simulate)
        return self.compression.apply(m) if self.compression is not None else m

    def delivered(self, simulate: Callable[[float], np.ndarray], rng: np.random.Generator,
                  *, quantized: bool) -> np.ndarray:
        """As the product is delivered: with a noise realisation, whole DN if quantized,
        then compressed (JPEG encodes the noisy, quantized product)."""
        return self._deliver(self._before_compression(simulate), rng, quantized=quantized)

    def delivered_realisations(self, simulate: Callable[[float], np.ndarray],
                               rngs: list[np.random.Generator], *, quantized: bool
                               ) -> list[np.ndarray]:
        """:meth:`delivered` with each of ``rngs`` (noise realisations of one model), the
        deterministic part rendered once (the same arrays as separate calls give)."""
        m = self._before_compression(simulate)
        return [self._deliver(m, rng, quantized=quantized) for rng in rngs]

    def _deliver(self, m: np.ndarray, rng: np.random.Generator, *, quantized: bool
                 ) -> np.ndarray:
        """The deterministic image ``m`` (before compression) as delivered (not modified)."""
        if self.noise is not None and self.noise.claimed:
            m = get_effect("sensor_noise").apply(m, rng=rng, gain_dn=self.noise.gain_dn,
                                                 read_var_dn2=self.noise.read_var_dn2)
        m = np.round(m) if quantized else m
        return self.compression.apply(m) if self.compression is not None else m

    def without(self, **changes: Any) -> ForwardModel:
        return replace(self, **changes)


@dataclass
class Claim:
    """One named effect in diagnosis.json."""

    name: str
    params: dict[str, Any]
    uncertainty: dict[str, Any]
    delta_bic: float
    heldout_gain: float | None = None
    alternatives: list[dict[str, Any]] = field(default_factory=list)
    rmse_after: float = float("nan")
    spectral_error_after: float = float("nan")
    #: the statistics of a claim found by a test rather than a fit (compression: the
    #: quantisation lattice's log-likelihood gain and the quality's margin, and the
    #: block-edge steps' ratios, z-scores and phases per direction; an anisotropic blur
    #: renamed in the pixels: the member the transfer named and the pixels' evidence)
    test: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        e = get_effect(self.name)
        out: dict[str, Any] = {
            "name": self.name, "params": self.params, "uncertainty": self.uncertainty,
            "explanation": e.describe(self.params), "signature": e.signature,
            "delta_bic": self.delta_bic, "rmse_after": self.rmse_after,
            "spectral_error_after": self.spectral_error_after}
        if self.heldout_gain is not None:
            out["heldout_gain"] = self.heldout_gain
        if self.test is not None:
            out["test"] = self.test
        if self.alternatives:
            out["alternatives"] = self.alternatives
            out["indistinguishable_from"] = [a["name"] for a in self.alternatives]
        return out
