"""What a procedure declares: the measurements it takes and the options it accepts, on its ``checklist`` the way
OpenHTF declares measurements on a phase (``@htf.measures(...)``) and a driver declares its URL options
(``station.robot.url.Option``)::

    from station.engine.declare import PLAN_OPTIONS, SOLVE, measures, takes

    @measures(*SOLVE, judged=("samples", "fit_rms", "holdout_rms"))
    @takes(*PLAN_OPTIONS)
    def checklist(s): ...

A measurement states its name, the unit it is shown and judged in, what it is, and whether the limits file must
judge it (``judged``): when the procedure is run, every section of the limits file for it is checked against the
declaration before the robot is opened (``station.engine.limits.check_limits``: a judged measurement without a
limit, a limit for a measurement the procedure does not take, a limit in a unit of another quantity are each one
line). A session refuses to journal a measurement its procedure did not declare.

An option states its command-line flag, the session option it sets, what values it accepts (a :class:`Kind`: its
form in words and its reading, one line naming the flag for a bad value) and its unit; its default is the
procedure's ``DEFAULTS`` (or the engine's, said in ``default_doc``). ``station run`` builds its flags from the
options of the shipped procedures and ``station run PROC --help`` lists PROC's (docs/procedures.md)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

from station import units
from station.robot.errors import ConfigError


@dataclass(frozen=True)
class Measurement:
    name: str
    unit: str  # the unit it is shown and judged in (station.units: mm, deg, count, ...)
    doc: str
    # the limits file must give it a limit: the figure a verdict means nothing without (every other declared
    # measurement is judged where the file gives it a limit, informational where not)
    judged: bool = False

    @property
    def quantity(self) -> str:
        return units.quantity_of(self.unit)


@dataclass(frozen=True)
class Kind:
    """The values an option accepts: ``form`` in words (help and messages), the command-line type, and
    ``read(value, flag, options)`` -> the session option's value (``options``: the ones read before it); a
    ``ValueError`` becomes one line naming the flag and the form, a ``ConfigError`` is passed on as it is.

    ``valid(value)`` says whether a session value (what ``read`` gives, as the journal keeps it) is one of this
    kind, ``stored`` its form in words where that is not ``form``: a resume holds the journal's options to them (a
    journal is data: it may be damaged). ``valid`` None: not checked."""

    form: str
    type: type
    read: Callable[[Any, str, dict], Any]
    valid: Callable[[Any], bool] | None = None
    stored: str | None = None

    @property
    def stored_form(self) -> str:
        return self.stored or self.form


@dataclass(frozen=True)
class Option:
    name: str  # the session option (``s.options[name]``), journaled
    flag: str  # the command-line flag (``--grid``)
    kind: Kind
    doc: str
    unit: str | None = None  # the unit of a bare value (a value may carry its own where the kind says so)
    default_doc: str | None = None  # the default when the procedure's DEFAULTS have none (the engine's)

    @property
    def param(self) -> str:
        """The command-line parameter's Python name (``--span-deg`` -> ``span_deg``)."""
        return self.flag.removeprefix("--").replace("-", "_")

    def read(self, value, options: dict | None = None):
        """The option value of a command-line ``value``; one line naming the flag when it is not one."""
        flag = self.flag or self.name  # a setting has no flag
        try:
            return self.kind.read(value, flag, options or {})
        except ConfigError:
            raise
        except (ValueError, TypeError, OverflowError):
            raise ConfigError(f"{flag} {value!r}: expected {self.kind.form}") from None

    def holds(self, value) -> bool:
        """Whether ``value`` is a session value of this option (``Kind.valid``; True where the kind has none)."""
        return self.kind.valid is None or bool(self.kind.valid(value))

    def default_text(self, defaults: dict) -> str:
        if self.name in defaults:
            value = defaults[self.name]
            return f"{value:g}" if isinstance(value, float) else str(value)
        return self.default_doc or "none"


# ---- option kinds -----------------------------------------------------------------------------------------
def is_number(v, lo: float, hi: float, open_low: bool = False) -> bool:
    """A JSON number (not a bool) in ``[lo, hi]`` (``(lo, hi]`` with ``open_low``)."""
    return (type(v) in (int, float) and math.isfinite(v) and (lo < v if open_low else lo <= v) and v <= hi)


