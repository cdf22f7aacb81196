"""Pure geometry of the pair augmentations: affine matrices and box tracking.

Coordinates
-----------
All matrices and boxes use *pixel-edge* coordinates of the image they act on:
``x`` to the right (columns) and ``y`` down (rows), in pixels, with the outer
corner of pixel ``(row 0, col 0)`` at ``(0, 0)`` and the centre of pixel
``(r, c)`` at ``(c + 0.5, r + 0.5)``. A ``cols`` × ``rows`` image spans
``[0, cols] × [0, rows]`` and its centre is ``(cols / 2, rows / 2)``. This is
the frame YOLO labels are normalised in, so a YOLO box maps to pixels by
multiplying by the image size and nothing else.

Matrices are 3 × 3 homogeneous and *forward*: they map a point of the input
image to where it lands in the output image (``p_out = M @ p_in``). All the
paper's geometric functions act about the image centre so that the output keeps
the input's size and the centre stays put.

Boxes are tracked as polygons (shapely 2, vectorised): the *full* object (never
clipped) and its *visible* part (clipped to the image after every resampling).
A rotated box stays a rotated quadrilateral, so chaining transforms never
inflates a box more than once; the YOLO box written at the end is the enclosing
axis-aligned box of the visible polygon, and a box is dropped when its visible
area falls below a fraction of its full area.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import shapely

__all__ = [
    "Boxes",
    "BoxTrack",
    "about_centre",
    "compose",
    "identity",
    "integer_permutation",
    "is_identity",
    "mirror_matrix",
    "rotation_matrix",
    "scale_matrix",
    "shear_matrix",
    "shift_matrix",
    "to_cv2_inverse",
]

_EPS = 1e-9


def identity() -> np.ndarray:
    """The 3 × 3 identity matrix (float64)."""
    return np.eye(3)


def _translation(dx_px: float, dy_px: float) -> np.ndarray:
    m = np.eye(3)
    m[0, 2] = dx_px
    m[1, 2] = dy_px
    return m


def about_centre(linear: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Forward matrix applying the 2 × 2 ``linear`` map about the image centre.

    Parameters
    ----------
    linear
        2 × 2 linear part, acting on pixel-edge coordinates (x right, y down).
    shape
        ``(rows, cols)`` of the image, pixels.
    """
    rows, cols = shape
    cx, cy = cols / 2.0, rows / 2.0
    m = np.eye(3)
    m[:2, :2] = np.asarray(linear, dtype=float)
    return _translation(cx, cy) @ m @ _translation(-cx, -cy)


def rotation_matrix(rotation_deg: float, shape: tuple[int, int]) -> np.ndarray:
    """Rotation about the image centre.

    Parameters
    ----------
    rotation_deg
        Angle, degrees; positive turns the content counter-clockwise as displayed
        (rows down), as ``cv2.getRotationMatrix2D`` does.
    shape
        ``(rows, cols)``, pixels.
    """
    if rotation_deg == 0:
        return identity()
    t = np.deg2rad(rotation_deg)
    c, s = np.cos(t), np.sin(t)
    # Exact zeros/ones at multiples of 90° so that those rotations are pixel permutations.
    c, s = (0.0 if abs(c) < 1e-15 else c), (0.0 if abs(s) < 1e-15 else s)
    return about_centre(np.array([[c, s], [-s, c]]), shape)


def shift_matrix(dx_px: float, dy_px: float) -> np.ndarray:
    """Translation by ``dx_px`` (right) and ``dy_px`` (down), pixels."""
    return _translation(float(dx_px), float(dy_px))


def scale_matrix(factor: float, shape: tuple[int, int]) -> np.ndarray:
    """Isotropic scaling by ``factor`` (dimensionless, > 0) about the image centre."""
    if factor <= 0:
        raise ValueError(f"scale factor must be > 0, got {factor}")
    return about_centre(np.diag([factor, factor]), shape)


def shear_matrix(shear_x: float, shear_y: float, shape: tuple[int, int]) -> np.ndarray:
    """Shear about the image centre: ``x' = x + shear_x · y``, ``y' = y + shear_y · x``.

    Parameters
    ----------
    shear_x, shear_y
        Shear ratios (dimensionless; pixels of displacement per pixel of distance
        from the centre line).
    shape
        ``(rows, cols)``, pixels.
    """
    return about_centre(np.array([[1.0, shear_x], [shear_y, 1.0]]), shape)


