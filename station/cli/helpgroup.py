"""One style for every ``--help``: a group lists each command with its whole first sentence (wrapped to the
terminal, never cut with "..."). Used by the ``station`` group and every typer sub-group (map, model, records,
mock, mock world)."""

from __future__ import annotations

from typer.core import TyperGroup


def first_sentence(text: str | None) -> str:
    """The first paragraph of a help text, one line (what a command list shows)."""
    para = (text or "").strip().split("\n\n")[0]
    return " ".join(para.split())


class HelpGroup(TyperGroup):
    def format_commands(self, ctx, formatter) -> None:
        rows = []
        for name in self.list_commands(ctx):
            cmd = self.get_command(ctx, name)
            if cmd is None or cmd.hidden:
                continue
            rows.append((name, first_sentence(cmd.short_help or cmd.help)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)
