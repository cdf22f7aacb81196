"""Blur stage: the Q grid of exact simulations, screened Welch blocks and block
cross-validation folds (:class:`SpectralSetup`), forward blur selection with room for Q
(:func:`select_with_q_room`) and the exact window-aware family decisions
(:func:`exact_anisotropic`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from geosim.diagnose.alias_cells import ALIAS_Q_MAX, SPLIT_Q_MAX, AliasPieces, alias_pieces
from geosim.diagnose.context import FitWindow
from geosim.diagnose.exact_family import EXACT_FAMILIES, exact_duel
from geosim.diagnose.fit import (
    BinFilter,
    SpectralData,
    alias_unexplained_share,
    build_spectral_data,
)
from geosim.diagnose.jpeg_transfer import JpegTransfer
from geosim.diagnose.model import ForwardModel, Registration
from geosim.diagnose.select import BlurSelection, select_blur
from geosim.diagnose.spectra import apply_taper, block_origins, screen_blocks
from geosim.diagnose.stage_inputs import Inputs, grey
from geosim.errors import DiagnosisError

__all__ = ["SpectralSetup", "spectral_setup", "change_taper", "extent_block_px",
           "select_with_q_room", "quadrant_folds", "exact_anisotropic", "adopt", "ISOTROPIC",
           "MIN_BLOCKS", "MIN_FIT_BLOCKS", "Q_EXTEND", "Q_GRID_STEP", "Q_MAX", "TAPER_SIGMA_PX"]

#: Welch blocks wanted for a stable transfer-function estimate
MIN_BLOCKS = 16
#: fewest Welch blocks a transfer fit is made from (after smaller blocks and the change
#: taper were tried): fewer is refused
MIN_FIT_BLOCKS = 8
#: σ (px) of the Gaussian edge with which the changed regions are tapered out of both
#: images where they leave too few whole blocks (:func:`change_taper`): the taper's edge
#: leaks the scene's strong low frequencies, unblurred in both images, towards higher
#: ones and so biases a measured blur transfer towards 1 — by 6-11 % at 0.1-0.25 cycles/px
#: with σ 1.5 px, 3-6 % with 3 px, on a scene half tapered (tests/test_diagnose_change_taper)
TAPER_SIGMA_PX = 3.0
#: Q grid extension when the fitted Q is pinned at its upper end (factor, largest Q)
Q_EXTEND = 1.5
#: ratio of neighbouring Q values of the grid of exact simulations
Q_GRID_STEP = 1.12
Q_MAX = 6.0
#: effects whose smooth isotropic roll-off the JPEG's high-frequency loss can imitate
ISOTROPIC = ("detector_integration", "atmospheric_blur")


@dataclass
class SpectralSetup:
    """Q grid of exact simulations, Welch blocks and the block cross-validation folds."""

    q_grid: np.ndarray
    #: the grey Q-grid simulations as rendered (not tapered: see ``taper``)
    sims_grey: list[np.ndarray]
    origins: list[tuple[int, int]]
    block_px: int
    full: SpectralData
    folds: list[tuple[SpectralData, SpectralData]]
    n_screened: int
    #: the bins the transfer fits use (under JPEG: where its linearised transfer was
    #: measured, :meth:`~geosim.diagnose.jpeg_transfer.JpegTransfer.measured_at`); None: all
    keep: BinFilter | None = None
    #: weights (rows, cols) in [0, 1] with which the changed regions are tapered out of
    #: the real scene and of every simulation before its blocks are cut (``full`` and
    #: ``folds`` were built so; the exact model tapers its renders, :func:`change_taper`);
    #: None: not tapered
    taper: np.ndarray | None = None
    #: the simulations' parts folded from each alias cell (:func:`split_alias_cells`, not
    #: tapered; ``full`` and ``folds`` were built with them tapered); None: not split
    pieces: AliasPieces | None = None
    #: per bin of the block grid, the share of the incoherent power that is noise, not
    #: the alias cells' folding (:func:`~geosim.diagnose.fit.alias_unexplained_share`;
    #: ``full``, ``folds`` and the exact duels' blocks were built with it); None: all
    share: np.ndarray | None = None

    def tapered(self, img: np.ndarray) -> np.ndarray:
        """A grey image (rows, cols) as the fits see it: with the changed regions tapered
        out as they were from the simulations (unchanged without a taper)."""
        return apply_taper(img, self.taper)


def adopt(model: ForwardModel, sel: BlurSelection) -> ForwardModel:
    """``model`` with the Q and blur effects of the selection's final fit."""
    return model.without(q=sel.final.q, blur=dict(sel.final.effects))


