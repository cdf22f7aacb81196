"""A composable, reproducible augmentation pipeline for aligned image pairs.

A pipeline is an ordered list of steps, each one of the twelve functions of
:mod:`geosim.augment.functions` with its parameters and the probability that it
is applied. It is described in TOML::

    [pipeline]
    min_visible_fraction = 0.5   # boxes less visible than this are dropped
    interpolation = "cubic"      # image resampling: cubic | linear | nearest
    reference_gsd_m = 0.05       # optional: lengths below are pixels at this GSD

    [[functions]]
    name = "rotate"
    probability = 0.5
    min_deg = -10.0
    max_deg = 10.0

Applying it to a pair draws every random number from one explicit
``numpy.random.Generator``, in step order, and returns the records of what was
drawn (which reproduce the output exactly, see :meth:`Pipeline.replay`).

Execution. Consecutive affine operations (rotate, shift, alignment, scale,
shear, mirror) are composed into one matrix and resampled once: one
interpolation instead of several, and content rotated out of the frame by one
step and back in by the next is not lost. An affine followed by a local warp is
resampled together with the warp, in one remap. Consecutive photometric
operations share one float32 working copy per row block, rounded back to the
image dtype once. The
valid-data mask follows with nearest-neighbour interpolation; pixels that come
from outside the image become invalid (and 0). Boxes move with the pixels (see
:class:`geosim.augment.geometry.BoxTrack`).
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Generator, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np

from geosim.augment import photometric as photo
from geosim.augment.functions import (
    FUNCTIONS,
    AffineOp,
    AugmentFunction,
    Op,
    PixelOp,
    WarpOp,
    hsv_op,
)
from geosim.augment.geometry import Boxes, BoxTrack, is_identity
from geosim.augment.resample import (
    INTERPOLATION,
    affine_resample_hwc,
    bands_last_view,
    interleave,
    permute_exact,
    remap_resample_hwc,
    zero_invalid,
)
from geosim.errors import ConfigError, InputFileError

__all__ = ["AugImage", "AugmentResult", "Pipeline", "AugmentStep", "default_config_path",
           "flatten_records", "load_pipeline"]

#: Longest box edge (pixels) between vertices inserted before a non-affine warp.
DENSIFY_PX = 1.0

#: Rows per block in photometric stages (bounded float32 working memory, cache-sized).
BLOCK_ROWS = 128

_T = TypeVar("_T")

_PIPELINE_KEYS = {"min_visible_fraction", "interpolation", "reference_gsd_m"}


@dataclass(frozen=True)
class AugImage:
    """One image of a pair with its valid-data mask and its boxes.

    Attributes
    ----------
    image
        ``(bands, rows, cols)`` pixel values (uint8, uint16, int16 or float32). It may be
        a view of a pixel-interleaved ``(rows, cols, bands)`` buffer
        (``np.moveaxis(hwc, -1, 0)``): tiles are read that way, the pipeline works in
        that layout and returns its images as such views, and the writers take them as
        they are (no layout pass anywhere between the file read and the file written).
    mask
        ``(rows, cols)`` bool, True where the data are valid.
    boxes
        Labelled boxes, pixel-edge coordinates of this image.
    """

    image: np.ndarray
    mask: np.ndarray
    boxes: Boxes = field(default_factory=Boxes.empty)

    def __post_init__(self) -> None:
        if self.image.ndim != 3:
            raise ValueError(f"image must be (bands, rows, cols), got {self.image.shape}")
        if self.mask.dtype != bool or self.mask.shape != self.image.shape[1:]:
            raise ValueError(f"mask must be bool {self.image.shape[1:]}, got "
                             f"{self.mask.dtype} {self.mask.shape}")

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, cols)``."""
        return self.mask.shape  # type: ignore[return-value]


@dataclass(frozen=True)
class AugmentStep:
    """One pipeline step: a function and the probability that it is applied."""

    function: AugmentFunction
    probability: float = 1.0