def mirror_matrix(flip_ud: bool, flip_lr: bool, shape: tuple[int, int]) -> np.ndarray:
    """Flip up/down and/or left/right; the result is an exact pixel permutation."""
    return about_centre(np.diag([-1.0 if flip_lr else 1.0, -1.0 if flip_ud else 1.0]), shape)


def compose(*matrices: np.ndarray) -> np.ndarray:
    """Matrix of applying ``matrices`` in the order given (first one first)."""
    out = identity()
    for m in matrices:
        out = np.asarray(m, dtype=float) @ out
    return out


def is_identity(matrix: np.ndarray, *, atol: float = _EPS) -> bool:
    """Whether a forward matrix moves no pixel by more than ``atol`` pixels."""
    return bool(np.allclose(matrix, np.eye(3), rtol=0.0, atol=atol))


def to_cv2_inverse(matrix: np.ndarray) -> np.ndarray:
    """2 × 3 matrix for ``cv2.warpAffine(..., flags=WARP_INVERSE_MAP)``.

    OpenCV puts pixel centres at integer coordinates; our matrices use pixel
    edges. The returned matrix maps an output pixel *index* to the input
    position it samples, in OpenCV's convention.
    """
    back = np.linalg.inv(np.asarray(matrix, dtype=float))
    half = _translation(0.5, 0.5)
    return (_translation(-0.5, -0.5) @ back @ half)[:2]


def integer_permutation(matrix: np.ndarray) -> np.ndarray | None:
    """The backward map as an integer 2 × 3 matrix when it permutes whole pixels.

    Returns
    -------
    numpy.ndarray or None
        Integer matrix ``B`` (index convention, as :func:`to_cv2_inverse`) when
        the linear part is a signed permutation (flips, multiples of 90°) and the
        translation is a whole number of pixels; such transforms need no
        interpolation and are done exactly by indexing. ``None`` otherwise.
    """
    b = to_cv2_inverse(matrix)
    r = np.rint(b)
    if not np.allclose(b, r, rtol=0.0, atol=1e-9):
        return None
    lin = r[:, :2]
    if not (np.abs(lin).sum(axis=0) == 1).all() or not (np.abs(lin).sum(axis=1) == 1).all():
        return None
    return r.astype(np.int64)


# --------------------------------------------------------------------------- boxes


@dataclass(frozen=True)
class Boxes:
    """Axis-aligned labelled boxes in pixel-edge coordinates.

    Attributes
    ----------
    class_id
        ``(n,)`` int64 class indexes (0 = cattle).
    xyxy_px
        ``(n, 4)`` float64 ``x0, y0, x1, y1``, pixels (x right, y down, edges).
    """

    class_id: np.ndarray
    xyxy_px: np.ndarray

    def __post_init__(self) -> None:
        cid = np.asarray(self.class_id, dtype=np.int64).reshape(-1)
        xyxy = np.asarray(self.xyxy_px, dtype=float).reshape(-1, 4)
        if cid.shape[0] != xyxy.shape[0]:
            raise ValueError(f"{cid.shape[0]} class ids for {xyxy.shape[0]} boxes")
        object.__setattr__(self, "class_id", cid)
        object.__setattr__(self, "xyxy_px", xyxy)

    def __len__(self) -> int:
        return int(self.class_id.shape[0])

    @classmethod
    def empty(cls) -> Boxes:
        """No boxes."""
        return cls(np.zeros(0, np.int64), np.zeros((0, 4)))

    @classmethod
    def from_yolo(cls, yolo: np.ndarray, shape: tuple[int, int]) -> Boxes:
        """From YOLO rows ``class cx cy w h`` normalised to an image of ``shape`` (rows, cols)."""
        arr = np.asarray(yolo, dtype=float).reshape(-1, 5)
        rows, cols = shape
        cx, cy = arr[:, 1] * cols, arr[:, 2] * rows
        hw, hh = arr[:, 3] * cols / 2, arr[:, 4] * rows / 2
        return cls(np.rint(arr[:, 0]).astype(np.int64),
                   np.stack([cx - hw, cy - hh, cx + hw, cy + hh], axis=1))

    def to_yolo(self, shape: tuple[int, int]) -> np.ndarray:
        """YOLO rows ``class cx cy w h`` normalised to an image of ``shape`` (rows, cols)."""
        rows, cols = shape
        x0, y0, x1, y1 = self.xyxy_px.T
        return np.stack([self.class_id.astype(float), (x0 + x1) / 2 / cols, (y0 + y1) / 2 / rows,
                         (x1 - x0) / cols, (y1 - y0) / rows], axis=1)


