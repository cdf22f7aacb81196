"""The catalogue of physics the paper's model leaves out.

Each effect is a small object with

* ``name`` – the identifier used in ``diagnosis.json`` and in ``truth.json``;
* ``params`` – :class:`ParamSpec` entries with physical units and bounds;
* ``apply(image, **params)`` – the forward model on the 0.5 m grid, using
  :mod:`geosim.physics.otf` and :mod:`geosim.physics.radiometry`;
* ``transfer(fy, fx, **params)`` for effects that act as a linear shift-invariant
  blur (their expected transfer function, fitted to the measured cross-spectrum);
* ``signature`` – what in the data tells this effect apart from the others;
* ``explanation`` – the physics in plain words, and ``describe(params)`` – a
  sentence with the fitted numbers.

Conventions: images bands-first in DN (0–255 for 8-bit), frequencies in cycles
per pixel of the 0.5 m grid, directions in degrees clockwise from grid north in
[0, 180).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from geosim.physics import cubic, otf, radiometry
from geosim.physics.cubic import OPENCV_A
from geosim.physics.geometry import fourier_shift, step_side

__all__ = [
    "NON_LSI", "lsi_transfers",
    "ParamSpec", "Effect", "BlurEffect", "CATALOGUE", "BLUR_EFFECTS", "get_effect",
    "resampling_transfer",
]


@dataclass(frozen=True)
class ParamSpec:
    """One parameter of an effect.

    Attributes
    ----------
    name
        Parameter name with its unit suffix (``length_px``, ``direction_deg``).
    unit
        Unit in words (``"pixels of the 0.5 m grid"``).
    lower, upper
        Physical bounds used by the fit.
    initial
        Starting values for the fit (several = multi-start).
    periodic
        Period of an angular parameter (180 for directions), else ``None``.
    nuisance
        A shape parameter rather than the effect's size (the resampling's cubic kernel):
        a fit at either end of its range is still a real instance of the effect.
    """

    name: str
    unit: str
    lower: float
    upper: float
    initial: tuple[float, ...]
    periodic: float | None = None
    nuisance: bool = False


class Effect:
    """Base class: an effect with a forward model, signature and explanation."""

    name: ClassVar[str] = ""
    kind: ClassVar[str] = ""          # blur | radiometric | noise | compression | geometric | scene
    params: ClassVar[tuple[ParamSpec, ...]] = ()
    signature: ClassVar[str] = ""
    explanation: ClassVar[str] = ""

    def apply(self, image: np.ndarray, *, rng: np.random.Generator | None = None,
              **params: Any) -> np.ndarray:
        """Forward model on a bands-first image on the 0.5 m grid."""
        raise NotImplementedError

    def describe(self, params: Mapping[str, Any]) -> str:
        """A plain-language sentence with the parameter values."""
        vals = ", ".join(f"{k} = {_fmt(v)}" for k, v in params.items())
        return f"{self.explanation} Fitted: {vals}."


def _fmt(v: Any) -> str:
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


class BlurEffect(Effect):
    """A linear shift-invariant blur with a parametric transfer function."""

    kind = "blur"

    def transfer(self, fy: np.ndarray, fx: np.ndarray, **params: float) -> np.ndarray:
        raise NotImplementedError

    def apply(self, image: np.ndarray, *, rng: np.random.Generator | None = None,
              **params: Any) -> np.ndarray:
        return otf.apply_transfer(np.asarray(image, dtype=float),
                                  lambda fy, fx: self.transfer(fy, fx, **params))


class DetectorIntegration(BlurEffect):
    name = "detector_integration"
    params = (ParamSpec("pitch_px", "detector width in pixels of the 0.5 m grid", 0.2, 3.0,
                        (0.6, 1.2, 2.0)),)
    signature = ("isotropic, separable sinc roll-off (square symmetry), first zero at "
                 "1/pitch_px cycles per pixel")
    explanation = ("Each detector element integrates the light falling on its whole area, "
                   "which averages the scene over a box one detector wide and damps fine "
                   "detail with a sinc-shaped transfer function.")

    def transfer(self, fy, fx, *, pitch_px):
        return otf.detector_otf(fy, fx, pitch_px=pitch_px)


class AtmosphericBlur(BlurEffect):
    name = "atmospheric_blur"
    params = (ParamSpec("f0_cyc_per_px", "cycles per pixel (1/e frequency)", 0.05, 3.0,
                        (0.25, 0.5, 1.0)),)
    signature = "isotropic smooth roll-off exp(-(f/f0)^(5/3)), no zeros, heavy at mid frequencies"
    explanation = ("Turbulence and scattering in the air column between ground and satellite "
                   "spread each point of light into a soft halo, an extra blur that grows "
                   "smoothly with spatial frequency.")

    def transfer(self, fy, fx, *, f0_cyc_per_px):
        return otf.atmospheric_otf(fy, fx, f0_cyc_per_px=f0_cyc_per_px)


class MotionSmear(BlurEffect):
    name = "motion_smear"
    params = (ParamSpec("length_px", "smear length in pixels of the 0.5 m grid", 0.2, 8.0,
                        (1.5, 3.0)),
              ParamSpec("direction_deg", "degrees clockwise from grid north", 0.0, 180.0,
                        (0.0, 45.0, 90.0, 135.0), periodic=180.0))
    signature = ("anisotropic: sinc(L f) along one direction (zeros and sign flips at "
                 "multiples of 1/L), no loss across it")
    explanation = ("The platform moved (or the TDI clock was mismatched) during the exposure, "
                   "so each ground point was smeared into a short line along one direction.")

    def transfer(self, fy, fx, *, length_px, direction_deg):
        return otf.motion_otf(fy, fx, length_px=length_px, direction_deg=direction_deg)


class OffNadirAnisotropy(BlurEffect):
    name = "off_nadir_anisotropy"
    params = (ParamSpec("sigma_px", "Gaussian σ along the look azimuth, pixels", 0.05, 3.0,
                        (0.4, 1.0)),
              ParamSpec("azimuth_deg", "degrees clockwise from grid north", 0.0, 180.0,
                        (0.0, 45.0, 90.0, 135.0), periodic=180.0))
    signature = "anisotropic smooth Gaussian roll-off along one azimuth, no zeros"
    explanation = ("The satellite looked at the ground at an angle, which stretches each "
                   "detector's footprint along the viewing azimuth and blurs the image more in "
                   "that direction than across it.")

    def transfer(self, fy, fx, *, sigma_px, azimuth_deg):
        return otf.off_nadir_otf(fy, fx, sigma_px=sigma_px, azimuth_deg=azimuth_deg)


def resampling_transfer(fy: np.ndarray, fx: np.ndarray, native_pitch_px: float,
                        cubic_a: float = OPENCV_A) -> np.ndarray:
    """Average (coherent) transfer of area-averaging onto a native grid of ``native_pitch_px``
    and cubic convolution (kernel parameter ``cubic_a``) back:
    ∏ sinc(p f) · K_a(p f) over both axes.

    Content above the native Nyquist 1/(2p) is aliased; the aliased part is incoherent
    with the scene at the same frequency and shows up as low coherence, not in H.
    """
    p = native_pitch_px
    return (np.sinc(p * fx) * cubic.cubic_mtf(p * fx, cubic_a)
            * np.sinc(p * fy) * cubic.cubic_mtf(p * fy, cubic_a))


class Resampling(BlurEffect):
    name = "resampling"
    params = (ParamSpec("native_pitch_px", "native GSD / product GSD", 1.1, 3.0,
                        (1.3, 1.6, 2.0)),
              # processors differ: OpenCV -0.75, GDAL/Pillow/most "cubic convolution" -0.5
              # (Keys); the transfer is linear in it. A shape parameter, not an effect size:
              # either end of its range is a real kernel, so a fit there is no sign of
              # the effect standing in for another (not checked by ``at_bound``)
              ParamSpec("cubic_a", "cubic-convolution kernel parameter (dimensionless)",
                        -1.0, -0.5, (-0.6,), nuisance=True))
    signature = ("transfer near zero above the native Nyquist 1/(2·native_pitch_px), with "
                 "aliased (incoherent) power there")
    explanation = ("The product was delivered on a finer grid than the detector really "
                   "sampled (e.g. 0.65–0.8 m native resampled or pansharpened to 0.5 m), so "
                   "detail finer than the native sampling is missing or aliased.")

    def transfer(self, fy, fx, *, native_pitch_px, cubic_a=OPENCV_A):
        return resampling_transfer(fy, fx, native_pitch_px, cubic_a)

    def apply(self, image, *, rng=None, native_pitch_px, cubic_a=OPENCV_A):
        return radiometry.resample_through_native(np.asarray(image, dtype=float),
                                                  native_pitch_px=native_pitch_px,
                                                  cubic_a=cubic_a)


class SensorNoise(Effect):
    name = "sensor_noise"
    kind = "noise"
    params = (ParamSpec("gain_dn", "shot-noise variance per DN of signal (DN)", 0.0, 10.0, (0.1,)),
              ParamSpec("read_var_dn2", "signal-independent variance (DN²)", 0.0, 1000.0, (1.0,)))
    signature = ("flat (white) spectral floor in the real scene with low coherence; residual "
                 "variance rises linearly with brightness")
    explanation = ("Photon shot noise and electronic read noise add a random grain to every "
                   "pixel; its variance grows with the brightness of the pixel.")

    def apply(self, image, *, rng=None, gain_dn, read_var_dn2):
        if rng is None:
            raise ValueError("sensor_noise needs an explicit numpy.random.Generator")
        return radiometry.add_sensor_noise(image, gain_dn=gain_dn, read_var_dn2=read_var_dn2,
                                           rng=rng)


class Haze(Effect):
    name = "haze"
    kind = "radiometric"
    params = (ParamSpec("transmission", "fraction per band [r, g, b]", 0.2, 1.2, (1.0,)),
              ParamSpec("path_radiance_dn", "DN per band [r, g, b]", -50.0, 150.0, (0.0,)))
    signature = "per-band offset > 0 and gain < 1, strongest in blue"
    explanation = ("Light scattered by the atmosphere into the sensor adds a veil of "
                   "brightness (path radiance) and lowers the contrast of the ground, more in "
                   "blue than in red. (Transmission is relative to the UAV mosaic's "
                   "radiometry, so it also holds any exposure or white-balance difference.)")

    def apply(self, image, *, rng=None, transmission, path_radiance_dn):
        return radiometry.haze(image, transmission=transmission,
                               path_radiance_dn=path_radiance_dn)


class ColourResponse(Effect):
    name = "colour_response"
    kind = "radiometric"
    params = (ParamSpec("gain", "multiplicative factor per band [r, g, b]", 0.2, 5.0, (1.0,)),)
    signature = "per-band gains different from 1 without an offset"
    explanation = ("The satellite's spectral bands and white balance differ from the UAV "
                   "camera's, so each colour channel is scaled differently.")

    def apply(self, image, *, rng=None, gain):
        return radiometry.apply_gain_offset(image, gain=gain)


class ExposureSeam(Effect):
    name = "exposure_seam"
    kind = "flight_artefact"
    params = (ParamSpec("factor", "brightness factor of the stepped side", 0.5, 2.0, (1.0,)),
              ParamSpec("normal_deg", "line normal, degrees from the column axis toward the "
                        "row axis (image axes)", 0.0, 360.0, (0.0,), periodic=360.0),
              ParamSpec("offset_px", "line distance from the image centre, pixels", -1e4, 1e4,
                        (0.0,)))
    signature = ("two radiometric relations on the two sides of a straight line: the same "
                 "offset, gains in the same ratio in every band")
    explanation = ("The UAV mosaic blends frames taken with different exposures: on one side "
                   "of a straight seam every band is brighter by the same factor. This belongs "
                   "to the flight, not to the satellite; the haze is fitted with the seam "
                   "corrected, relative to the brighter side.")

    def apply(self, image, *, rng=None, factor, normal_deg, offset_px, **_):
        img = np.asarray(image, dtype=float)
        side = step_side(img.shape[-2:], normal_deg=normal_deg, offset_px=offset_px)
        return img * np.where(side, factor, 1.0)


#: side of a JPEG minimum coded unit with 4:2:0 chroma subsampling, px
MCU_PX = 16


class Compression(Effect):
    name = "compression"
    kind = "compression"
    params = (ParamSpec("quality", "JPEG quality 1–100", 5.0, 100.0, (75.0,)),)
    signature = "steps at 8×8 block edges; spectral peaks at multiples of 1/8 cycle per pixel"
    explanation = ("The product was stored with lossy block compression (JPEG-like 8×8 DCT), "
                   "which removes fine detail inside blocks and leaves steps at block edges.")

    def apply(self, image, *, rng=None, quality, block_offset_px=(0, 0)):
        """JPEG (4:2:0) round trip whose 16 px minimum coded units start at rows and
        columns ≡ ``block_offset_px`` (mod 16); the 8×8 luma blocks at the same phase mod 8.
        The phase mod 16 places the chroma's 16 × 16 blocks (subsampled 8 × 8)."""
        img = np.asarray(image, dtype=float)
        orow, ocol = (int(block_offset_px[0]) % MCU_PX, int(block_offset_px[1]) % MCU_PX)
        pr, pc = (MCU_PX - orow) % MCU_PX, (MCU_PX - ocol) % MCU_PX
        padded = np.pad(img, ((0, 0), (pr, 0), (pc, 0)), mode="edge")
        out = radiometry.jpeg_roundtrip(padded, quality=int(round(quality)))
        return out[:, pr:, pc:]