@dataclass(frozen=True)
class AugmentResult:
    """An augmented pair and how it was made.

    Attributes
    ----------
    a, b
        The augmented images (same shapes as the inputs).
    records
        One dict per step: ``step`` (index), ``function``, ``applied`` and, if
        applied, ``params`` (what was drawn; pixels of this image).
    chain_a, chain_b
        The resampling stages actually run on each image, in order: dicts with
        ``kind`` (``affine``, ``warp`` or ``photometric``), ``functions`` and,
        for affine stages, ``matrix_px`` (3 × 3 forward, pixel edges).
    dropped_a, dropped_b
        Number of boxes dropped (visible fraction below the threshold).
    """

    a: AugImage
    b: AugImage
    records: list[dict[str, Any]]
    chain_a: list[dict[str, Any]]
    chain_b: list[dict[str, Any]]
    dropped_a: int
    dropped_b: int

    @property
    def on_map_grid(self) -> tuple[bool, bool]:
        """Whether each output still sits on its source's pixel grid (no geometric stage)."""
        return (not any(s["kind"] != "photometric" for s in self.chain_a),
                not any(s["kind"] != "photometric" for s in self.chain_b))

    @staticmethod
    def pixel_to_source(chain: Sequence[Mapping[str, Any]]) -> np.ndarray | None:
        """Backward 3 × 3 matrix from output to source pixel-edge coordinates.

        ``None`` when a non-affine stage (local warp) was applied.
        """
        fwd = np.eye(3)
        for stage in chain:
            if stage["kind"] == "warp":
                return None
            if stage["kind"] == "affine":
                fwd = np.asarray(stage["matrix_px"]) @ fwd
        return np.linalg.inv(fwd)


