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


def _help(o: Option, procedures: tuple[str, ...]) -> str:
    """The flag's help for every procedure: what it is, its unit, which shipped procedures take it."""
    every = [p.name for p in shipped_procedures()]
    others = [n for n in every if n not in procedures]
    unit = f" Unit: {o.unit}." if o.unit and o.unit != "count" else ""
    if not others:
        return o.doc + unit
    which = f"all but {', '.join(others)}" if len(others) < len(procedures) else ", ".join(procedures)
    return f"{o.doc}{unit} ({which})"


def with_declared_flags(fn):
    """``fn`` (a typer command taking ``**declared``) with one parameter per declared flag before its last one
    (once: a command registered again keeps its parameters)."""
    if "__signature__" in fn.__dict__:
        return fn
    sig = inspect.signature(fn)
    params = [p for p in sig.parameters.values() if p.kind is not inspect.Parameter.VAR_KEYWORD]
    last = params.pop()
    hints = dict(fn.__annotations__)
    for o, procedures in declared_flags():
        params.append(inspect.Parameter(o.param, inspect.Parameter.POSITIONAL_OR_KEYWORD,
                                        default=typer.Option(None, o.flag, help=_help(o, procedures)),
                                        annotation=o.kind.type))
        hints[o.param] = o.kind.type
    fn.__signature__ = sig.replace(parameters=[*params, last])
    fn.__annotations__ = hints
    return fn


def read_options(given: dict, procedure=None) -> dict:
    """The session options of the declared flags given (``{param: value}``, None: not given), in declaration
    order (a value may depend on one read before it: ``--calibration`` on ``--payload``). ``procedure``: a
    ``Procedure`` whose declaration is held to (a flag it does not take: one line)."""
    takes = None if procedure is None or procedure.options is None else {o.flag for o in procedure.options}
    out: dict = {}
    for o in _all_options(procedure):
        value = given.get(o.param)
        if value is None:
            continue
        if takes is not None and o.flag not in takes:
            their = ", ".join(sorted(takes)) or "none"
            raise ConfigError(f"{o.flag}: procedure {procedure.name} takes no {o.flag} (its options: {their})")
        out[o.name] = o.read(value, out)
    return out


def _all_options(procedure=None) -> list[Option]:
    """The declared flags of station run, then the options only ``procedure`` declares (a site's procedure)."""
    out = [o for o, _ in declared_flags()]
    known = {o.flag for o in out}
    return out + [o for o in (procedure.options or ()) if o.flag not in known] if procedure is not None else out


def _own_params(procedure) -> list:
    """Command-line parameters for the options only ``procedure`` declares (not a shipped procedure's flag), made
    the way the declared flags are (a typer option each)."""
    known = {o.flag for o, _ in declared_flags()}
    own = [o for o in procedure.options or () if o.flag not in known]
    if not own:
        return []
    reserved = {"procedure", "robot", "serial", "limits", "db", "apply", "cell", "operator", "touch", "identify",
                "quiet"}
    clash = [o.flag for o in own if o.param in reserved]
    if clash:
        raise ConfigError(f"procedure {procedure.name}: option {clash[0]} is one of station run's own")

    def own_options(**given) -> None:
        """The procedure's own options."""

    own_options.__signature__ = inspect.Signature([inspect.Parameter(
        o.param, inspect.Parameter.KEYWORD_ONLY, annotation=o.kind.type,
        default=typer.Option(None, o.flag, help=f"{o.doc} (procedure {procedure.name})")) for o in own])
    own_options.__annotations__ = {o.param: o.kind.type for o in own}
    scratch = typer.Typer(rich_markup_mode=None)
    scratch.command()(own_options)
    return list(typer.main.get_command(scratch).params)


def _is_option(param) -> bool:
    return getattr(param, "param_type_name", "") == "option"  # typer carries its own click: no isinstance


def _named(command: click.Command, args: list[str]) -> str | None:
    """The first positional argument (the procedure), skipping the values of options that take one."""
    takes_value = {name for p in command.params if _is_option(p) and not p.is_flag and not p.count
                   for name in p.opts}
    skip = False
    for a in args:
        if skip:
            skip = False
        elif a == "--":
            continue
        elif a.startswith("-"):
            skip = a in takes_value
        else:
            return a
    return None


class RunCommand(TyperCommand):
    """``station run``: a procedure of a site folder (or a file) may declare options of its own, which become flags
    of its run; with a procedure named, ``--help`` shows that procedure's options and measurements."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        ctx.meta[META] = _named(self, args)
        return super().parse_args(ctx, args)

    def _procedure(self, ctx: click.Context):
        if META + ".loaded" not in ctx.meta:
            ctx.meta[META + ".loaded"] = _load(ctx.meta.get(META))
        return ctx.meta[META + ".loaded"]

    def get_params(self, ctx: click.Context) -> list:
        """With a procedure named: its own flags added; for ``--help`` with a procedure that declares its options,
        the declared flags are listed in its own section (units, its defaults), not among the general ones."""
        params = super().get_params(ctx)
        proc = self._procedure(ctx)
        if proc is None or proc.options is None:
            return params
        if ctx.meta.get(META + ".help"):
            declared = {o.flag for o in _all_options(proc)}
            return [p for p in params if not (_is_option(p) and set(p.opts) & declared)]
        own = ctx.meta.setdefault(META + ".own", _own_params(proc))
        return [*params[:-1], *own, *params[-1:]]  # click's --help stays last

    def invoke(self, ctx: click.Context):
        # the procedure's own flags are not parameters of the run function: handed over beside the call
        own = {p.name for p in ctx.meta.get(META + ".own", ())}
        token = _OWN_GIVEN.set({k: ctx.params.pop(k) for k in list(ctx.params) if k in own})
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


def own_given() -> dict:
    """The values of the named procedure's own flags in the running ``station run`` (``{param: value}``)."""
    return dict(_OWN_GIVEN.get() or {})


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
