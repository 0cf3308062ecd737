"""``station.cli.tables``: tables that fit any terminal width: numbers whole, optional columns dropped first,
a vertical layout when even the essential ones do not fit, text wrapped at words."""

from __future__ import annotations

import io

import pytest
from rich.console import Console

from station.cli.tables import Col, print_table, wrap_lines

COLS = [Col("parameter"), Col("value", "right"), Col("std", "right"), Col("note", priority=2),
        Col("reason", text=True, priority=1)]
ROWS = [{"parameter": "offset.j2", "value": "0.123456789", "std": "0.000012345", "note": "moved since last run",
         "reason": "a rotation about joint 1 moves the unknown point the same way"},
        {"parameter": "dh.j3.a", "value": "-425.000001", "std": "0.0031", "note": "", "reason": ""}]
NUMBERS = ["0.123456789", "0.000012345", "-425.000001", "0.0031"]


def render(width: int) -> list[str]:
    out = io.StringIO()
    print_table(Console(file=out, width=width, color_system=None), "Parameters", COLS, ROWS)
    return out.getvalue().splitlines()


@pytest.mark.parametrize("width", [200, 90, 60, 30])
def test_every_width_keeps_numbers_whole_and_lines_inside(width):
    lines = render(width)
    assert all(len(line) <= width for line in lines), lines
    text = "\n".join(lines)
    for n in NUMBERS:
        assert n in text, (width, n, text)  # on one line: never split


def test_optional_columns_go_first_then_the_vertical_layout():
    wide, mid, narrow = render(200), render(60), render(30)
    assert any("note" in x and "reason" in x for x in wide)
    head = next(x for x in mid if "parameter" in x)
    assert "note" not in head and "value" in head  # the priority-2 column went before the text
    assert narrow[0] == "Parameters" and narrow[1] == "offset.j2"  # each row a block
    assert any(x.strip().startswith("value") and x.strip().endswith("0.123456789") for x in narrow)


def test_wrap_lines_at_words():
    lines = wrap_lines("a rotation about joint 1 moves the unknown point the same way", 24)
    assert all(len(x) <= 24 for x in lines) and " ".join(x.strip() for x in lines).startswith("a rotation about")
    assert wrap_lines("x" * 40, 20) == ["  " + "x" * 40]  # a word longer than the line is never cut