@dataclass(frozen=True)
class Pipeline:
    """An ordered list of augmentation steps with the options that apply to all.

    Attributes
    ----------
    steps
        The steps in application order (a function may appear more than once).
    min_visible_fraction
        Boxes whose visible area falls below this fraction of the whole object
        are dropped (dimensionless, 0–1).
    interpolation
        Image resampling for geometric steps: ``cubic`` (default), ``linear``,
        ``nearest``. Masks always use nearest.
    reference_gsd_m
        If set, the pixel lengths of the steps are pixels at this GSD (metres)
        and are rescaled to the GSD of each image (see :meth:`length_scale`).
    """

    steps: tuple[AugmentStep, ...]
    min_visible_fraction: float = 0.5
    interpolation: str = "cubic"
    reference_gsd_m: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_visible_fraction <= 1.0:
            raise ConfigError(f"pipeline: min_visible_fraction = {self.min_visible_fraction} "
                              "must be in [0, 1]")
        if self.interpolation not in INTERPOLATION:
            raise ConfigError(f"pipeline: interpolation = {self.interpolation!r}; use one of "
                              f"{', '.join(INTERPOLATION)}")
        if self.reference_gsd_m is not None and not self.reference_gsd_m > 0:
            raise ConfigError(f"pipeline: reference_gsd_m = {self.reference_gsd_m} must be > 0")

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_dict(cls, config: Mapping[str, Any], *, source: str = "augmentation config"
                  ) -> Pipeline:
        """Build from a parsed TOML document; errors name ``source`` and the entry."""
        unknown = sorted(set(config) - {"pipeline", "functions"})
        if unknown:
            raise ConfigError(f"{source}: unknown table(s) {', '.join(unknown)}; "
                              "use [pipeline] and [[functions]]")
        opts = dict(config.get("pipeline", {}))
        bad = sorted(set(opts) - _PIPELINE_KEYS)
        if bad:
            raise ConfigError(f"{source}: unknown [pipeline] key(s) {', '.join(bad)}; known: "
                              f"{', '.join(sorted(_PIPELINE_KEYS))}")
        entries = config.get("functions", [])
        if not isinstance(entries, list):
            raise ConfigError(f"{source}: 'functions' must be an array of tables "
                              "([[functions]] entries)")
        steps = []
        for i, entry in enumerate(entries):
            where = f"{source}: functions[{i}]"
            if not isinstance(entry, Mapping) or "name" not in entry:
                raise ConfigError(f"{where}: each [[functions]] entry needs name = one of "
                                  f"{', '.join(FUNCTIONS)}")
            params = dict(entry)
            name = params.pop("name")
            if name not in FUNCTIONS:
                raise ConfigError(f"{where}: unknown function {name!r}; use one of "
                                  f"{', '.join(FUNCTIONS)}")
            prob = params.pop("probability", 1.0)
            if isinstance(prob, bool) or not isinstance(prob, int | float) or not (
                    0.0 <= prob <= 1.0):
                raise ConfigError(f"{where} ({name}): probability = {prob!r} must be a number "
                                  "in [0, 1]")
            try:
                fn = FUNCTIONS[name].from_params(params)
            except ConfigError as exc:
                raise ConfigError(f"{where}: {exc}") from None
            steps.append(AugmentStep(fn, float(prob)))
        try:
            return cls(tuple(steps), **opts)
        except ConfigError as exc:
            raise ConfigError(f"{source}: {exc}") from None
        except TypeError as exc:
            raise ConfigError(f"{source}: bad [pipeline] value ({exc})") from None

    @classmethod
    def from_toml(cls, path: str | os.PathLike[str]) -> Pipeline:
        """Read a pipeline TOML file (see the module docstring for the format)."""
        p = Path(path)
        if not p.is_file():
            raise InputFileError(f"augmentation config {p} does not exist; give a TOML file "
                                 f"(an example ships at {default_config_path()})")
        try:
            doc = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"augmentation config {p}: not valid TOML ({exc}); fix the "
                              "syntax") from exc
        return cls.from_dict(doc, source=f"augmentation config {p}")

    def to_dict(self) -> dict[str, Any]:
        """The configuration as a TOML-shaped dict (round-trips through :meth:`from_dict`)."""
        opts: dict[str, Any] = {"min_visible_fraction": self.min_visible_fraction,
                                "interpolation": self.interpolation}
        if self.reference_gsd_m is not None:
            opts["reference_gsd_m"] = self.reference_gsd_m
        return {"pipeline": opts,
                "functions": [{"name": s.function.name, "probability": s.probability,
                               **s.function.params()} for s in self.steps]}

    # ------------------------------------------------------------------ running

    def length_scale(self, gsd_m: float | None) -> float:
        """Image pixels per reference pixel: ``reference_gsd_m / gsd_m`` (1 if either unset)."""
        if self.reference_gsd_m is None or gsd_m is None:
            return 1.0
        return self.reference_gsd_m / gsd_m

    def record_columns(self) -> list[str]:
        """Flat column names of the records, ``NN_function.applied`` and ``NN_function.param``.

        Every record of this pipeline flattens (:func:`flatten_records`) into a
        subset of these columns; the structure of a function's draw does not
        depend on the values drawn, so one throw-away draw per step gives them.
        """
        cols: list[str] = []
        for i, step in enumerate(self.steps):
            rec = {"step": i, "function": step.function.name, "applied": True,
                   "params": step.function.draw(np.random.default_rng(0))}
            cols.extend(flatten_records([rec]))
        return cols

    def draw(self, rng: np.random.Generator, *, length_scale: float = 1.0
             ) -> list[dict[str, Any]]:
        """Draw the records of one application (see :attr:`AugmentResult.records`)."""
        records = []
        for i, step in enumerate(self.steps):
            applied = bool(rng.random() < step.probability)
            rec: dict[str, Any] = {"step": i, "function": step.function.name,
                                   "applied": applied}
            if applied:
                rec["params"] = step.function.draw(rng, length_scale=length_scale)
            records.append(rec)
        return records

    def apply(self, a: AugImage, b: AugImage, rng: np.random.Generator, *,
              length_scale: float = 1.0) -> AugmentResult:
        """Augment a pair: draw from ``rng``, then :meth:`replay`.

        Parameters
        ----------
        a, b
            The two images of the pair (same shape).
        rng
            The only source of randomness.
        length_scale
            Image pixels per reference pixel (:meth:`length_scale`).
        """
        return self.replay(a, b, self.draw(rng, length_scale=length_scale))

    def replay(self, a: AugImage, b: AugImage, records: Sequence[Mapping[str, Any]]
               ) -> AugmentResult:
        """Apply recorded draws to a pair (deterministic: same records, same output)."""
        if a.shape != b.shape:
            raise ValueError(f"the images of a pair must have the same shape; got {a.shape} "
                             f"and {b.shape}")
        if len(records) != len(self.steps):
            raise ValueError(f"{len(records)} records for {len(self.steps)} steps")
        ops_a: list[tuple[str, Op]] = []
        ops_b: list[tuple[str, Op]] = []
        for step, rec in zip(self.steps, records, strict=True):
            if not rec["applied"]:
                continue
            op_a, op_b = step.function.ops(rec["params"], a.shape)
            if op_a is not None:
                ops_a.append((step.function.name, op_a))
            if op_b is not None:
                ops_b.append((step.function.name, op_b))
        # The two images run in turn, photometric block by photometric block, so that the
        # pair's shared noise ("together": one seed) is drawn once per block for both.
        noise = photo.NoiseBlockCache()
        (out_a, chain_a, dropped_a), (out_b, chain_b, dropped_b) = _in_turn(
            _execute(a, ops_a, self.interpolation, self.min_visible_fraction, noise),
            _execute(b, ops_b, self.interpolation, self.min_visible_fraction, noise))
        return AugmentResult(out_a, out_b, [dict(r) for r in records], chain_a, chain_b,
                             dropped_a, dropped_b)


