"""Noise stage: the scene's noise beyond the deterministic model
(:func:`~geosim.diagnose.noise.estimate_noise` on the stage's blocks), the noisy model's
expected spectrum from a few realisations, and the test that a claimed noise brings the
expected spectra together (:func:`noise_helps`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from geosim.diagnose.context import EvalContext
from geosim.diagnose.model import ForwardModel
from geosim.diagnose.noise import estimate_noise
from geosim.diagnose.stage_blur import SpectralSetup
from geosim.diagnose.stage_inputs import Inputs

__all__ = ["estimate_scene_noise", "realisations", "realisation_scatter", "noise_helps",
           "NOISE_SPECTRAL_GAIN", "NOISE_REALISATIONS", "NOISE_SCATTER_TOLERANCE"]

#: a claimed noise must bring the refined model's *expected* spectral error to this
#: fraction of the error without it, or less (plus the scatter below). Was 0.9 on a single
#: realisation: under JPEG, or where the scene's power dwarfs the noise, a right noise
#: changes the expected spectrum by < 1 % (development extension x5002, x5019)
NOISE_SPECTRAL_GAIN = 1.0
#: noise realisations whose mean Welch power stands for a noisy model's expected spectrum
#: in the noise and JPEG-isotropic tests (one realisation's error scatters by ± 0.08 on a
#: small JPEG'd scene, x5002)
NOISE_REALISATIONS = 4
#: the noisy model's expected error may exceed the one without noise by this many
#: standard deviations of its single realisations' errors (the estimate's own scatter)
NOISE_SCATTER_TOLERANCE = 1.0


def estimate_scene_noise(inp: Inputs, model: ForwardModel, setup: SpectralSetup,
                         fit_mask: np.ndarray) -> ForwardModel:
    """``model`` with the noise of the real scene beyond its deterministic part."""
    comp = model.compression
    return model.without(noise=estimate_noise(
        inp.real, model.deterministic(inp.simulate), fit_mask, origins=setup.origins,
        block_px=setup.block_px, quantized=inp.quantized,
        uncompressed=(model.without(compression=None).deterministic(inp.simulate)
                      if comp is not None else None),
        block_offset_px=comp.offset_px if comp is not None else (0, 0)))


def realisations(inp: Inputs, m: ForwardModel, rng_seed: int) -> list[np.ndarray]:
    """The delivered refined simulation of ``m``; with noise claimed, NOISE_REALISATIONS
    noise realisations of it (the first is the one delivered), whose mean Welch power is
    the model's expected spectrum."""
    n = NOISE_REALISATIONS if m.noise is not None and m.noise.claimed else 1
    return m.delivered_realisations(
        inp.simulate, [np.random.default_rng(rng_seed + k) for k in range(n)],
        quantized=inp.quantized)


def realisation_scatter(img: list[np.ndarray], se_of: Callable[[np.ndarray], float]) -> float:
    """NOISE_SCATTER_TOLERANCE standard deviations of the single realisations' spectral
    errors (0 for one image): the expected spectrum of a noisy model may exceed another
    model's error by this much, as two realisations of the truth differ at the floor."""
    if len(img) < 2:
        return 0.0
    return NOISE_SCATTER_TOLERANCE * float(np.std([se_of(i) for i in img], ddof=1))


def noise_helps(inp: Inputs, model: ForwardModel, ev: EvalContext
                ) -> tuple[ForwardModel, list[dict[str, str]]]:
    """Noise is kept only where adding it brings the expected spectra together: its
    expected spectral error (on ``ev``'s blocks, realisations from ``ev.noise_seed``) at
    most NOISE_SPECTRAL_GAIN × the model's without it (plus the realisations' scatter)."""
    if model.noise is None or not model.noise.claimed:
        return model, []
    se_of = ev.spectral_error
    quiet = model.without(noise=None)
    noisy = realisations(inp, model, ev.noise_seed)
    if se_of(noisy) <= NOISE_SPECTRAL_GAIN * se_of(realisations(inp, quiet, ev.noise_seed)) \
            + realisation_scatter(noisy, se_of):
        return model, []
    return quiet, [{"name": "sensor_noise",
                    "reason": "adding it does not improve the expected spectral fit"}]