def quadrant_folds(origins: list[tuple[int, int]], block_px: int, shape: tuple[int, int]
                   ) -> list[list[tuple[int, int]]]:
    """Blocks grouped by quadrant of their centre (contiguous, so held-out blocks share
    as few pixels as possible with the training blocks)."""
    rows, cols = shape
    groups: list[list[tuple[int, int]]] = [[], [], [], []]
    for o in origins:
        k = 2 * int(o[0] + block_px / 2 >= rows / 2) + int(o[1] + block_px / 2 >= cols / 2)
        groups[k].append(o)
    return [g for g in groups if len(g) >= 2]


def select_with_q_room(inp: Inputs, model: ForwardModel, window: FitWindow,
                       jpeg: JpegTransfer | None = None) -> tuple[SpectralSetup, BlurSelection]:
    """Q grid, Welch blocks and forward blur selection, with room for Q.

    The Q grid ends at ``window.q_hi`` (from the LV baseline, which noise and JPEG pull
    far from the true Q). When Q alone (the null model) or Q with the chosen blur is
    pinned at that end, the scene is blurrier than the grid allows and an isotropic blur
    stands in for the missing optics; the grid is then extended (× :data:`Q_EXTEND`, up to
    :data:`Q_MAX`) and the selection redone (the caller's ``window`` is unchanged). The
    grid is not widened otherwise: a wide grid lets Q absorb real isotropic blurs (tried
    and reverted before).

    ``window``: the fit mask, Q range, candidate effects and Q starting values.
    ``jpeg``: under compression, the JPEG's transfer linearised around the blurred model
    (the simulations are filtered by it instead of being JPEG'd sharp)."""
    while True:
        setup = spectral_setup(inp, model, window, jpeg)
        sel = select_blur(setup.full, setup.folds, candidates=window.candidates,
                          q_starts=window.q_starts)
        top = setup.q_grid[-1] / 1.01
        if window.q_hi >= Q_MAX or not (sel.null.q >= top or sel.final.q >= top):
            return setup, sel
        window = replace(window, q_hi=min(Q_MAX, Q_EXTEND * window.q_hi))