def _in_turn(*runs: Generator[None, None, _T]) -> list[_T]:
    """Advance generators one step each in turn until all are done; their return values."""
    results: list[Any] = [None] * len(runs)
    pending = dict(enumerate(runs))
    while pending:
        for i, run in list(pending.items()):
            try:
                next(run)
            except StopIteration as done:
                results[i] = done.value
                del pending[i]
    return results


def _execute(img: AugImage, ops: Iterable[tuple[str, Op]], interpolation: str,
             min_visible_fraction: float, noise: photo.NoiseBlockCache | None = None
             ) -> Generator[None, None, tuple[AugImage, list[dict[str, Any]], int]]:
    """Run one image's operations, fusing consecutive affine and photometric ones.

    A generator: it pauses after every block of a photometric stage (see
    :func:`_in_turn`) and returns ``(image, chain, dropped boxes)``; ``noise`` is the
    pair's :class:`~geosim.augment.photometric.NoiseBlockCache`.

    An image that is a view of a pixel-interleaved buffer is worked on in that layout
    (OpenCV's) from the start. A contiguous bands-first image is interleaved once, at the
    first stage that interpolates or changes values (exact pixel permutations, flips and
    quarter turns, before that run on the bands-first image). An interleaved result is
    returned as its ``(bands, rows, cols)`` view (no split pass).
    """
    ops = list(ops)
    mask = img.mask
    shape = img.shape
    track = BoxTrack.from_boxes(img.boxes, shape)
    dn_max = photo.dn_max_for(img.image.dtype)
    hwc = img.image  # bands-first until interleaved; never modified in place
    interleaved = False
    view = bands_last_view(img.image)
    if view is not None:
        hwc, interleaved = view, True
    chain: list[dict[str, Any]] = []
    affine = np.eye(3)
    affine_names: list[str] = []
    pixel_ops: list[tuple[str, PixelOp]] = []

    def to_interleaved() -> None:
        nonlocal hwc, interleaved
        if not interleaved:
            hwc, interleaved = interleave(hwc), True

    def flush_affine(pixel_stage_next: bool = False) -> None:
        nonlocal hwc, mask, track, affine, affine_names
        if affine_names and not is_identity(affine):
            exact = permute_exact(hwc, mask, affine, bands_last=interleaved)
            if exact is None:
                to_interleaved()
                # a photometric stage next zeroes invalid pixels itself (its ops are
                # pixel-wise: what lies under the mask never reaches a valid pixel)
                exact = affine_resample_hwc(hwc, mask, affine, interpolation=interpolation,
                                            zero=not pixel_stage_next)
            hwc, mask = exact
            track = track.affine(affine, shape)
            chain.append({"kind": "affine", "functions": affine_names,
                          "matrix_px": affine.tolist()})
        affine, affine_names = np.eye(3), []

    def flush_pixel() -> Generator[None, None, None]:
        nonlocal hwc, pixel_ops
        if pixel_ops:
            to_interleaved()
            hwc = yield from _photometric_blocks(hwc, mask, [op for _, op in pixel_ops],
                                                 dn_max, noise)
            chain.append({"kind": "photometric", "functions": [n for n, _ in pixel_ops]})
        pixel_ops = []

    for i, (name, op) in enumerate(ops):
        if isinstance(op, AffineOp):
            yield from flush_pixel()
            affine = op.matrix @ affine
            affine_names.append(name)
        elif isinstance(op, WarpOp):
            yield from flush_pixel()
            f = op.field
            pending = affine if affine_names and not is_identity(affine) else None
            if pending is not None:
                # the pending affine and the warp are resampled in one remap
                track = track.affine(pending, shape)
                chain.append({"kind": "affine", "functions": affine_names,
                              "matrix_px": pending.tolist(), "resampled_with_next_warp": True})
            affine, affine_names = np.eye(3), []
            to_interleaved()
            pixel_next = i + 1 < len(ops) and isinstance(ops[i + 1][1], PixelOp)
            hwc, mask = remap_resample_hwc(hwc, mask, f.u_px, f.v_px,
                                           interpolation=interpolation, matrix=pending,
                                           zero=not pixel_next)
            track = track.map_points(f.forward_points, shape, densify_px=DENSIFY_PX)
            chain.append({"kind": "warp", "functions": [name],
                          "max_px": f.max_px,
                          "max_gradient": f.max_gradient})
        else:
            flush_affine(pixel_stage_next=True)
            pixel_ops.append((name, op))
    flush_affine()
    yield from flush_pixel()
    # never hand back the caller's arrays
    if np.may_share_memory(hwc, img.image):
        hwc = hwc.copy()
    image = np.moveaxis(hwc, -1, 0) if interleaved else hwc
    mask = mask.copy() if mask is img.mask else mask
    boxes, kept = track.to_boxes(min_visible_fraction=min_visible_fraction)
    return AugImage(image, mask, boxes), chain, int((~kept).sum())