def count(lo: int, hi: int, form: str | None = None) -> Kind:
    def read(v, flag, options):
        if isinstance(v, bool) or int(v) != v or not lo <= int(v) <= hi:
            raise ValueError
        return int(v)
    return Kind(form or f"an integer {lo}..{hi}", int, read, lambda v: type(v) is int and lo <= v <= hi,
                f"an integer {lo}..{hi}")


def angle(lo: float, hi: float, bare: str, example: str, what: str = "an angle") -> Kind:
    """An angle in ``(lo, hi]`` of ``bare`` (``50deg``, ``0.87rad``; a bare number is ``bare``), in ``bare``."""
    def read(v, flag, options):
        from station.quantity import parse_option

        x = parse_option(v, flag, "angle", bare, example)
        if not lo < x <= hi:
            raise ConfigError(f"{flag} {v!r}: expected {what} in ({lo:g}, {hi:g}] {bare}, e.g. {example}")
        return x
    return Kind(f"{what} in ({lo:g}, {hi:g}] {bare}, e.g. {example} (a bare number is {bare})", str, read,
                lambda v: is_number(v, lo, hi, open_low=True), f"{what} in ({lo:g}, {hi:g}] {bare}")


def number(lo: float, hi: float, unit: str, open_low: bool = False) -> Kind:
    """A plain number of ``unit`` in ``[lo, hi]`` (``(lo, hi]`` with ``open_low``): a setting's kind."""
    def read(v, flag, options):
        x = float(v)
        if not is_number(x, lo, hi, open_low):
            raise ValueError
        return x
    span = f"{'(' if open_low else '['}{lo:g}, {hi:g}]"
    return Kind(f"{unit} in {span}", float, read, lambda v: is_number(v, lo, hi, open_low))


def choice(*words: str) -> Kind:
    def read(v, flag, options):
        if v not in words:
            raise ValueError
        return v
    return Kind("one of " + ", ".join(words), str, read, lambda v: type(v) is str and v in words)


def url(example: str) -> Kind:
    def read(v, flag, options):
        if "://" not in str(v) or len(str(v)) >= 1000:
            raise ValueError
        return str(v)
    return Kind(f"a URL, e.g. {example}", str, read, lambda v: type(v) is str and "://" in v and len(v) < 1000,
                "a URL")


def switch() -> Kind:
    """On or off (a flag without a value: ``--apply``)."""
    def read(v, flag, options):
        if type(v) is not bool:
            raise ValueError
        return v
    return Kind("true or false", bool, read, lambda v: type(v) is bool)


def seed_kind() -> Kind:
    return count(0, 2**63 - 1, "a non-negative integer")


# ---- the engine's own options and measurements -------------------------------------------------------------
# what Session.plan reads: a procedure that plans poses takes these (``station run --poses`` ...)
POSES = Option("n_fit", "--poses", count(1, 100_000, "a pose count of at least 1 (and at least the unknowns)"),
               "Number of fit poses.", "count", "from the plan: enough for the unknowns")
HOLDOUT = Option("n_holdout", "--holdout", count(0, 100_000, "a pose count of 0 or more"),
                 "Number of held-out poses.", "count", "4")
CONE = Option("cone_deg", "--cone", angle(0, 90, "deg", "50deg", "a half-angle"), "Half-angle of the cone of tool "
              "directions around each point, an angle: 50deg, 0.87rad (a bare number is degrees).", "deg", "35")
SEED = Option("seed", "--seed", seed_kind(), "Seed of the pose plan.", None, "0")
REFERENCE = Option("reference", "--reference", choice("unknown", "cell"), "Reference: unknown (solve the point) or "
                   "cell (use the cell file's surveyed positions).", None, "unknown")
PLAN_OPTIONS = (POSES, HOLDOUT, CONE, SEED, REFERENCE)

# the session options the engine itself reads besides the plan's: station run's own --touch and --apply, and the
# settings of the pose plan a caller may give in ``options=`` (no flag); held to on a resume like every option
TOUCH = Option("touch", "--touch", choice("seat", "guarded", "manual"), "How the tool meets a point: seat (socket), "
               "guarded (contact input) or manual.")
