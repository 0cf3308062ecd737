"""One declaration per command-line option, for both ways the station defines commands.

The hot commands of factory scripts (``station solve``, ``station fk``) are plain click commands: typer 0.29
converts every option value through a pydantic ``TypeAdapter`` built at parse time, which cost those commands
~0.2 s of cpu per call, more than the solve (bench/startup.py). The other commands stay typer. An
option both kinds use (``--model``, ``--tip-link`` ...) is declared once here as an :class:`Opt` and turned into
a ``click.Option`` (:meth:`Opt.click`) or a ``typer.Option`` default (:meth:`Opt.typer`); its help text exists once.

Help looks as typer prints it (``--model <str>  ...  [required]``), so the two kinds read alike.
"""

from __future__ import annotations

import inspect
from pathlib import Path

REQUIRED = ...  # the default of an option that must be given (typer's convention)
_METAVAR = {str: "<str>", float: "<float>", int: "<int>", Path: "<path>"}


class Opt:
    """``--flag`` with its parameter name, help, default (``REQUIRED``: must be given), value type and whether it
    repeats (then the value is a tuple, empty when not given). A plain class: a dataclass costs each command that
    imports it ~1 ms to build."""

    __slots__ = ("name", "flag", "help", "default", "kind", "multiple")

    def __init__(self, name: str, flag: str, help: str, default: object = None, kind: type = str,
                 multiple: bool = False) -> None:
        self.name, self.flag, self.help, self.default, self.kind, self.multiple = (name, flag, help, default, kind,
                                                                                  multiple)

    def __repr__(self) -> str:
        return f"Opt({self.flag})"

    def click(self):
        import click

        metavar = f"<list[{self.kind.__name__.lower()}]>" if self.multiple else _METAVAR[self.kind]
        kind = _PathType() if self.kind is Path else self.kind
        required = self.default is REQUIRED
        # no default at all when there is none: click >= 8.3 tells "not given" from an explicit None default
        default = {} if required or self.default is None else {"default": self.default, "show_default": True}
        return click.Option([self.flag, self.name], type=kind, multiple=self.multiple, required=required,
                            metavar=metavar, help=self.help, **default)

    def typer(self):
        import typer

        return typer.Option(self.default, self.flag, help=self.help)


def _PathType():
    """A file name as a ``Path``, unchecked (the command says what is wrong with the file, in one line): click's
    own ``click.Path`` would refuse an unreadable file with a message of its own."""
    import click

    class PathType(click.ParamType):
        name = "path"

        def convert(self, value, param, ctx):
            return value if isinstance(value, Path) else Path(value)

    return PathType()


def click_command(name: str, callback, options: list[Opt]):
    """A click command named ``name`` that calls ``callback(**options)``; its help is the callback's docstring."""
    import click

    return click.Command(name, callback=callback, params=[o.click() for o in options],
                         help=inspect.cleandoc(callback.__doc__ or ""))