def _rect_polygons(xyxy: np.ndarray) -> np.ndarray:
    x0, y0, x1, y1 = np.asarray(xyxy, dtype=float).reshape(-1, 4).T
    return shapely.box(x0, y0, x1, y1, ccw=False) if x0.size else np.empty(0, dtype=object)


@dataclass(frozen=True)
class BoxTrack:
    """Boxes followed through a chain of geometric transforms of one image.

    Attributes
    ----------
    class_id
        ``(n,)`` class indexes.
    full
        ``(n,)`` shapely polygons: the whole object, never clipped, pixels.
    visible
        ``(n,)`` shapely geometries: the part inside the image after every
        resampling so far (parts that left the image do not come back, just as
        their pixels do not), pixels.
    """

    class_id: np.ndarray
    full: np.ndarray
    visible: np.ndarray

    @classmethod
    def from_boxes(cls, boxes: Boxes, shape: tuple[int, int]) -> BoxTrack:
        """Start tracking ``boxes`` on an image of ``shape`` (rows, cols)."""
        full = _rect_polygons(boxes.xyxy_px)
        return cls(boxes.class_id.copy(), full, _clip(full, shape))

    def map_points(self, func: Callable[[np.ndarray], np.ndarray], shape: tuple[int, int],
                   *, densify_px: float | None = None) -> BoxTrack:
        """Move every polygon vertex with ``func`` and clip the visible part to the image.

        Parameters
        ----------
        func
            Maps an ``(m, 2)`` array of input points (x, y), pixels, to output points.
        shape
            ``(rows, cols)`` of the output image, pixels.
        densify_px
            For non-affine maps: insert vertices so that no edge is longer than
            this (pixels) before mapping, so that curved images of edges are
            followed. ``None`` for affine maps (edges stay straight).
        """
        if len(self.class_id) == 0:
            return self
        full, visible = self.full, self.visible
        if densify_px is not None:
            full = shapely.segmentize(full, densify_px)
            visible = shapely.segmentize(visible, densify_px)
        full = shapely.transform(full, func)
        visible = _clip(shapely.transform(visible, func), shape)
        return BoxTrack(self.class_id, full, visible)

    def affine(self, matrix: np.ndarray, shape: tuple[int, int]) -> BoxTrack:
        """Apply a forward affine ``matrix`` (pixel edges) and clip to ``shape``."""
        m = np.asarray(matrix, dtype=float)
        lin, t = m[:2, :2], m[:2, 2]
        return self.map_points(lambda p: p @ lin.T + t, shape)

    def visible_fraction(self) -> np.ndarray:
        """``(n,)`` visible area over full area (0 for degenerate boxes)."""
        full = shapely.area(self.full)
        vis = shapely.area(self.visible)
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(full > 0, vis / np.where(full > 0, full, 1.0), 0.0)
        return np.clip(frac, 0.0, 1.0)

    def to_boxes(self, *, min_visible_fraction: float) -> tuple[Boxes, np.ndarray]:
        """Enclosing boxes of the visible parts, dropping barely visible ones.

        Parameters
        ----------
        min_visible_fraction
            Boxes whose visible area is below this fraction of their full area
            (dimensionless, 0–1) are dropped.

        Returns
        -------
        boxes
            The kept boxes, pixels.
        kept
            ``(n,)`` bool, which of the tracked boxes were kept.
        """
        if len(self.class_id) == 0:
            return Boxes.empty(), np.zeros(0, bool)
        frac = self.visible_fraction()
        kept = (frac >= min_visible_fraction) & (frac > 0) & ~shapely.is_empty(self.visible)
        bounds = shapely.bounds(self.visible[kept]).reshape(-1, 4)
        return Boxes(self.class_id[kept], bounds), kept


def _clip(geoms: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    rows, cols = shape
    if len(geoms) == 0:
        return geoms
    return shapely.clip_by_rect(geoms, 0.0, 0.0, float(cols), float(rows))