def spectral_setup(inp: Inputs, model: ForwardModel, window: FitWindow,
                   jpeg: JpegTransfer | None = None) -> SpectralSetup:
    """Exact simulations on the Q grid from ``window.q_lo`` to ``window.q_hi``, screened
    Welch blocks inside ``window.mask``, CV folds (under JPEG, with ``jpeg`` given: the
    uncompressed simulations filtered by its linearised transfer)."""
    rows, cols = inp.valid.shape
    q_lo, q_hi = window.q_lo, window.q_hi
    n_q = int(np.ceil(np.log(q_hi / q_lo) / np.log(Q_GRID_STEP))) + 1
    q_grid = np.exp(np.linspace(np.log(q_lo), np.log(q_hi), n_q))
    if jpeg is not None and model.compression is None:
        jpeg = None  # nothing compressed: the simulations are used as they are
    if jpeg is not None:
        sims_grey = [jpeg.apply(grey(model.sim_at(inp.simulate, q, compressed=False)))
                     for q in q_grid]
    else:
        sims_grey = [grey(model.sim_at(inp.simulate, q)) for q in q_grid]
    base_g = grey(model.sim_at(inp.simulate, inp.q_base))
    real_g = inp.grey
    block_px = inp.block_px
    while True:  # smaller Welch blocks when changes leave too few whole blocks
        origins = block_origins((rows, cols), block_px=block_px, valid=window.mask)
        origins, rho = screen_blocks(base_g, real_g, origins, block_px)
        if len(origins) >= MIN_BLOCKS or block_px <= 16:
            break
        block_px //= 2
    taper = None
    if len(origins) < MIN_BLOCKS and not window.mask[inp.valid].all():
        # changed regions scattered over a small scene leave too few whole blocks even of
        # 16 px: they are tapered out of the scene and every simulation alike, and every
        # valid block is used (see change_taper), of the size the valid extent holds
        taper = change_taper(window.mask, inp.valid)
        real_g = apply_taper(inp.grey, taper)
        block_px = extent_block_px(inp.valid, inp.block_px)
        origins = block_origins((rows, cols), block_px=block_px, valid=inp.valid)
        origins, rho = screen_blocks(apply_taper(base_g, taper), real_g, origins, block_px)
    if len(origins) < MIN_FIT_BLOCKS:
        # still too few (most blocks unlike the simulation): every valid block as it is
        # (the changes then lower the coherence, which the fit weights by)
        taper, real_g = None, inp.grey
        block_px = extent_block_px(inp.valid, inp.block_px)
        origins = block_origins((rows, cols), block_px=block_px, valid=inp.valid)
        rho = np.zeros(len(origins))
    if len(origins) < MIN_FIT_BLOCKS:
        raise DiagnosisError(f"real scene: only {len(origins)} fully valid {block_px}×{block_px} "
                             f"blocks on the {inp.gsd_m:g} m grid; the diagnosis needs at least "
                             f"{MIN_FIT_BLOCKS} — give a larger common extent")
    keep = jpeg.measured_at if jpeg is not None else None
    fit_sims = [apply_taper(s, taper) for s in sims_grey]
    # blurs before sampling (alias cells); the fits see the pieces tapered as the
    # simulations (the taper is linear), the exact model tapers its renders itself
    pieces = split_alias_cells(inp, model, q_grid)
    fit_pieces = taper_pieces(pieces, taper)
    share = (alias_unexplained_share(fit_sims[0], fit_pieces[0], real_g, origins, block_px)
             if fit_pieces is not None and fit_pieces[0] is not None else None)

    def spectral_data(blocks: list[tuple[int, int]]) -> SpectralData:
        return build_spectral_data(fit_sims, q_grid, real_g, origins=blocks,
                                   block_px=block_px, keep=keep, pieces=fit_pieces,
                                   share=share)

    full = spectral_data(origins)
    groups = quadrant_folds(origins, block_px, (rows, cols))
    folds = []
    if len(groups) >= 2:
        for k, g in enumerate(groups):
            train = [o for j, gg in enumerate(groups) if j != k for o in gg]
            folds.append((spectral_data(train), spectral_data(g)))
    return SpectralSetup(q_grid=q_grid, sims_grey=sims_grey, origins=origins, block_px=block_px,
                         full=full, folds=folds, n_screened=len(rho) - len(origins), keep=keep,
                         taper=taper, pieces=pieces, share=share)


def extent_block_px(valid: np.ndarray, block_px: int) -> int:
    """The largest Welch block side (px) of ``block_px``, its half, ... down to 16 of which
    the valid extent holds :data:`MIN_BLOCKS` whole (half-overlapping) blocks; 16 where
    none does. A flight's turned footprint in a small window holds few 32 px blocks: the
    changes tapered out at 32 px left 4 of them and the flight was refused (12 of 128
    development flights with moved objects, round 38), while 16 px blocks fill it."""
    while block_px > 16 and len(block_origins(valid.shape, block_px=block_px,
                                              valid=valid)) < MIN_BLOCKS:
        block_px //= 2
    return block_px


def change_taper(mask: np.ndarray, valid: np.ndarray,
                 sigma_px: float = TAPER_SIGMA_PX) -> np.ndarray:
    """Weights (rows, cols) in [0, 1] that taper the changed regions out of an image.

    ``mask`` is True where the fit may look (valid and outside the changed regions, which
    :func:`~geosim.diagnose.locate.regions_mask` already dilates); the weight is its
    Gaussian blur (σ ``sigma_px``), 0 outside ``valid``. Moved cattle scattered over a
    128 px scene leave few whole 32 px (or 16 px) blocks outside them (development c264:
    18 blobs, 34 % of the scene, 0 blocks of 32 px, 9 of 16 px), and the fit then lost the
    blur it was there to find; with every block included as it was, the moved objects'
    power, which the simulation does not share, distorts the transfer (by 0.10-0.15 RMS in
    ln on the test's scenes). Multiplying the real scene and every simulation by the same
    smooth weight (around their means) keeps every block's unchanged part. The weight's
    edge is not a blur: it leaks the scene's strong low frequencies, unblurred in either
    image, towards higher ones, so a blur measures a few per cent weaker than it is
    (:data:`TAPER_SIGMA_PX`; 0.03-0.04 RMS in ln on the test's scenes, half of each
    tapered); the exact model, which tapers its renders after their blur, carries the
    same leakage."""
    w = ndimage.gaussian_filter(np.asarray(mask, float), sigma_px)
    return np.where(valid, w, 0.0)


