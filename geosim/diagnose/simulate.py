"""The paper's degradation model as seen by the diagnosis.

``paper_model(uav, q=, phi=)`` is I_sat = (I_uav ⊛ PSF(Q)) ↓φ with bicubic
downsampling: the project's one implementation,
:func:`geosim.degrade.core.degrade_array` (and its cached spectral form,
:class:`geosim.degrade.core.SpectralDegrader`, for many Q on one image).
"""

from __future__ import annotations

import numpy as np

from geosim.degrade.core import (
    SpectralDegrader,
    dct_coefficients,
    degrade_array,
    fill_invalid,
    optics_otf_below_cutoff,
)
from geosim.diagnose.alias_cells import iter_cell_parts
from geosim.physics import otf
from geosim.physics.cubic import OPENCV_A
from geosim.physics.geometry import AffineField, fourier_shift, warp_to_fine_grid
from geosim.physics.native_grid import native_cols_dct, native_rows_dct, native_to_product
from geosim.physics.otf import TransferFunction
from geosim.physics.radiometry import luma

__all__ = ["paper_model", "QSimulator", "VARIANT_CACHE"]

#: moved / pre-blurred variants a simulator keeps (each holds only its truncated DCT
#: coefficients, not the filtered UAV image)
VARIANT_CACHE = 4


def paper_model(uav: np.ndarray, *, q: float, phi: int, valid: np.ndarray | None = None
                ) -> np.ndarray:
    """Simulated satellite image (bands, rows/phi, cols/phi) in DN, float64.

    Parameters
    ----------
    uav
        UAV image, bands first, on the fine grid (phi pixels per satellite pixel).
    q
        Q of the simulated optics (dimensionless, λ f / (D p)).
    phi
        Ratio satellite GSD / UAV GSD (whole number).
    """
    out, _ = degrade_array(np.asarray(uav), q=q, phi=phi, valid=valid)
    return np.asarray(out, dtype=float)


