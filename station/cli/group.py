"""The typer group of the ``station`` command (``station.cli.app``): every command of ``station.cli.COMMANDS``,
imported when invoked. ``station.cli.main`` runs a click-defined command (solve, fk) without it."""

from __future__ import annotations

import typer
from typer import _click
from typer.core import TyperCommand

from station.cli import COMMANDS, load_commands
from station.cli.helpgroup import HelpGroup


class LazyGroup(HelpGroup):
    """The ``station`` group: lists COMMANDS from the table, imports a command's module when it is invoked."""

    def list_commands(self, ctx) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx, cmd_name: str):
        if cmd_name not in self.commands and cmd_name in COMMANDS:
            for name, command in load_commands(COMMANDS[cmd_name][0]).items():
                self.commands[name] = command if isinstance(command, _click.Command) else _Forward(command)
        return self.commands.get(cmd_name)

    def format_commands(self, ctx, formatter) -> None:
        # from the table: listing the commands imports none of their modules; whole first lines, wrapped
        with formatter.section("Commands"):
            formatter.write_dl([(n, h) for n, (_, h) in COMMANDS.items()])

    def resolve_command(self, ctx, args):
        try:
            return super().resolve_command(ctx, args)
        except Exception as e:  # a typo: the suggestion TyperGroup makes from the commands it holds, from all
            from difflib import get_close_matches

            matches = get_close_matches(args[0], list(COMMANDS)) if args and hasattr(e, "message") else []
            if matches and "Did you mean" not in e.message:
                e.message = f"{e.message.rstrip('.')}. Did you mean {', '.join(repr(m) for m in matches)}?"
            raise


class _Forward(TyperCommand):
    """A plain click command (another click than the one typer vendors) inside this group: its arguments are
    handed over unparsed. ``station.cli.main`` does not come here; ``app`` used directly (tests) does."""

    def __init__(self, command) -> None:
        super().__init__(command.name, help=command.help, add_help_option=False,
                         context_settings={"ignore_unknown_options": True, "allow_extra_args": True,
                                           "allow_interspersed_args": False})
        self.command = command

    def invoke(self, ctx):
        return self.command.main(list(ctx.args), prog_name=ctx.command_path, standalone_mode=False)


# rich_markup_mode=None: plain click help, so that no command imports rich unless it prints a rich table
app = typer.Typer(cls=LazyGroup, add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  rich_markup_mode=None)


@app.callback(help="Robot calibration station: jog, record, solve, verify, report, write back.")
def _station() -> None:
    pass