class Misregistration(Effect):
    name = "misregistration"
    kind = "geometric"
    params = (ParamSpec("shift_px", "[column (east), row (south)] pixels", -8.0, 8.0, (0.0,)),)
    signature = "linear phase ramp in the cross-spectrum; no change of its magnitude"
    explanation = ("The simulation and the real scene are offset (and possibly slightly "
                   "rotated or scaled) relative to each other by georeferencing errors of either "
                   "product; to a pixel-by-pixel comparison this looks like blur, but it is only "
                   "geometry.")

    def apply(self, image, *, rng=None, shift_px):
        return fourier_shift(image, (float(shift_px[0]), float(shift_px[1])))


class SceneChange(Effect):
    name = "scene_change"
    kind = "scene"
    params = ()
    signature = "localized object-sized residuals that no global physics explains"
    explanation = ("The ground itself changed between the UAV flight and the satellite pass "
                   "(cattle moved, shadows, water, vehicles); these areas are excluded from the "
                   "physics fit, and the refined simulation models the change in them as "
                   "compact objects that appeared or left, seen through the fitted optics "
                   "(n_objects_modelled; 0 where they did not improve the fit).")

    def apply(self, image, *, rng=None, **params):
        return np.asarray(image, dtype=float)


CATALOGUE: dict[str, Effect] = {e.name: e for e in (
    DetectorIntegration(), AtmosphericBlur(), MotionSmear(), OffNadirAnisotropy(), Resampling(),
    SensorNoise(), Haze(), ColourResponse(), ExposureSeam(), Compression(), Misregistration(),
    SceneChange())}

BLUR_EFFECTS: tuple[str, ...] = tuple(n for n, e in CATALOGUE.items() if e.kind == "blur")


def get_effect(name: str) -> Effect:
    """The catalogue entry called ``name`` (KeyError lists the known names)."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise KeyError(f"unknown effect {name!r}; known: {', '.join(CATALOGUE)}") from None


#: blur effects whose forward model is not shift-invariant (applied with ``apply``, so that
#: the refined simulation carries their aliasing, not only their average transfer)
NON_LSI = ("resampling",)


def lsi_transfers(effects: Mapping[str, Mapping[str, Any]]) -> list[otf.TransferFunction]:
    """The transfer functions of the shift-invariant effects among ``effects`` (name →
    parameters), in their order; compose them with :func:`geosim.physics.otf.compose`."""
    return [(lambda fy, fx, n=n, p=p: get_effect(n).transfer(fy, fx, **p))
            for n, p in effects.items() if n not in NON_LSI]