class QSimulator:
    """Cache of paper-model simulations at several Q for one UAV image.

    Calling ``sim(q)`` returns the (cached) paper model at that Q.
    """

    def __init__(self, uav: np.ndarray, *, phi: int, valid: np.ndarray | None = None,
                 q_min: float = 0.5, keep_image: bool = True) -> None:
        self.uav: np.ndarray | None = np.asarray(uav)
        self.phi = int(phi)
        self.valid = valid
        #: whether every UAV pixel is valid (no fill needed)
        self._all_valid = valid is None or bool(np.all(valid))
        self.q_min = float(q_min)
        self._cache: dict[float, np.ndarray] = {}
        self._fast = SpectralDegrader(self.uav, phi=self.phi, q_min=self.q_min, valid=valid)
        self._variants: dict[object, QSimulator] = {}
        #: (key, the optics' image of the moved fine image as its DCT below the cut-off)
        self._native_fine: tuple[object, np.ndarray] | None = None
        self._native_low: tuple[object, tuple[np.ndarray, np.ndarray, np.ndarray]] | None \
            = None
        #: (key, the native rows' step of the last native sampling and their centres)
        self._native_rows: tuple[object, tuple[np.ndarray, np.ndarray]] | None = None
        self._native_coef: tuple[object, np.ndarray] | None = None
        self._alias: tuple[object, dict[tuple[int, int], tuple[QSimulator, QSimulator]]] | None \
            = None
        self._weighted: tuple[tuple[float, ...], QSimulator] | None = None
        self._warped: tuple[AffineField, QSimulator] | None = None
        #: the UAV image with its invalid pixels filled (float32), where it has any
        self._filled: np.ndarray | None = None
        if not keep_image:  # only the degrader's truncated coefficients (variants: memory)
            self.uav = None

    def _complete(self) -> np.ndarray:
        """The UAV image (float64) as the paper's model degrades it: invalid pixels filled
        by :func:`~geosim.degrade.core.fill_invalid`, as
        :class:`~geosim.degrade.core.SpectralDegrader` fills them (kept once made)."""
        if self._all_valid:
            return np.asarray(self.uav, dtype=float)
        if self._filled is None:
            self._filled = fill_invalid(self.uav, self.valid)
        return np.asarray(self._filled, dtype=float)

    def _moved_valid(self) -> np.ndarray | None:
        """The valid mask of a simulator of this image moved or filtered on the fine grid:
        this one's where it is all valid; None (complete) where the invalid pixels were
        filled — the move carries filled values across the mask, and the caller fills the
        invalid product pixels from the nearest valid ones
        (:attr:`~geosim.diagnose.model.Registration.fill_idx`)."""
        return self.valid if self._all_valid else None

    def __call__(self, q: float) -> np.ndarray:
        key = round(float(q), 4)
        if key not in self._cache:
            if key >= self.q_min:
                out = np.asarray(self._fast.degrade(key), dtype=float)
                self._cache[key] = out[np.newaxis] if out.ndim == 2 else out
            else:
                if self.uav is None:
                    raise ValueError(f"q = {key} is below q_min = {self.q_min} of a simulator "
                                     "that keeps no image (a variant)")
                self._cache[key] = paper_model(self.uav, q=key, phi=self.phi, valid=self.valid)
        return self._cache[key]

    def with_image(self, image: np.ndarray) -> QSimulator:
        """A simulator of ``image`` (the same grid: bands first or 2-D, on this one's fine
        grid, DN) with this one's φ, valid mask and Q floor — e.g. the UAV image with the
        ground that changed before the satellite pass painted in
        (:func:`geosim.diagnose.stage_painted.paint_objects`), which every Q, blur, shift
        and native resampling then renders as it renders the ground."""
        return QSimulator(image, phi=self.phi, valid=self.valid, q_min=self.q_min)

    def shifted(self, shift_px: tuple[float, float]) -> QSimulator | None:
        """The same simulator for the UAV image moved by ``shift_px`` (d_col, d_row) pixels
        of the **satellite** grid, the move made on the fine grid *before* the optics and
        sampling, where a real misregistration acts. Moving the sampled simulation instead
        is not the same when the optics pass content above the satellite Nyquist (Q ≲ 1.2):
        the aliased part then moves by a different phase, loses its coherence with the
        scene and looks like blur and noise. Invalid UAV pixels are filled first
        (:meth:`_complete`). ``None`` when this simulator keeps no image (the caller then
        moves the sampled simulation).
        """
        return self.variant(shift_px=shift_px)

    def warped(self, field: AffineField) -> QSimulator | None:
        """The same simulator for the UAV image moved by a shift + rotation + scale
        ``field`` (displacement in **satellite** pixels, affine in the satellite pixel
        position: :func:`geosim.physics.geometry.affine_field`), the move made on the fine
        grid before the optics and sampling, as :meth:`shifted` moves a global shift (the
        UAV image warped once by a cubic spline on the fine grid, where the optics remove
        what the spline gets wrong; warping every *sampled* simulation instead costs a warp
        per render and moves its aliased content by the wrong phase). It keeps its image,
        so its own :meth:`variant`, :meth:`native`, :meth:`weighted` and
        :meth:`alias_simulators` render the moved scene; the last one is kept. Invalid UAV
        pixels are filled first (:meth:`_complete`). ``None`` when this simulator keeps no
        image."""
        if self.uav is None:
            return None
        if self._warped is None or self._warped[0] != field:
            img = warp_to_fine_grid(self._complete(), field, self.phi)
            self._warped = (field, QSimulator(img.astype(np.float32), phi=self.phi,
                                              valid=self._moved_valid(), q_min=self.q_min))
        return self._warped[1]

    def variant(self, *, shift_px: tuple[float, float] = (0.0, 0.0),
                transfer: TransferFunction | None = None, key: object = None
                ) -> QSimulator | None:
        """The simulator of the UAV image moved by ``shift_px`` (satellite pixels) and
        filtered by ``transfer`` (a blur given in cycles per **satellite** pixel), both on
        the fine grid, before the optics and the sampling — where the real physics acts.
        A blur applied to the sampled simulation cannot remove the aliased power that the
        same blur, acting before sampling, keeps out of the real scene (Q ≲ 1.5).

        ``key``: a hashable description of ``transfer`` for the cache (the last
        :data:`VARIANT_CACHE` variants are kept). Invalid UAV pixels are filled first
        (:meth:`_complete`). ``None`` when this simulator keeps no image (the caller then
        works on the sampled simulation).
        """
        if self.uav is None:
            return None
        ck = (round(float(shift_px[0]), 6), round(float(shift_px[1]), 6), key)
        if ck in self._variants:
            return self._variants[ck]
        img = self._moved_filtered(self._complete(), shift_px, transfer)
        out = QSimulator(img.astype(np.float32), phi=self.phi, valid=self._moved_valid(),
                         q_min=self.q_min, keep_image=False)
        if len(self._variants) >= VARIANT_CACHE:
            self._variants.pop(next(iter(self._variants)))
        self._variants[ck] = out
        return out

    def weighted(self, weights: tuple[float, ...]) -> QSimulator | None:
        """The simulator of the one-band image ``Σ_b weights[b] · uav[b]`` (its paper
        model, variants and native renders are the same weighted sums of this one's, every
        step being linear and the same in each band); the last one is kept. ``None`` when
        this simulator keeps no image or ``weights`` does not match its bands."""
        if self.uav is None or len(weights) != (self.uav.shape[0] if self.uav.ndim == 3 else 1):
            return None
        key = tuple(float(w) for w in weights)
        if self._weighted is None or self._weighted[0] != key:
            img = np.asarray(self.uav, dtype=float)
            img = img[np.newaxis] if img.ndim == 2 else img
            one = np.tensordot(np.asarray(key), img, axes=1)[np.newaxis]
            self._weighted = (key, QSimulator(one, phi=self.phi, valid=self.valid,
                                              q_min=self.q_min))
        return self._weighted[1]

    def alias_simulators(self, shift_px: tuple[float, float] = (0.0, 0.0)
                         ) -> dict[tuple[int, int], tuple[QSimulator, QSimulator]] | None:
        """Per alias cell (:data:`geosim.diagnose.alias_cells.ALIAS_CELLS`), simulators of
        the real and the imaginary part of the cell's share of the grey UAV image moved by
        ``shift_px`` (satellite pixels, on the fine grid as :meth:`variant` moves it): their
        paper model at Q is the part of the grey simulation that sampling folds from that
        cell. ``None`` where :meth:`variant` gives none (no image kept).
        The last shift's are kept."""
        if self.uav is None:
            return None
        key = (round(float(shift_px[0]), 6), round(float(shift_px[1]), 6))
        if self._alias is not None and self._alias[0] == key:
            return self._alias[1]
        fine = self._moved_filtered(luma(self._complete()), shift_px, None)
        sims = {c: tuple(QSimulator(part[np.newaxis].astype(np.float32), phi=self.phi,
                                    q_min=self.q_min, keep_image=False)
                         for part in (im.real, im.imag))
                for c, im in iter_cell_parts(fine, self.phi)}
        self._alias = (key, sims)  # type: ignore[assignment]
        return sims  # type: ignore[return-value]

    def _moved_filtered(self, img: np.ndarray, shift_px: tuple[float, float],
                        transfer: TransferFunction | None) -> np.ndarray:
        """The fine-grid image ``img`` moved by ``shift_px`` and filtered by ``transfer``
        (both in satellite-grid units, scaled here by φ)."""
        if shift_px[0] != 0 or shift_px[1] != 0:
            img = fourier_shift(img, (float(shift_px[0]) * self.phi,
                                      float(shift_px[1]) * self.phi))
        if transfer is not None:
            phi = self.phi
            img = otf.apply_transfer(img, lambda fy, fx: transfer(fy * phi, fx * phi))
        return img

    def native(self, q: float, native_pitch_px: float, *, cubic_a: float = OPENCV_A,
               shift_px: tuple[float, float] = (0.0, 0.0),
               transfer: TransferFunction | None = None, key: object = None,
               phase_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray | None:
        """A product resampled from a coarser native sampling, rendered where it happens:
        the UAV image (moved by ``shift_px`` and filtered by ``transfer``, satellite-grid
        units, as in :meth:`variant`) through the optics of ``q`` on the fine grid, each
        native detector averaging its area (``native_pitch_px`` product pixels, any real
        value; a native pixel edge at ``phase_px``, (row, col) product pixels), then cubic
        convolution (kernel parameter ``cubic_a``) onto the product grid
        (:func:`geosim.physics.native_grid.render_through_native`).
        Resampling the *sampled* simulation instead misses the aliasing the native
        sampling makes of content above the product Nyquist (Q ≲ 1.5). Invalid UAV pixels
        are filled first (:meth:`_complete`). ``None`` when the simulator keeps no image.
        Bands first, DN, float64."""
        if self.uav is None:
            return None
        moved_key = (round(float(shift_px[0]), 6), round(float(shift_px[1]), 6), key)
        ck = (round(float(q), 4), *moved_key)
        if self._native_fine is None or self._native_fine[0] != ck:
            if self._native_coef is None or self._native_coef[0] != moved_key:
                # the moved, filtered fine image's DCT kept: scans refit Q pitch by pitch
                img = self._complete()
                img = self._moved_filtered(img[np.newaxis] if img.ndim == 2 else img,
                                           shift_px, transfer)
                self._native_coef = (moved_key, dct_coefficients(img))
            # the optics' image as its DCT below the cut-off (the pitch and phase scans
            # reuse it): no inverse transform of the fine image
            coef = self._native_coef[1]
            # at the Q of the cache key, as __call__ renders: a Q differing beyond the key's
            # digits would otherwise render as whichever came first
            otf_k = optics_otf_below_cutoff(coef.shape[-2:], q=ck[0], phi=self.phi)
            self._native_fine = (ck, coef[:, :otf_k.shape[0], :otf_k.shape[1]] * otf_k)
            self._native_low = self._native_rows = None
        band_coef = self._native_fine[1]
        fine_shape = self._native_coef[1].shape[-2:]   # type: ignore[index]
        # the native sampling kept for the next call: the kernel scans render each pitch
        # with both cubic kernels, one after the other; and its row step, which the phase
        # scans share between the column phases of a row phase (the same products)
        rk = (ck, round(float(native_pitch_px), 9), round(float(phase_px[0]), 9))
        nk = (*rk, round(float(phase_px[1]), 9))
        if self._native_low is None or self._native_low[0] != nk:
            if self._native_rows is None or self._native_rows[0] != rk:
                self._native_rows = (rk, native_rows_dct(band_coef, fine_shape[0], self.phi,
                                                         native_pitch_px, phase_px[0]))
            rows_step, cr = self._native_rows[1]
            nat, cc = native_cols_dct(rows_step, fine_shape[1], self.phi, native_pitch_px,
                                      phase_px[1])
            self._native_low = (nk, (nat, cr, cc))
        nat, cr, cc = self._native_low[1]
        rows, cols = fine_shape[0] // self.phi, fine_shape[1] // self.phi
        return native_to_product(nat, cr, cc, (rows, cols), cubic_a)
