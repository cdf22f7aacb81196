"""The paper's local-warp figure: the u-component of a random smooth field and the warped image."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from geosim.augment.resample import remap_resample  # noqa: E402
from geosim.augment.warp import DisplacementField, smooth_field  # noqa: E402
from geosim.io.atomic import atomic_path  # noqa: E402

__all__ = ["default_warp_parameters", "plot_local_warp"]


def default_warp_parameters(shape: tuple[int, int]) -> tuple[float, float]:
    """Exaggerated, clearly visible warp for a figure: ``(max_px, filter_sigma_px)``.

    3 % and 10 % of the shorter image side, pixels.
    """
    side = min(shape)
    return max(1.0, 0.03 * side), max(2.0, 0.10 * side)


def _display(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(rows, cols[, 3]) float in [0, 1] for imshow: first three bands, 2–98 % stretch."""
    img = image[:3] if image.shape[0] >= 3 else image[:1]
    vals = img[:, mask] if mask.any() else img.reshape(img.shape[0], -1)
    lo, hi = np.percentile(vals, [2, 98]) if vals.size else (0.0, 1.0)
    out = np.clip((img.astype(np.float32) - lo) / max(float(hi - lo), 1e-6), 0.0, 1.0)
    out = np.moveaxis(out, 0, -1)
    if out.shape[-1] == 1:
        out = np.repeat(out, 3, axis=-1)
    return np.where(mask[..., np.newaxis], out, 1.0)  # invalid shown white


def plot_local_warp(image: np.ndarray, mask: np.ndarray, out_path: str | os.PathLike[str], *,
                    max_px: float, filter_sigma_px: float, rng: np.random.Generator,
                    grid_step_px: int | None = None, title: str | None = None,
                    px_scale: float = 1.0) -> tuple[Path, DisplacementField]:
    """Draw a random local warp and plot its u-component beside the warped image.

    Parameters
    ----------
    image
        ``(bands, rows, cols)`` image (first three bands shown as RGB).
    mask
        ``(rows, cols)`` bool valid-data mask.
    out_path
        PNG to write (atomically).
    max_px, filter_sigma_px
        Field maximum displacement and low-pass filter width, pixels (see
        :func:`geosim.augment.warp.smooth_field`).
    rng
        Source of the field.
    grid_step_px
        Spacing of a reference grid drawn over the warped image, moved with the
        pixels so the warp is visible (``None``: an eighth of the shorter side;
        0: no grid).
    title
        Figure title.
    px_scale
        Source pixels per pixel of ``image`` when it is a decimated preview: axes,
        offsets and the annotated parameters are then shown in source pixels.

    Returns
    -------
    path, field
        The PNG written and the field drawn.
    """
    rows, cols = mask.shape
    field = smooth_field((rows, cols), max_px=max_px, filter_sigma_px=filter_sigma_px, rng=rng)
    warped, wmask = remap_resample(image, mask, field.u_px, field.v_px)
    fig, (ax_u, ax_img) = plt.subplots(1, 2, figsize=(12, 5.4), constrained_layout=True)
    k = float(px_scale)
    extent = (0.0, cols * k, rows * k, 0.0)
    lim = float(np.abs(field.u_px).max()) * k or 1.0
    im = ax_u.imshow(field.u_px * np.float32(k), cmap="RdBu_r", vmin=-lim, vmax=lim,
                     extent=extent)
    fig.colorbar(im, ax=ax_u, label="u offset (px)", shrink=0.85)
    ax_u.set_title(f"u component of the field (max |d| = {field.max_px * k:.3g} px, "
                   f"filter σ = {filter_sigma_px * k:.3g} px)", fontsize=10)
    ax_img.imshow(_display(warped, wmask), extent=extent, interpolation="antialiased")
    step = grid_step_px if grid_step_px is not None else max(4, min(rows, cols) // 8)
    if step:
        n = 200
        lines = [np.column_stack([np.full(n, x), np.linspace(0, rows, n)])
                 for x in np.arange(step, cols, step)]
        lines += [np.column_stack([np.linspace(0, cols, n), np.full(n, y)])
                  for y in np.arange(step, rows, step)]
        for line in lines:
            pts = field.forward_points(line) * k
            ax_img.plot(pts[:, 0], pts[:, 1], color="yellow", lw=0.6, alpha=0.8)
        ax_img.set_xlim(0, cols * k)
        ax_img.set_ylim(rows * k, 0)
    ax_img.set_title("warped image (yellow: a straight grid, moved with the pixels)",
                     fontsize=10)
    for ax in (ax_u, ax_img):
        ax.set_xlabel("column (px)")
        ax.set_ylabel("row (px)")
    if title:
        fig.suptitle(title)
    out = Path(out_path)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=120, format="png")
    plt.close(fig)
    return out, field