def _merge_hsv(ops: Sequence[PixelOp]) -> list[PixelOp]:
    """Fuse runs of HSV shifts acting on different channels into one colour-space round trip.

    Hue, saturation and value are separate HSV channels, so shifting them in one
    conversion equals shifting them one after the other (each is clipped on its own).
    """
    out: list[PixelOp] = []
    for op in ops:
        prev = out[-1] if out else None
        if (prev is not None and prev.hsv is not None and op.hsv is not None
                and not any(x and y for x, y in zip(prev.hsv, op.hsv, strict=True))):
            h, s, v = (x + y for x, y in zip(prev.hsv, op.hsv, strict=True))
            out[-1] = hsv_op(f"{prev.name}+{op.name}", h, s, v)
        else:
            out.append(op)
    return out


def _photometric_stage(hwc: np.ndarray, mask: np.ndarray, ops: Sequence[PixelOp],
                       dn_max: float) -> np.ndarray:
    """:func:`_photometric_blocks` run to the end on its own: the new image."""
    run = _photometric_blocks(hwc, mask, ops, dn_max)
    while True:
        try:
            next(run)
        except StopIteration as done:
            return done.value  # type: ignore[no-any-return]


def _photometric_blocks(hwc: np.ndarray, mask: np.ndarray, ops: Sequence[PixelOp],
                        dn_max: float, noise: photo.NoiseBlockCache | None = None
                        ) -> Generator[None, None, np.ndarray]:
    """Apply photometric ops in float32, row block by row block (bounded memory).

    A generator pausing after each block (the pipeline runs the pair's two images in
    turn, :func:`_in_turn`) and returning the new image; trailing noise goes through
    the pair's ``noise`` cache (the same values, drawn once for both images).

    ``hwc`` is the interleaved ``(rows, cols, bands)`` image. Each block is
    converted to float32 once, goes through every op (colour conversions and
    per-band arithmetic are single OpenCV passes on that layout) and is rounded
    back to the image dtype once. Each op with a seed gets one generator per image,
    consumed block after block in a fixed order, so the result does not depend on
    anything but the seeds. Invalid pixels are set to 0. Returns a new interleaved
    array.

    Passes that cannot change a value are skipped (the result is the same, bit for
    bit, as running every kernel in full; tested): a leading colour shift of a uint8
    image is its float32 look-up table, applied while converting (one ``cv2.LUT``
    instead of convert, add and clip; a colour shift alone is a uint8 table); an HSV
    shift does not re-clip a block that is already in range; the last op does not clip
    before a saturating conversion to uint8/uint16, and trailing noise is added, rounded
    and saturated into the output in one pass.
    """
    ops = _merge_hsv(ops)
    dtype = hwc.dtype
    bands = hwc.shape[-1]
    lut = None
    if ops[0].colour_dn is not None and dtype == np.uint8 and 2 <= bands <= 4:
        lut = photo.colour_lut(np.asarray(ops[0].colour_dn), bands, dn_max=dn_max)
        ops = ops[1:]
        if not ops:  # a colour shift alone: the rounded table, uint8 to uint8
            out = cv2.LUT(hwc, photo.from_work(lut, np.uint8))
            return zero_invalid(out, mask)
    rngs = [np.random.default_rng(op.seed) if op.seed is not None else None for op in ops]
    rows = hwc.shape[0]
    out = np.empty(hwc.shape, dtype)
    for r0 in range(0, rows, BLOCK_ROWS):
        block = slice(r0, min(rows, r0 + BLOCK_ROWS))
        _photometric_block(hwc[block], mask[block], out[block], ops, rngs, lut, dn_max, noise)
        yield
    return out