def split_alias_cells(inp: Inputs, model: ForwardModel, q_grid: np.ndarray
                      ) -> AliasPieces | None:
    """The Q-grid simulations' parts folded from each alias cell, made as the simulations
    are (the registration's shift on the fine grid, or the sampled image moved), so that a
    blur acts on them before sampling (:mod:`geosim.diagnose.alias_cells`).

    Where the images have invalid pixels the pieces are filled from the nearest valid
    pixel as the simulations are (a linear map, so they still sum to the simulation).

    None where the fits start at Q ≥ :data:`~geosim.diagnose.alias_cells.SPLIT_Q_MAX`,
    the simulator cannot split, or the model holds a compression: through the JPEG's
    linearised transfer the pieces fitted the development scenes worse than none (round
    29: 5 of the 7 JPEG rows at Q < 1.8 whose fit changed, e.g. spectral error 0.013 ->
    0.061), so under JPEG the fits keep the sampled model."""
    reg = model.registration
    source, shift = reg.fine_source(inp.simulate)
    cells = getattr(source, "alias_simulators", None)
    if (q_grid[0] >= ALIAS_Q_MAX or model.q >= SPLIT_Q_MAX or not callable(cells)
            or model.compression is not None):
        return None
    sims = cells(shift)
    if sims is None:
        return None
    finish = _piece_finish(reg)
    return alias_pieces(sims, q_grid, q_min=float(getattr(inp.simulate, "q_min", 0.0)),
                        finish=finish)


def _piece_finish(reg: Registration) -> Callable[[np.ndarray], np.ndarray] | None:
    """What a sampled 2-D piece goes through to lie on the real scene, as the simulations
    do (:meth:`~geosim.diagnose.model.Registration.onto_scene`); None where that is
    nothing (all pixels valid, and the move made before sampling or none)."""
    if reg.fill_idx is None and (reg.before_sampling or not reg.applied):
        return None
    return lambda img: reg.onto_scene(img[np.newaxis])[0]


def taper_pieces(pieces: AliasPieces | None, taper: np.ndarray | None
                 ) -> AliasPieces | None:
    """The alias pieces as the fits see the simulations: each real and imaginary part
    tapered by :func:`~geosim.diagnose.spectra.apply_taper` (linear in the image, so the
    tapered pieces sum to the tapered simulation); unchanged without a taper."""
    if pieces is None or taper is None:
        return pieces
    return [None if pc is None else
            {c: apply_taper(a.real, taper) + 1j * apply_taper(a.imag, taper)
             for c, a in pc.items()} for pc in pieces]


def exact_anisotropic(inp: Inputs, setup: SpectralSetup, sel: BlurSelection
                      ) -> BlurSelection:
    """Choose the anisotropic, then the isotropic blur by the exact (window-aware) model
    and refit the chosen blurs with it (:mod:`geosim.diagnose.exact_family`).

    The fast fit sees every blur through the Welch window's leakage, which smooths a sinc
    towards a Gaussian (``motion_smear`` / ``off_nadir_anisotropy``) and the detector's
    box towards the atmosphere's roll-off (``detector_integration`` /
    ``atmospheric_blur``); within each family the exact model's χ² on all blocks decides
    (members have equal numbers of parameters), the held-out χ² gives the evidence. The
    chosen effects, Q and gain are then the exact model's joint fit (on all blocks)."""
    groups = quadrant_folds(setup.origins, setup.block_px, inp.valid.shape)
    for family in EXACT_FAMILIES:
        sel = exact_duel(setup.tapered(inp.grey), setup.sims_grey, setup.q_grid, setup.full,
                         setup.origins, groups, setup.block_px, sel, family, inp.q_base, setup.keep,
                         taper=setup.taper, pieces=setup.pieces, share=setup.share)
    return sel