APPLY = Option("apply", "--apply", switch(), "Write identified joint offsets back (two-phase).")
SESSION_OPTIONS = (
    TOUCH, APPLY,
    Option("roll_deg", "", number(0, 360, "degrees"), "Half-range of the tool's roll about its axis over the plan.",
           "deg"),
    Option("margin_deg", "", number(0, 90, "degrees"), "How far inside each joint limit the planned poses stay.",
           "deg"),
    Option("clearance", "", number(0, 1, "metres"), "Stand-off along a point's approach direction the tool backs "
           "away to.", "m"),
    Option("plan_noise_m", "", number(0, 0.01, "metres", open_low=True), "The touch noise the plan-time check "
           "assumes.", "m"),
)

# what Session.measure_result measures after a solve
SOLVE = (
    Measurement("samples", "count", "samples the solve used (fit and held out)"),
    Measurement("fit_rms", "mm", "RMS residual of the fit"),
    Measurement("fit_max", "mm", "largest residual of the fit"),
    Measurement("identified", "count", "model parameters the data identified"),
    Measurement("holdout_rms", "mm", "RMS residual of the held-out samples"),
    Measurement("holdout_max", "mm", "largest residual of the held-out samples"),
    Measurement("offset_abs_max", "deg", "largest identified joint zero offset (revolute joints)"),
    Measurement("offset_std_max", "deg", "largest standard deviation of an identified joint zero (revolute joints)"),
)
# what the write-back's check touch measures (station.engine.writeback: only with --apply)
WRITE_BACK = (Measurement("writeback_check", "mm", "after the write-back: distance of the check touch from the solved "
                          "reference (default limit: 3 x fit_rms)"),)
# what Session.measure_consistency measures (no solve)
CONSISTENCY = (
    Measurement("samples", "count", "touches recorded"),
    Measurement("verify_rms", "mm", "RMS distance of the tip positions from their point's centroid"),
    Measurement("verify_max", "mm", "largest distance of a tip position from its point's centroid"),
)


# ---- the declarations on a checklist ------------------------------------------------------------------------
def measures(*measurements: Measurement, judged: Iterable[str] = ()):
    """Declare what ``checklist`` measures; ``judged``: names among them the limits file must judge."""
    judged = set(judged)
    names = [m.name for m in measurements]
    dup = sorted({n for n in names if names.count(n) > 1})
    unknown = sorted(judged - set(names))
    if dup or unknown:
        raise ConfigError(f"measures(): {'measured twice: ' + ', '.join(dup) if dup else ''}"
                          f"{'judged but not measured: ' + ', '.join(unknown) if unknown else ''}")
    declared = tuple(replace(m, judged=True) if m.name in judged else m for m in measurements)

    def attach(fn):
        fn.measurements = declared
        return fn
    return attach


def takes(*options: Option, settings: Iterable[Option] = ()):
    """Declare the options ``checklist`` takes (each flag once); ``settings``: the session options it reads that
    have no flag (set by its ``DEFAULTS`` or a caller's ``options=``), declared so a resume checks them too."""
    flags = [o.flag for o in options]
    dup = sorted({f for f in flags if flags.count(f) > 1})
    if dup:
        raise ConfigError(f"takes(): option {', '.join(dup)} declared twice")
    settings = tuple(settings)
    if any(o.flag for o in settings) or not all(o.flag for o in options):
        raise ConfigError("takes(): an option has a flag, a setting has none")

    def attach(fn):
        fn.options = tuple(options)
        fn.settings = settings
        return fn
    return attach


def declared_measurements(checklist) -> tuple[Measurement, ...] | None:
    """What a checklist declares it measures; None: it declares nothing (a procedure written before
    declarations: nothing is checked)."""
    return getattr(checklist, "measurements", None)


def declared_options(checklist) -> tuple[Option, ...] | None:
    return getattr(checklist, "options", None)


def session_options(checklist) -> dict[str, Option]:
    """Every declaration a session value of ``checklist`` is held to, by option name: the engine's own, the plan's,
    then the checklist's options and settings (a procedure's own declaration of a name wins)."""
    mine = (*(declared_options(checklist) or ()), *getattr(checklist, "settings", ()))
    return {o.name: o for o in (*SESSION_OPTIONS, *PLAN_OPTIONS, *mine)}
