"""Tables for people at any terminal width: a number is never split across lines, a header never wraps, text
(reasons, notes) wraps at word boundaries only. Columns are chosen by width: the optional ones go first, in the
order their priority says; when even the essential ones do not fit, each row is printed as a block of
``name: value`` lines (a vertical layout) instead of a table."""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

from rich import box
from rich.console import Console
from rich.table import Table
from rich.text import Text


@dataclass
class Col:
    name: str
    justify: str = "left"
    priority: int = 0  # 0: essential; higher numbers are dropped first when the table does not fit
    text: bool = False  # free text (a reason): wraps at words; every other column never wraps


def _table(title: str, cols: list[Col], rows: list[dict], style) -> Table:
    t = Table(title=title or None, title_justify="left", box=style, pad_edge=style is not box.SIMPLE_HEAD)
    for c in cols:
        t.add_column(c.name, justify=c.justify, no_wrap=not c.text, overflow="fold" if c.text else "ellipsis",
                     min_width=max((len(w) for w in c.name.split()), default=1) if c.text else None)
    for r in rows:
        t.add_row(*(str(r.get(c.name, "")) for c in cols))
    return t


def _needed(table: Table, cols: list[Col], rows: list[dict], title: str, style) -> int:
    """The narrowest width at which nothing is cut or split: every no-wrap cell (header included) at its full
    width, every text column at its longest word; measured by rendering that table unconstrained."""
    probe = []
    for r in rows:
        row = {}
        for c in cols:
            cell = Text.from_markup(str(r.get(c.name, ""))).plain
            row[c.name] = max(cell.split() or [""], key=len) if c.text else cell
        probe.append(row)
    wide = Console(width=100_000, file=_Null(), color_system=None, legacy_windows=False)
    with wide.capture() as cap:
        wide.print(_table("", cols, probe, style))
    return max((Text(line).cell_len for line in cap.get().splitlines()), default=0)


class _Null:
    def write(self, s: str) -> int:
        return len(s)

    def flush(self) -> None:
        pass


def _fits(con: Console, cols: list[Col], rows: list[dict], style) -> bool:
    return _needed(None, cols, rows, "", style) <= con.width


def print_table(con: Console, title: str, cols: list[Col], rows: list[dict], *, style=box.SIMPLE_HEAD,
                vertical_key: str | None = None) -> None:
    """Print ``rows`` (``{column name: cell text with rich markup}``) as a table that fits ``con.width``."""
    shown = list(cols)
    levels = sorted({c.priority for c in cols if c.priority}, reverse=True)
    while True:
        if _fits(con, shown, rows, style):
            con.print(_table(title, shown, rows, style))
            return
        if not levels:
            break
        level = levels.pop(0)
        shown = [c for c in shown if c.priority < level]
    print_vertical(con, title, cols, rows, key=vertical_key or cols[0].name)


def print_vertical(con: Console, title: str, cols: list[Col], rows: list[dict], *, key: str) -> None:
    """Each row as a block: its key on a line, then ``name: value`` per column, text wrapped at words."""
    if title:
        con.print(title)
    width = max(con.width, 20)
    label = max(len(c.name) for c in cols if c.name != key) if len(cols) > 1 else 0
    for r in rows:
        con.print(f"[bold]{r.get(key, '')}[/]", soft_wrap=True)
        for c in cols:
            if c.name == key:
                continue
            value = Text.from_markup(str(r.get(c.name, ""))).plain
            if not value:
                continue
            head = f"  {c.name:<{label}}  "
            lines = textwrap.wrap(value, max(width - len(head), 10), break_long_words=False,
                                  break_on_hyphens=False) or [""]
            con.print(head + lines[0], markup=False, highlight=False, soft_wrap=True)
            for line in lines[1:]:
                con.print(" " * len(head) + line, markup=False, highlight=False, soft_wrap=True)


def wrap_lines(text: str, width: int, indent: str = "  ", subsequent: str = "    ") -> list[str]:
    """``text`` wrapped at word boundaries (never mid-word) to ``width`` columns."""
    return textwrap.wrap(text, max(width, 20), initial_indent=indent, subsequent_indent=subsequent,
                         break_long_words=False, break_on_hyphens=False) or [indent]