def _photometric_block(hwc: np.ndarray, mask: np.ndarray, out: np.ndarray,
                       ops: Sequence[PixelOp], rngs: Sequence[np.random.Generator | None],
                       lut: np.ndarray | None, dn_max: float,
                       noise: photo.NoiseBlockCache | None) -> None:
    """One row block of :func:`_photometric_blocks`, written into ``out``."""
    dtype = hwc.dtype
    saturating = photo.saturates_to_range(dtype)
    work = cv2.LUT(hwc, lut) if lut is not None else photo.to_work(hwc)
    in_range = saturating or lut is not None  # every kernel's result is clipped too
    written = False
    for i, (op, rng) in enumerate(zip(ops, rngs, strict=True)):
        last = i == len(ops) - 1
        if last and saturating and op.noise_sigma_dn is not None:
            photo.add_noise(work, sigma_dn=op.noise_sigma_dn, rng=rng, dn_max=dn_max,
                            out=out, cache=noise)
            written = True
        elif op.hsv is not None:
            h, s, v = op.hsv
            work = photo.hsv_shift(work, hue_deg=h, saturation_dn=s, value_dn=v,
                                   dn_max=dn_max, clip_input=not in_range,
                                   clip_output=not (last and saturating))
        else:
            work = op.func(work, dn_max, rng)
        in_range = True
    if not written:
        photo.from_work(work, dtype, out=out)
    zero_invalid(out, mask)  # while the block is in cache


def flatten_records(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Records as one flat dict: ``NN_function.applied`` and ``NN_function.param[.sub]``."""
    flat: dict[str, Any] = {}

    def walk(prefix: str, obj: Any) -> None:
        if isinstance(obj, Mapping):
            for k, v in obj.items():
                walk(f"{prefix}.{k}", v)
        else:
            flat[prefix] = obj

    for rec in records:
        base = f"{rec['step']:02d}_{rec['function']}"
        flat[f"{base}.applied"] = rec["applied"]
        if rec["applied"]:
            walk(base, rec["params"])
    return flat


def default_config_path() -> Path:
    """Path of the example pipeline shipped with geosim (``default_augment.toml``)."""
    return Path(str(resources.files("geosim.augment").joinpath("default_augment.toml")))


def load_pipeline(path: str | os.PathLike[str] | None = None) -> Pipeline:
    """Read a pipeline TOML; ``None`` reads the shipped example."""
    return Pipeline.from_toml(default_config_path() if path is None else path)
