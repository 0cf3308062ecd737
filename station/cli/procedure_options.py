"""``station run``'s procedure flags, built from what the procedures declare (``station.engine.declare``): the
engine's plan options and every shipped procedure's ``@takes(...)``, each flag once. A value is read by its
declaration (one line naming the flag when it is wrong); a flag the named procedure does not take is refused.
``station run PROC --help`` shows PROC's options with their units and defaults and the measurements it declares."""

from __future__ import annotations

import contextvars
import functools
import inspect

import typer
import typer.main
from typer import _click as click
from typer.core import TyperCommand

from station.engine.declare import PLAN_OPTIONS, Option
from station.robot.errors import ConfigError

META = "station.run.procedure"  # where the command keeps the procedure named on the command line (for --help)
_OWN_GIVEN: contextvars.ContextVar[dict | None] = contextvars.ContextVar("station_run_own_options", default=None)


@functools.cache
def shipped_procedures() -> tuple:
    from station.engine.procedure import load_procedure, shipped_names

    return tuple(load_procedure(name) for name in shipped_names())


@functools.cache
def declared_flags() -> tuple[tuple[Option, tuple[str, ...]], ...]:
    """Every declared option (the engine's plan options first, then the shipped procedures' in their order) with
    the shipped procedures that take it. One flag is one declaration: two different ones are a defect."""
    seen: dict[str, tuple[Option, list[str]]] = {o.flag: (o, []) for o in PLAN_OPTIONS}
    for proc in shipped_procedures():
        for o in proc.options or ():
            if o.flag in seen and seen[o.flag][0] != o:
                raise ConfigError(f"procedure {proc.name}: {o.flag} is declared differently by another procedure; "
                                  "declare it once and share it")
            seen.setdefault(o.flag, (o, []))[1].append(proc.name)
    return tuple((o, tuple(names)) for o, names in seen.values())


def _help(o: Option, procedures: tuple[str, ...] | None = None) -> str:
    """The flag's help: what it is, its unit, which shipped procedures take it (when they are loaded anyway)."""
    unit = f" Unit: {o.unit}." if o.unit and o.unit != "count" else ""
    if procedures is None:
        return o.doc + unit
    others = [p.name for p in shipped_procedures() if p.name not in procedures]
    if not others:
        return o.doc + unit
    which = f"all but {', '.join(others)}" if len(others) < len(procedures) else ", ".join(procedures)
    return f"{o.doc}{unit} ({which})"


def with_declared_flags(fn):
    """``fn`` (a typer command taking ``**declared``) with one parameter per plan option (the engine's, taken by
    most procedures) before its last one; once: a command registered again keeps its parameters. A procedure's
    other flags are added when it is named (:class:`RunCommand`): no procedure is loaded to build the command."""
    if "__signature__" in fn.__dict__:
        return fn
    sig = inspect.signature(fn)
    params = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    last = params.pop()
    hints = dict(fn.__annotations__)
    for o in PLAN_OPTIONS:
        params.append(inspect.Parameter(o.param, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                        default=typer.Option(None, o.flag, help=_help(o)), annotation=o.kind.type))
        hints[o.param] = o.kind.type
    fn.__signature__ = sig.replace(parameters=[*params, last])
    fn.__annotations__ = hints
    return fn


def _option_of(param: str, procedure=None) -> tuple[int, Option]:
    """The declaration of a given parameter, with its place in the order values are read."""
    mine = list(procedure.options or ()) if procedure is not None and procedure.options is not None else []
    for k, o in enumerate(mine):
        if o.param == param:
            return k, o
    for k, o in enumerate(PLAN_OPTIONS):
        if o.param == param:
            return len(mine) + k, o
    for k, (o, _) in enumerate(declared_flags()):
        if o.param == param:
            return len(mine) + len(PLAN_OPTIONS) + k, o
    raise ConfigError(f"--{param.replace('_', '-')}: no procedure declares this option")


def read_options(given: dict, procedure=None) -> dict:
    """The session options of the declared flags given (``{param: value}``, None: not given), in declaration
    order (a value may depend on one read before it: ``--calibration`` on ``--payload``). ``procedure``: a
    ``Procedure`` whose declaration is held to (a flag it does not take: one line)."""
    takes = None if procedure is None or procedure.options is None else {o.flag for o in procedure.options}
    found = sorted((_option_of(k, procedure) + (v,) for k, v in given.items() if v is not None),
                   key=lambda t: t[0])
    out: dict = {}
    for _, o, value in found:
        if takes is not None and o.flag not in takes:
            their = ", ".join(sorted(takes)) or "none"
            raise ConfigError(f"{o.flag}: procedure {procedure.name} takes no {o.flag} (its options: {their})")
        out[o.name] = o.read(value, out)
    return out


def _params(options: list[tuple[Option, str]]) -> list:
    """Command-line parameters for ``(option, help)``, made the way typer makes the run's own (a typer option
    each, value type from the declaration)."""
    if not options:
        return []
    reserved = {"procedure", "robot", "serial", "limits", "db", "apply", "cell", "operator", "touch", "identify",
                "quiet"}
    clash = [o.flag for o, _ in options if o.param in reserved]
    if clash:
        raise ConfigError(f"option {clash[0]} is one of station run's own; a procedure declares another name")

    def declared(**given) -> None:
        """The declared options."""

    declared.__signature__ = inspect.Signature([inspect.Parameter(
        o.param, inspect.Parameter.KEYWORD_ONLY, annotation=o.kind.type, default=typer.Option(None, o.flag, help=h))
        for o, h in options])
    declared.__annotations__ = {o.param: o.kind.type for o, _ in options}
    scratch = typer.Typer(rich_markup_mode=None, add_completion=False)
    scratch.command()(declared)
    return list(typer.main.get_command(scratch).params)


