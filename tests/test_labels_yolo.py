"""YOLO text: parsing, validation errors naming file and line, formatting."""

from __future__ import annotations

import numpy as np
import pytest

from geosim.errors import GeosimError, LabelError
from geosim.labels.yolo import (
    format_yolo,
    parse_classes,
    parse_yolo,
    read_classes_file,
    read_yolo_file,
)

CLASSES = ("cattle",)


def test_parse_labelimg_output():
    # Exactly what LabelImg writes: six decimals, one box per line, trailing newline.
    text = "0 0.512500 0.250000 0.045000 0.020000\n0 0.100000 0.900000 0.040000 0.030000\n"
    labels = parse_yolo(text, source="PA1.txt", class_list=CLASSES)
    assert len(labels) == 2
    np.testing.assert_array_equal(labels.boxes[0], [0.5125, 0.25, 0.045, 0.02])
    assert labels.lines.tolist() == [1, 2]
    assert labels.class_names == ("cattle", "cattle")


def test_blank_lines_are_skipped_and_line_numbers_kept():
    text = "\n0 0.5 0.5 0.1 0.1\n\n0 0.2 0.2 0.1 0.1\n"
    labels = parse_yolo(text, source="x.txt", class_list=CLASSES)
    assert labels.lines.tolist() == [2, 4]


def test_empty_file_is_no_boxes():
    labels = parse_yolo("", source="x.txt", class_list=CLASSES)
    assert len(labels) == 0 and labels.boxes.shape == (0, 4)


def test_labelimg_classes_with_extra_names_are_fine_when_unused():
    # LabelImg writes its whole predefined class list into classes.txt.
    class_list = parse_classes("dog\ncattle\nperson\n", source="classes.txt")
    labels = parse_yolo("1 0.5 0.5 0.1 0.1\n", source="a.txt", class_list=class_list)
    assert labels.class_names == ("cattle",)
    assert labels.class_ids.tolist() == [1]


BAD_LINES = {
    "too few fields": ("0 0.5 0.5 0.1", "expected 5 fields"),
    "too many fields": ("0 0.5 0.5 0.1 0.1 0.93", "expected 5 fields"),
    "value above 1": ("0 1.2 0.5 0.1 0.1", "outside [0, 1]"),
    "value below 0": ("0 0.5 -0.1 0.1 0.1", "outside [0, 1]"),
    "not a number": ("0 0.5 abc 0.1 0.1", "not a number"),
    "nan": ("0 0.5 nan 0.1 0.1", "not a finite number"),
    "zero width": ("0 0.5 0.5 0 0.1", "zero or negative box size"),
    "negative height": ("0 0.5 0.5 0.1 -0.2", "outside [0, 1]"),
    "unknown class id": ("3 0.5 0.5 0.1 0.1", "unknown class 3"),
    "class not an integer": ("0.0 0.5 0.5 0.1 0.1", "not a whole number"),
    "box outside image (left)": ("0 0.02 0.5 0.1 0.1", "outside its image (left edge"),
    "box outside image (bottom)": ("0 0.5 0.97 0.1 0.1", "outside its image (bottom edge"),
}


@pytest.mark.parametrize("kind", sorted(BAD_LINES))
def test_each_malformed_kind_names_file_and_line(kind, tmp_path):
    bad, expected = BAD_LINES[kind]
    path = tmp_path / "PA1.txt"
    path.write_text(f"0 0.5 0.5 0.1 0.1\n0 0.3 0.3 0.1 0.1\n{bad}\n")
    with pytest.raises(LabelError) as info:
        read_yolo_file(path, class_list=CLASSES)
    msg = str(info.value)
    assert str(path) in msg
    assert "line 3" in msg
    assert expected in msg
    assert isinstance(info.value, GeosimError) and isinstance(info.value, ValueError)


def test_negative_size_in_range_is_refused():
    # A negative width is also a value below 0, but the message must still be clear.
    with pytest.raises(LabelError, match="line 1"):
        parse_yolo("0 0.5 0.5 -0.1 0.1", source="x.txt", class_list=CLASSES)


def test_class_name_not_known_is_an_error():
    with pytest.raises(LabelError, match=r"line 2: class 0 is 'dog'"):
        parse_yolo("\n0 0.5 0.5 0.1 0.1\n", source="x.txt", class_list=("dog",))


def test_counts_further_bad_lines():
    text = "0 2 0.5 0.1 0.1\n0 0.5 0.5 0.1 0.1\n9 0.5 0.5 0.1 0.1\n0 0.5\n"
    with pytest.raises(LabelError, match=r"line 1: .*\(2 more bad line"):
        parse_yolo(text, source="x.txt", class_list=CLASSES)


def test_box_touching_edge_with_labelimg_rounding_is_accepted():
    # Box from pixel 0 to 37 of a 3001-px-wide image, printed with six decimals.
    w = 37 / 3001
    line = f"0 {w / 2:.6f} 0.5 {w:.6f} 0.1"
    assert parse_yolo(line, source="x", class_list=CLASSES).boxes.shape == (1, 4)


def test_missing_classes_file(tmp_path):
    with pytest.raises(LabelError, match="classes.txt"):
        read_classes_file(tmp_path / "classes.txt")


def test_blank_line_inside_classes_is_an_error():
    with pytest.raises(LabelError, match="line 2"):
        parse_classes("cattle\n\nsheep\n", source="classes.txt")


def test_format_then_parse_reproduces_boxes():
    rng = np.random.default_rng(1)
    x0, y0 = rng.uniform(0, 0.8, (2, 50))
    w, h = rng.uniform(1e-3, 0.2, (2, 50))
    boxes = np.column_stack([x0 + w / 2, y0 + h / 2, w, h])
    text = format_yolo(np.zeros(50, dtype=int), boxes)
    back = parse_yolo(text, source="x", class_list=CLASSES)
    # Six decimals: each value within half a unit of the last digit.
    assert np.max(np.abs(back.boxes - boxes)) <= 5e-7 + 1e-12
    assert text.count("\n") == 50


def test_format_empty_is_empty_string():
    assert format_yolo(np.zeros(0, dtype=int), np.zeros((0, 4))) == ""


def test_format_refuses_invalid_boxes():
    with pytest.raises(ValueError):
        format_yolo(np.array([0]), np.array([[0.5, 0.5, 1.2, 0.1]]))
