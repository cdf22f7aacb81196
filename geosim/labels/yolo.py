"""YOLO label text: parse, validate and format.

A YOLO label file has one box per line, ``class cx cy w h``: an integer class
index into ``classes.txt`` and the box centre and size normalised to the width
and height of the image it labels (so every value is in [0, 1]). This is what
LabelImg writes (with six decimals) and what the paper's labels use.

Everything here is pure (text in, arrays out) except :func:`read_yolo_file`
and :func:`read_classes_file`, thin readers that only add the file name to
messages.

References
----------
LabelImg, https://github.com/tzutalin/labelImg (YOLO writer: ``yolo_io.py``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geosim.errors import InputFileError, LabelError

#: The project's classes; the index is the YOLO class id written in our outputs.
CLASS_NAMES: tuple[str, ...] = ("cattle",)

#: Slack (normalised units) when testing that a box lies inside its image. LabelImg
#: prints cx and w with six decimals, so an edge computed as cx - w/2 may be off by
#: up to 7.5e-7 for a box that touches the image edge.
EDGE_TOLERANCE = 1e-6

_FIX = "fix or delete that line (a YOLO line is 'class cx cy w h', each value normalised to [0, 1])"


@dataclass(frozen=True)
class YoloLabels:
    """The boxes of one YOLO file.

    Attributes
    ----------
    source
        Where the boxes came from (a file path, used in messages and attributes).
    class_ids
        ``(n,)`` int, index into the file's class list.
    class_names
        ``(n,)`` the class name of each box (from the file's class list).
    boxes
        ``(n, 4)`` float64 ``cx, cy, w, h`` normalised to image width/height (dimensionless).
    lines
        ``(n,)`` int, 1-based line number of each box in ``source``.
    """

    source: str
    class_ids: np.ndarray
    class_names: tuple[str, ...]
    boxes: np.ndarray
    lines: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.boxes.shape[0])


def _problem(source: str, line_no: int, what: str) -> str:
    return f"{source}: line {line_no}: {what}; {_FIX}"


def _check_line(fields: list[str], class_list: Sequence[str], known: Sequence[str],
                ) -> tuple[int, list[float]] | str:
    """Validate one split line; return ``(class_id, [cx, cy, w, h])`` or a problem text."""
    if len(fields) != 5:
        return f"expected 5 fields (class cx cy w h), found {len(fields)}"
    try:
        class_id = int(fields[0])
    except ValueError:
        return f"class {fields[0]!r} is not a whole number (class index into classes.txt)"
    if not 0 <= class_id < len(class_list):
        return (f"unknown class {class_id}: the class list has {len(class_list)} "
                f"entr{'y' if len(class_list) == 1 else 'ies'} ({', '.join(class_list)})")
    if class_list[class_id] not in known:
        return (f"class {class_id} is {class_list[class_id]!r}, which is not a known class "
                f"(known: {', '.join(known)})")
    values: list[float] = []
    for name, text in zip(("cx", "cy", "w", "h"), fields[1:], strict=True):
        try:
            value = float(text)
        except ValueError:
            return f"{name} = {text!r} is not a number"
        if not math.isfinite(value):
            return f"{name} = {text!r} is not a finite number"
        if not 0.0 <= value <= 1.0:
            return f"{name} = {text} is outside [0, 1] (values are normalised to the image)"
        values.append(value)
    cx, cy, w, h = values
    if w <= 0.0 or h <= 0.0:
        return f"zero or negative box size (w = {fields[3]}, h = {fields[4]})"
    edges = {"left": cx - w / 2, "top": cy - h / 2, "right": cx + w / 2, "bottom": cy + h / 2}
    for side, value in edges.items():
        outside = value < -EDGE_TOLERANCE if side in ("left", "top") else (
            value > 1.0 + EDGE_TOLERANCE)
        if outside:
            return (f"box extends outside its image ({side} edge at {value:.6g} of the image "
                    f"{'width' if side in ('left', 'right') else 'height'})")
    return class_id, values


def parse_yolo(text: str, *, source: str, class_list: Sequence[str],
               known_classes: Sequence[str] = CLASS_NAMES) -> YoloLabels:
    """Parse and validate YOLO label text.

    Parameters
    ----------
    text
        File contents. Blank lines are ignored; every other line is one box.
    source
        Name of the file (used in error messages and kept in the result).
    class_list
        Class names indexed by class id (the lines of ``classes.txt``).
    known_classes
        Class names this project accepts; a box whose class is not one of them is
        an error (a LabelImg ``classes.txt`` may list more classes than are used).

    Returns
    -------
    YoloLabels

    Raises
    ------
    LabelError
        For the first malformed line (wrong field count, a value outside [0, 1] or
        not a number, zero or negative size, unknown class, box outside its image),
        naming the file and line and how many further lines are bad.
    """
    problems: list[str] = []
    ids: list[int] = []
    vals: list[list[float]] = []
    lines: list[int] = []
    for line_no, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        checked = _check_line(fields, class_list, known_classes)
        if isinstance(checked, str):
            problems.append(_problem(source, line_no, checked))
            continue
        ids.append(checked[0])
        vals.append(checked[1])
        lines.append(line_no)
    if problems:
        more = f" ({len(problems) - 1} more bad line(s) in this file)" if len(problems) > 1 else ""
        raise LabelError(problems[0] + more)
    class_ids = np.asarray(ids, dtype=np.int64)
    return YoloLabels(
        source=source,
        class_ids=class_ids,
        class_names=tuple(class_list[i] for i in ids),
        boxes=np.asarray(vals, dtype=np.float64).reshape(-1, 4),
        lines=np.asarray(lines, dtype=np.int64),
    )


def parse_classes(text: str, *, source: str) -> tuple[str, ...]:
    """Parse a ``classes.txt`` (one class name per line; the line index is the class id).

    Blank lines at the end are ignored; a blank line in the middle is an error
    because it would shift every later class id.
    """
    names = [line.strip() for line in text.splitlines()]
    while names and not names[-1]:
        names.pop()
    for i, name in enumerate(names, start=1):
        if not name:
            raise LabelError(f"{source}: line {i}: empty class name; class ids are line "
                             "numbers, so remove the blank line or name the class")
    if not names:
        raise LabelError(f"{source}: no class names; write one class per line "
                         f"(this project uses: {', '.join(CLASS_NAMES)})")
    return tuple(names)


def read_classes_file(path: str | os.PathLike[str]) -> tuple[str, ...]:
    """Read a LabelImg ``classes.txt``."""
    p = Path(path)
    if not p.is_file():
        raise LabelError(f"{p}: classes.txt not found; a YOLO label folder (LabelImg layout) "
                         "needs classes.txt with one class name per line, e.g. 'cattle'")
    return parse_classes(p.read_text(encoding="utf-8-sig"), source=str(p))


def read_yolo_file(path: str | os.PathLike[str], *, class_list: Sequence[str],
                   known_classes: Sequence[str] = CLASS_NAMES) -> YoloLabels:
    """Read and validate one YOLO label file (see :func:`parse_yolo`)."""
    p = Path(path)
    if not p.is_file():
        raise InputFileError(f"{p}: YOLO label file not found; check the labels path")
    try:
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise LabelError(f"{p}: not a text file ({exc.reason}); YOLO labels are plain text "
                         "lines 'class cx cy w h'") from exc
    return parse_yolo(text, source=str(p), class_list=class_list, known_classes=known_classes)


def format_yolo(class_ids: np.ndarray, boxes: np.ndarray, *, decimals: int = 6) -> str:
    """Format boxes as YOLO text.

    Parameters
    ----------
    class_ids
        ``(n,)`` integer class ids.
    boxes
        ``(n, 4)`` ``cx, cy, w, h`` normalised to the image (dimensionless, in [0, 1]).
    decimals
        Digits after the decimal point. Six (LabelImg's choice) is 0.005 px on a
        5000 px tile.

    Returns
    -------
    str
        One line per box, each ending in a newline; ``""`` for no boxes (YOLO's
        convention for an image without objects).

    Raises
    ------
    ValueError
        If a box is not a valid YOLO box (caller bug: boxes are clipped before this).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    class_ids = np.asarray(class_ids).reshape(-1)
    if class_ids.shape[0] != boxes.shape[0]:
        raise ValueError("class_ids and boxes differ in length")
    if boxes.size and (not np.all(np.isfinite(boxes)) or boxes.min() < 0 or boxes.max() > 1
                       or (boxes[:, 2:] <= 0).any()):
        raise ValueError("boxes must be finite, in [0, 1] and of positive size")
    # A size that would print as zero is printed as one unit of the last digit.
    boxes = boxes.copy()
    boxes[:, 2:] = np.maximum(boxes[:, 2:], 10.0 ** -decimals)
    fmt = f"{{:d}} {{:.{decimals}f}} {{:.{decimals}f}} {{:.{decimals}f}} {{:.{decimals}f}}\n"
    return "".join(fmt.format(int(c), *b) for c, b in zip(class_ids, boxes, strict=True))