def own_given() -> dict:
    """The values of the named procedure's own flags in the running ``station run`` (``{param: value}``)."""
    return dict(_OWN_GIVEN.get() or {})


def _named(command: RunCommand, args: list[str]) -> str | None:
    """The first positional argument (the procedure), skipping the values of options that take one (a flag the
    command does not have yet is a procedure's declared option: every one takes a value)."""
    flags = {name for p in command.params if getattr(p, "param_type_name", "") == "option"
             and (p.is_flag or p.count) for name in [*p.opts, *p.secondary_opts]}
    skip = False
    for a in args:
        if skip:
            skip = False
        elif a == "--":
            continue
        elif a.startswith("-"):
            skip = "=" not in a and a not in flags and a != "--help"
        else:
            return a
    return None


class RunCommand(TyperCommand):
    """``station run``: its own options and the plan's are the command's ``params``; the named procedure's other
    declared options become flags of its run (a shipped one's or a site's alike: only that procedure is loaded).
    Without a procedure, ``--help`` (and the docs: :meth:`documented`) list every shipped procedure's flags; with
    one, its options and measurements in sections of their own."""

    _every: list | None = None

    def every_param(self) -> list:
        """The command's parameters and every flag a shipped procedure declares (loads them all)."""
        if self._every is None:
            have = {o for p in self.params for o in getattr(p, "opts", ())}
            self._every = [*self.params, *_params([(o, _help(o, names)) for o, names in declared_flags()
                                                   if o.flag not in have])]
        return self._every

    def documented(self) -> RunCommand:
        """A copy whose ``params`` are :meth:`every_param` (docs/cli.md's reference is generated from it)."""
        import copy

        doc = copy.copy(self)
        doc.params = self.every_param()
        return doc

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[META] = _named(self, args)
        proc = self._procedure(ctx)
        if proc is not None and proc.options is not None and "--help" not in args:
            have = {o for p in self.get_params(ctx)
                    for o in [*getattr(p, "opts", ()), *getattr(p, "secondary_opts", ())]}
            unknown = next((a.split("=")[0] for a in args if a.startswith("--") and a.split("=")[0] not in have), None)
            if unknown is not None and unknown != "--":
                theirs = ", ".join(sorted(o.flag for o in proc.options)) or "none"
                raise ConfigError(f"{unknown}: procedure {proc.name} takes no {unknown} (its options: {theirs}; "
                                  "station run's own: station run --help)")
        return super().parse_args(ctx, args)

    def _procedure(self, ctx: click.Context):
        if META + ".loaded" not in ctx.meta:
            ctx.meta[META + ".loaded"] = _load(ctx.meta.get(META))
        return ctx.meta[META + ".loaded"]

    def _own(self, ctx: click.Context, proc) -> list:
        if META + ".own" not in ctx.meta:
            have = {o for p in self.params for o in getattr(p, "opts", ())}
            ctx.meta[META + ".own"] = _params([(o, _help(o)) for o in proc.options if o.flag not in have])
        return ctx.meta[META + ".own"]

    def get_params(self, ctx: click.Context) -> list:
        proc = self._procedure(ctx)
        helping = bool(ctx.meta.get(META + ".help"))
        if proc is None:
            params = self.every_param() if helping else self.params
        elif proc.options is None:  # a procedure that declares nothing: every flag, as before declarations
            params = self.every_param()
        elif helping:  # its options are listed in its own section, with their units and its defaults
            plan = {o.flag for o in PLAN_OPTIONS}
            params = [p for p in self.params if not set(getattr(p, "opts", ())) & plan]
        else:
            params = [*self.params, *self._own(ctx, proc)]
        help_option = self.get_help_option(ctx)
        return [*params, help_option] if help_option is not None else params

    def invoke(self, ctx: click.Context):
        # flags that are not parameters of the run function: handed over beside the call
        mine = {p.name for p in self.params}
        token = _OWN_GIVEN.set({k: ctx.params.pop(k) for k in list(ctx.params) if k not in mine})
        try:
            return super().invoke(ctx)
        finally:
            _OWN_GIVEN.reset(token)

    def format_help(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        ctx.meta[META + ".help"] = True
        super().format_help(ctx, formatter)
        proc = self._procedure(ctx)
        if proc is not None:
            procedure_help(proc, formatter)


def _load(name: str | None):
    if not name:
        return None
    from station.engine.procedure import load_procedure

    try:
        return load_procedure(name)
    except ConfigError:
        return None  # the run says what is wrong with it; the help stays the general one


def procedure_help(proc, formatter: click.HelpFormatter) -> None:
    """A procedure's declarations as help sections: its options (value, unit, default) and measurements."""
    with formatter.section(f"Procedure {proc.name}"):
        formatter.write_text(" ".join((proc.module.__doc__ or "").strip().split("\n\n")[0].split()))
    defaults = proc.defaults
    if proc.options is None:
        with formatter.section(f"Options of {proc.name}"):
            formatter.write_text("not declared: every option above is passed to it")
    elif proc.options:
        rows = [(f"{o.flag} <{o.kind.type.__name__.lower()}>",
                 f"{o.doc} {f'Unit: {o.unit}; d' if o.unit else 'D'}efault: {o.default_text(defaults)}.")
                for o in proc.options]
        with formatter.section(f"Options of {proc.name}"):
            formatter.write_dl(rows)
    if proc.measurements is not None:
        rows = [(m.name, f"[{m.unit}{', judged' if m.judged else ''}] {m.doc}") for m in proc.measurements]
        with formatter.section(f"Measurements of {proc.name} (judged: the limits file must give a limit)"):
            formatter.write_dl(rows)
