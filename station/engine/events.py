"""The journal's one schema: a typed record for every event a session journal holds (docs/formats.md, "Session
journal"). Producers (engine, procedures, jog UI) build these records; ``station.engine.journal`` writes them
and validates every line it reads back against them; consumers (session record, records, report, resume,
``samples.csv``) read them. One meaning per field; units SI; times are host ``time.time()`` seconds unless the
field says otherwise.

``station-journal/2`` is written. The format is versioned ``station-journal/MAJOR[.MINOR]``: a writer that only
adds fields (or event types) keeps the major version, and a reader of that major version keeps what it does not
know (an unknown field is carried in the event and written back as it was, never dropped, never checked);
a newer major version is refused in one line (:func:`check_format`). The fields a reader knows are checked
for type and range whatever version wrote them. ``station-journal/1`` files (before this schema) are
converted on read (:func:`upgrade_v1`). Pure Python (dataclasses), cheap to import."""

import math
import types
import typing
from dataclasses import MISSING, dataclass, field, fields
from typing import Any, ClassVar, Literal

FORMAT = "station-journal/2"
FORMAT_V1 = "station-journal/1"
FORMAT_NAME = "station-journal"
MAJOR = 2  # the major version this station reads and writes (and /1, converted)
UNITS = "SI (m, rad, s); t = host unix time"


class SchemaError(ValueError):
    """One field of one event is wrong: ``field`` names it (dotted path), the message says what is wrong."""

    def __init__(self, field_name: str, message: str) -> None:
        super().__init__(f"field {field_name}: {message}" if field_name else message)
        self.field = field_name
        self.problem = message


# ---- the records ------------------------------------------------------------------------------------------
@dataclass(kw_only=True)
class Event:
    """Fields every event has. ``seq`` and ``t`` are set by ``Journal.append`` (the order and host time of the
    append, not of anything the event describes); ``session`` is the session id the event belongs to."""

    TYPE: ClassVar[str] = ""
    seq: int = -1
    t: float | None = None
    session: str | None = None

    @property
    def type(self) -> str:
        return self.TYPE

    @property
    def unknown(self) -> dict:
        """Fields a newer writer of the same major version added, as read (kept and written back, unchecked)."""
        return self.__dict__.get("_unknown") or {}

    def to_dict(self) -> dict:
        """The JSON object of the journal line (``type`` first, then every field, then the fields this station
        does not know, as read; values are the event's own, not copies)."""
        out: dict[str, Any] = {"type": self.type}
        for name, _, _ in _spec(type(self))[1]:
            out[name] = getattr(self, name)
        out.update(self.unknown)
        return out

    # events also read like the plain dicts of journal /1, for scripts written against it (``sample["q"]``)
    def __getitem__(self, key: str):
        if key == "type":
            return self.type
        if key not in _field_names(type(self)):
            return self.unknown[key]
        return getattr(self, key)

    def get(self, key: str, default=None):
        try:
            return self[key]
        except KeyError:
            return default


@dataclass(kw_only=True)
class Header(Event):
    """Line 1 of every journal: what the session is, on which robot, with which procedure/limits/cell."""

    TYPE: ClassVar[str] = "header"
    format: str = FORMAT
    seq: int = 0
    t: float | None = None  # when the session was created
    session: str
    procedure: str  # procedure name ("jog" for a technician session, the script's name for a script)
    procedure_path: str | None = None  # where the file was (informative; None: nothing to resume)
    procedure_sha256: str | None = None  # resume finds the procedure by name and runs it only with this sha256
    procedure_version: str | None = None  # the file's VERSION (a shipped one: the station's version)
    procedure_title: str = ""
    mode: Literal["procedure", "script", "technician"] = "procedure"
    serial: str  # serial of the robot under calibration
    operator: str = ""
    station: str = ""  # host name of the station PC
    url: str = ""  # robot URL
    model: str = ""  # kinematic model name
    robot: dict = field(default_factory=dict)  # Identity as dict (vendor, model, serial, firmware, devices...)
    limits: dict | None = None  # {path, version, sha256} of the limits file
    cell: dict | None = None  # {path, model, tool, points: [...]} of the cell file
    options: dict = field(default_factory=dict)  # procedure options (n_fit, apply, touch, identify...)
    db: str | None = None  # records URL the session stores to (never with a password)
    versions: dict = field(default_factory=dict)
    units: str = UNITS


@dataclass(kw_only=True)
class Step(Event):
    """One step of a session (``station.engine.steps``): ``start`` with its arguments (``info``), then ``done`` or
    ``failed`` with its ``duration``; or ``skipped`` with the reason. Steps nest: the journal's order says which
    step ran inside which."""

    TYPE: ClassVar[str] = "step"
    name: str
    status: Literal["start", "done", "failed", "skipped"]
    error: str | None = None  # exception class name when failed
    message: str | None = None  # what went wrong when failed
    reason: str | None = None  # why it was skipped
    info: dict = field(default_factory=dict)  # the step's arguments (e.g. identify, the plan pose)
    duration: float | None = None  # s from start to done/failed (monotonic clock; t is host time)


@dataclass(kw_only=True)
class Identity(Event):
    TYPE: ClassVar[str] = "identity"
    robot: dict  # Identity as dict, as the robot reported it (serial adopted from the operator where allowed)


@dataclass(kw_only=True)
class State(Event):
    """The robot's state before motion: enabled, the device calibration it applies (SI), joint values (SI)."""

    TYPE: ClassVar[str] = "state"
    enabled: bool
    calibration: dict[str, float] | None = None
    q: list[float]


@dataclass(kw_only=True)
class Warn(Event):
    TYPE: ClassVar[str] = "warning"
    step: str | None = None
    message: str


@dataclass(kw_only=True)
class Plan(Event):
    TYPE: ClassVar[str] = "plan"
    plan: dict  # PosePlan.to_dict(): poses with joint values (SI), point labels, sets


@dataclass(kw_only=True)
class Sample(Event):
    """One touch: all joints read in one transaction while the tip was on reference ``point``."""

    TYPE: ClassVar[str] = "sample"
    point: str  # label of the reference point touched
    q: list[float]  # joint values, SI (rad; m for prismatic joints), as the device reported them
    raw: list = field(default_factory=list)  # the device's own numbers (ticks, counts, rad)
    raw_unit: str | None = None  # unit of raw: tick | count | rad
    t_read: float | None = None  # host time the joints were read (t is when the sample was journaled)
    t_device: float | None = None  # the device's own clock at the reading (s), where it has one
    measured: list[float] | None = None  # external instrument measurement of the tip [x, y, z], m
    measured_rotation: list[float] | None = None  # 6-DoF instrument: tool orientation, rotation vector, rad
    pose: int | None = None  # index in the pose plan (the jog UI numbers its touches)
    set: Literal["fit", "holdout"] = "fit"
    status: dict = field(default_factory=dict)  # touch indicator, forced record, enabled...

    @classmethod
    def from_snapshot(cls, snap, point: str, *, pose: int | None = None, set: str = "fit",  # noqa: A002
                      status: dict | None = None, reading=None, instrument: str | None = None,
                      measured=None) -> "Sample":
        """The one way a sample is built, whoever takes it (engine, procedures, jog UI): every joint of one
        reading ``snap`` (``station.robot.JointSnapshot``: ``q`` SI, ``raw`` and ``raw_unit`` as the device
        sent them, ``t`` host time of the reading, ``t_device``), the reference ``point``, the plan ``pose``
        and its ``set``, and what the taker knows about the touch in ``status`` (touch indicator, forced,
        compliant...). An instrument's 6-DoF ``reading`` (``station.instruments.PoseReading``: ``xyz`` m, ``rv``
        rad, its clock ``t``) of the instrument with serial ``instrument`` goes into ``measured`` and
        ``measured_rotation`` (``status`` names the instrument and its time); ``measured`` alone is a position
        [x, y, z] (m). Checked when it is journaled."""
        status = dict(status or {})
        rotation = None
        if reading is not None:
            measured, rotation = reading.xyz, reading.rv
            status = {"instrument": instrument, "t_instrument": reading.t, **status}
        return cls(point=point, q=_floats(snap.q), raw=list(snap.raw), raw_unit=snap.raw_unit, t_read=snap.t,
                   t_device=snap.t_device, measured=None if measured is None else _floats(measured),
                   measured_rotation=None if rotation is None else _floats(rotation), pose=pose, set=set,
                   status=status)


def _floats(v) -> list:
    """Plain floats of a vector (a numpy array, tuple or list); what is not a number is left for the schema
    check to name."""
    return [float(x) if isinstance(x, (int, float)) or hasattr(x, "__float__") else x for x in
            (v.tolist() if hasattr(v, "tolist") else v)]


@dataclass(kw_only=True)
class Discard(Event):
    """A recorded sample left out of solves and records (a retake or the technician's choice)."""

    TYPE: ClassVar[str] = "discard"
    sample: int  # seq of the discarded sample
    reason: str = ""


@dataclass(kw_only=True)
class Result(Event):
    TYPE: ClassVar[str] = "result"
    result: dict  # CalibrationResult.to_dict() (SI)


@dataclass(kw_only=True)
class Measurement(Event):
    """One measurement judged against its limit; ``value``, ``low``, ``high``, ``marginal_at`` are in ``unit``."""

    TYPE: ClassVar[str] = "measurement"
    name: str
    value: float | None = None
    unit: str = ""
    quantity: str = ""  # length | angle | number
    low: float | None = None
    high: float | None = None
    marginal_at: float | None = None
    marginal: bool = False
    passed: bool
    note: str | None = None


@dataclass(kw_only=True)
class Verdict(Event):
    TYPE: ClassVar[str] = "verdict"
    passed: bool | None  # None: no verdict possible (``status`` says why)
    status: str | None = None  # "NO LIMITS": nothing to judge against; never a pass
    measurements: list[dict] = field(default_factory=list)  # the measurement dicts (see Measurement)
    limits_version: str | None = None


WRITEBACK_PHASES = ("pre-image", "written", "verified", "failed", "exported", "unsupported")


@dataclass(kw_only=True)
class Writeback(Event):
    """One phase of a write-back of joint zero offsets (station.engine.writeback), all values SI.

    ``pre-image``: journaled (and backed up) before anything is written: ``before`` = what the device held,
    ``after`` = what is about to be written. ``written``: the device stored ``after`` and read it back within
    one encoder count (``readback``). ``failed``: the write or the read-back failed (``error``); the device may
    hold part of ``after``. ``verified``: a touch at a known pose with the new calibration (``check``).
    ``exported``: the controller keeps its calibration itself; ``files`` were written for the integrator.
    ``unsupported``: nothing to write on this robot (``note``)."""

    TYPE: ClassVar[str] = "writeback"
    phase: Literal["pre-image", "written", "verified", "failed", "exported", "unsupported"]
    kind: Literal["write", "restore"] = "write"  # restore: writing the pre-image back after a failed write
    before: dict[str, float] | None = None
    after: dict[str, float] | None = None
    readback: dict[str, float] | None = None
    applied: bool = False  # the device holds ``after`` (stored and read back)
    verified: bool = False  # the known-pose check after the write passed (a read-back alone is not a check)
    check: dict | None = None
    error: str | None = None
    backup: str | None = None  # calibration-backup.json holding the session's first pre-image
    files: list[str] = field(default_factory=list)
    note: str = ""


@dataclass(kw_only=True)
class Fault(Event):
    TYPE: ClassVar[str] = "fault"
    step: str | None = None  # the step (or UI action) that was running: approach/seat/record/leave in the pose loop
    error: str  # error class name
    message: str
    pose: int | None = None  # the plan pose being worked on, when the fault came in the pose loop
    teardown: list[str] = field(default_factory=list)  # what the safe-state teardown could not do


@dataclass(kw_only=True)
class Resume(Event):
    TYPE: ClassVar[str] = "resume"
    samples_kept: int
    events_before: int


@dataclass(kw_only=True)
class End(Event):
    """Last event of a session: ``completed`` (the checklist ran to its end), ``error`` or ``interrupted``."""

    TYPE: ClassVar[str] = "end"
    status: Literal["completed", "error", "interrupted"]
    passed: bool | None = None  # the verdict, None when there is none
    n_samples: int | None = None


@dataclass(kw_only=True, init=False)
class Custom(Event):
    """An event of a type this schema does not know (``s.event({"type": "my_check", ...})`` in a script): kept
    as written, its fields unchecked (they must not reuse a known type's name)."""

    TYPE: ClassVar[str] = ""
    data: dict = field(default_factory=dict)

    def __init__(self, type: str, data: dict | None = None, *, seq: int = -1, t: float | None = None,  # noqa: A002
                 session: str | None = None) -> None:
        self.custom_type, self.data = str(type), dict(data or {})
        self.seq, self.t, self.session = seq, t, session

    @property
    def type(self) -> str:
        return self.custom_type

    def to_dict(self) -> dict:
        return {"type": self.custom_type, "seq": self.seq, "t": self.t, "session": self.session, **self.data}

    def __getitem__(self, key: str):
        if key in ("type", "seq", "t", "session"):
            return getattr(self, "custom_type" if key == "type" else key)
        return self.data[key]


EVENT_TYPES: dict[str, type[Event]] = {c.TYPE: c for c in (
    Header, Step, Identity, State, Warn, Plan, Sample, Discard, Result, Measurement, Verdict, Writeback, Fault,
    Resume, End)}


# ---- building and checking --------------------------------------------------------------------------------
def from_dict(d: dict, *, strict: bool = True, keep_unknown: bool | None = None) -> Event:
    """The typed event of a journal object; every field this schema knows is checked (type, range, shapes).
    ``strict`` (how journal lines are read): every required field present, and fields this station does not
    know are kept as read (``event.unknown``: a newer writer of the same major version added them);
    otherwise (an event about to be appended) ``seq``/``t`` may be missing and an unknown field is an error (a
    producer's typo), unless ``keep_unknown``. Raises :class:`SchemaError` naming the field."""
    if type(d) is not dict:
        raise SchemaError("", f"expected a JSON object, got {type(d).__name__}")
    kind = d.get("type")
    if not isinstance(kind, str) or not kind:
        raise SchemaError("type", "missing (every event needs a type)")
    cls = EVENT_TYPES.get(kind)
    if cls is None:
        base = {k: _checker(tp)(d[k], k) for k, tp in (("seq", int), ("t", float | None), ("session", str | None))
                if k in d}
        return Custom(kind, {k: v for k, v in d.items() if k not in ("type", "seq", "t", "session")}, **base)
    names, spec = _spec(cls)
    unknown = None
    if len(d) > len(names) or any(k not in names for k in d):
        if not (strict if keep_unknown is None else keep_unknown):
            raise SchemaError(next(k for k in d if k not in names), f"unknown field of a {kind} event")
        unknown = {k: v for k, v in d.items() if k not in names}
    kw = {}
    for name, check, required in spec:
        if name in d:
            kw[name] = check(d[name], name)
        elif required or (strict and name in ("seq", "t") and cls is not Header):
            raise SchemaError(name, f"missing from a {kind} event")
    event = cls(**kw)
    deep = _DEEP_CHECKS.get(cls)
    if deep is not None:
        deep(event)
    if unknown:
        event.__dict__["_unknown"] = unknown
    return event


def check_format(value) -> int:
    """The major version of a journal's ``format`` (``station-journal/MAJOR`` or ``/MAJOR.MINOR``): 1 or 2.
    A newer major version, or anything else, raises :class:`SchemaError` (one line: what the file is, what
    this station reads)."""
    prefix = FORMAT_NAME + "/"
    text = value if isinstance(value, str) else ""
    major, _, minor = text[len(prefix):].partition(".")
    if not text.startswith(prefix) or not major.isdigit() or (minor and not minor.isdigit()) or \
            (major == "1" and minor):
        raise SchemaError("format", f"{str(value)[:40]!r} is not a {FORMAT} (or /1) journal")
    if int(major) > MAJOR:
        raise SchemaError("format", f"{text[:40]} is a newer major version than this station reads ({FORMAT} "
                                    "and older): update the station to read it")
    if int(major) < 1:
        raise SchemaError("format", f"{text[:40]} is not a {FORMAT} (or /1) journal")
    return int(major)


# ---- what a field's annotation cannot say: the shapes inside a plan, bounds of joint values -------------------
MAX_JOINTS = 64
MAX_JOINT_VALUE = 1000.0  # rad or m: no joint turns 160 times or travels a kilometre; larger is a damaged file
_POSE_FIELDS = {"index": int, "point": str, "q": list[float], "approach_q": list[float],
                "set": Literal["fit", "holdout"], "via": list[list[float]]}
_POSE_REQUIRED = ("index", "point", "q", "approach_q")


def _joint_values(v: list[float], where: str, n: int | None = None) -> int:
    """``v`` (already a list of finite floats) is a joint vector: 1..MAX_JOINTS values within bounds, ``n`` long."""
    if not 1 <= len(v) <= MAX_JOINTS or (n is not None and len(v) != n):
        want = f"{n}" if n is not None else f"1 to {MAX_JOINTS}"
        raise SchemaError(where, f"expected {want} joint values, got {len(v)}")
    for i, x in enumerate(v):
        if abs(x) > MAX_JOINT_VALUE:
            raise SchemaError(f"{where}[{i}]", f"{x:g} is beyond any joint (|value| <= {MAX_JOINT_VALUE:g} rad or m)")
    return len(v)


def _check_plan(e: Plan) -> None:
    plan = e.plan
    if not isinstance(plan.get("poses"), list) or not plan["poses"]:
        raise SchemaError("plan.poses", "expected a list of planned poses")
    if not isinstance(plan.get("settings", {}), dict):
        raise SchemaError("plan.settings", "expected an object")
    # fields of a plan or a planned pose this station does not know stay in the dict, unchecked (a newer writer
    # of the same major version); PosePlan.from_dict takes only the ones it knows
    n = None
    for i, pose in enumerate(plan["poses"]):
        w = f"plan.poses[{i}]"
        if type(pose) is not dict:
            _fail(w, "an object", pose)
        for k in _POSE_REQUIRED:
            if k not in pose:
                raise SchemaError(f"{w}.{k}", "missing from a planned pose")
        checked = {k: _checker(tp)(pose[k], f"{w}.{k}") for k, tp in _POSE_FIELDS.items() if k in pose}
        if checked["index"] < 0 or not checked["point"]:
            raise SchemaError(f"{w}.{'index' if checked['index'] < 0 else 'point'}", "expected a pose index >= 0 "
                              "and a point label")
        n = _joint_values(checked["q"], f"{w}.q", n)
        _joint_values(checked["approach_q"], f"{w}.approach_q", n)
        for j, via in enumerate(checked.get("via", [])):
            _joint_values(via, f"{w}.via[{j}]", n)
        pose.update(checked)


def _check_sample(e: Sample) -> None:
    _joint_values(e.q, "q")
    for name in ("measured", "measured_rotation"):
        v = getattr(e, name)
        if v is not None and len(v) != 3:
            raise SchemaError(name, f"expected [x, y, z], got {len(v)} values")
        if v is not None and any(abs(x) > 1e6 for x in v):
            raise SchemaError(name, "beyond any instrument's range (|value| <= 1e6 m or rad)")


_PARAMETER_FIELDS = {"value": float | None, "std": float | None, "identifiable": bool, "kind": str,
                     "nominal": float | None, "unit": str}


def _check_result(e: Result) -> None:
    """The fields of a solve result that records and reports build on (each parameter's value, std, kind);
    the rest (residuals, notes, settings) is report material and passes through."""
    if "parameters" not in e.result:  # a solve that failed records its error only
        return
    params = e.result["parameters"]
    if type(params) is not dict:
        _fail("result.parameters", "an object of parameters", params)
    for name, p in params.items():
        w = f"result.parameters.{name!r}"
        if type(p) is not dict:
            _fail(w, "an object", p)
        if "value" not in p or "identifiable" not in p:
            raise SchemaError(w, "expected its value and identifiable")
        p.update({k: _checker(tp)(p[k], f"{w}.{k}") for k, tp in _PARAMETER_FIELDS.items() if k in p})


_DEEP_CHECKS = {Plan: _check_plan, Sample: _check_sample, Result: _check_result}


def make(event: "Event | dict") -> Event:
    """A typed, checked event from a producer (an Event or a dict). Numpy values become plain numbers and NaN/inf
    become null (JSON has neither), so a field that may be null takes them and a required number refuses them.
    A dict with a field the schema does not know is refused (a producer's typo); an event read from a journal
    keeps the unknown fields it was read with."""
    if isinstance(event, Custom):
        if event.type in EVENT_TYPES:
            raise SchemaError("type", f"{event.type!r} is a known event type; build it as such")
        return Custom(event.type, _plain(event.data), seq=event.seq, t=event.t, session=event.session)
    if isinstance(event, Event):
        return from_dict(_plain(event.to_dict()), strict=False, keep_unknown=bool(event.unknown))
    return from_dict(_plain(event), strict=False)


_SPECS: dict[type, tuple[frozenset, tuple]] = {}
_CHECKERS: dict = {}


def _spec(cls) -> tuple[frozenset, tuple]:
    """(field names incl. ``type``, ((name, checker, required), ...)) of an event class, built once."""
    if cls not in _SPECS:
        hints = typing.get_type_hints(cls)
        fs = fields(cls)
        _SPECS[cls] = (frozenset(["type", *(f.name for f in fs)]),
                       tuple((f.name, _checker(hints[f.name]), f.default is MISSING and f.default_factory is MISSING)
                             for f in fs))
    return _SPECS[cls]


def _field_names(cls) -> frozenset:
    return _spec(cls)[0] - {"type"}


def _checker(tp):
    """``check(value, where) -> value`` for annotation ``tp``, compiled once per annotation: returns the value
    normalised (ints as floats where floats are due), raises SchemaError naming ``where``."""
    c = _CHECKERS.get(tp)
    if c is None:
        c = _CHECKERS[tp] = _compile(tp)
    return c


def _fail(where: str, what: str, v):
    raise SchemaError(where, f"expected {what}, got {_got(v)}")


def _number(v, where):
    t = type(v)
    if t is float:
        if math.isfinite(v):
            return v
        raise SchemaError(where, f"not a finite number ({v})")
    if t is int:
        return float(v)
    _fail(where, "a number", v)


def _integer(v, where):
    if type(v) is int:
        return v
    if type(v) is float and v.is_integer():
        return int(v)
    _fail(where, "an integer", v)


def _boolean(v, where):
    if type(v) is bool:
        return v
    _fail(where, "true or false", v)


def _text(v, where):
    if type(v) is str:
        return v
    _fail(where, "text", v)


# exact types only: JSON's true is not the number 1, and 1 is not the text "1"
_SCALAR_CHECKS = {float: _number, int: _integer, bool: _boolean, str: _text}


def _union_check(tp):
    """``A | B | None``: null where allowed, else the first member that accepts the value."""
    args = typing.get_args(tp)
    nullable = type(None) in args
    rest = [_checker(a) for a in args if a is not type(None)]
    if len(rest) == 1:
        inner = rest[0]
        return (lambda v, where: None if v is None else inner(v, where)) if nullable else inner

    def union(v, where):
        if v is None and nullable:
            return None
        for c in rest:
            try:
                return c(v, where)
            except SchemaError:
                pass
        _fail(where, _name(tp), v)
    return union


def _literal_check(tp):
    allowed = typing.get_args(tp)

    def literal(v, where):
        if type(v) is str and v in allowed:
            return v
        raise SchemaError(where, f"{v!r} is not one of {', '.join(map(str, allowed))}")
    return literal


def _mapping_check(tp, origin):
    """``dict`` (any object) or ``dict[str, T]`` (every value checked, named ``where.key``)."""
    inner = _checker(typing.get_args(tp)[1]) if origin is dict else None

    def mapping(v, where):
        if type(v) is not dict:
            _fail(where, "an object", v)
        if inner is None:
            return v
        return {str(k): inner(x, f"{where}.{k}") for k, x in v.items()}
    return mapping


def _sequence_check(tp, origin):
    """``list`` or ``list[T]`` (every item checked; an error names the item's index)."""
    inner = _checker(typing.get_args(tp)[0]) if origin is list else None

    def sequence(v, where):
        if type(v) is not list and type(v) is not tuple:
            _fail(where, "a list", v)
        if inner is None:
            return list(v)
        try:
            return [inner(x, where) for x in v]
        except SchemaError:  # again, naming the element (errors are rare: no index strings on the way)
            return [inner(x, f"{where}[{i}]") for i, x in enumerate(v)]
    return sequence


def _compile(tp):
    if tp is Any:
        return lambda v, where: v
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return _union_check(tp)
    if origin is Literal:
        return _literal_check(tp)
    if tp in _SCALAR_CHECKS:
        return _SCALAR_CHECKS[tp]
    if tp is dict or origin is dict:
        return _mapping_check(tp, origin)
    if tp is list or origin is list:
        return _sequence_check(tp, origin)
    raise TypeError(f"events: no check for {tp!r}")  # a schema bug, not bad data


def _name(tp) -> str:
    return str(tp).replace("typing.", "").replace("NoneType", "null")


def _got(v) -> str:
    if v is None:
        return "null"
    text = repr(v)
    return f"{type(v).__name__} {text[:40]}{'...' if len(text) > 40 else ''}"


_SCALARS = (str, int, bool, type(None))


def _plain(obj):
    """JSON-safe copy: numpy scalars/arrays to Python; NaN/inf become null (JSON has no NaN: a value that does
    not exist, such as the position of a point the data could not see, is stored as null)."""
    t = type(obj)
    if t is float:
        return obj if math.isfinite(obj) else None
    if t in _SCALARS:
        return obj
    if t is dict:
        return {str(k): _plain(v) for k, v in obj.items()}
    if t is list or t is tuple:
        return [_plain(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if hasattr(obj, "tolist"):  # numpy array or scalar
        return _plain(obj.tolist())
    if isinstance(obj, float):
        return float(obj) if math.isfinite(obj) else None
    return obj


# ---- station-journal/1 -> /2 ------------------------------------------------------------------------------
_WB_PHASE_V1 = {"before": "pre-image", "written": "written", "verified": "verified", "exported": "exported",
                "unsupported": "unsupported"}
_V1_DROPPED_HEADER = ("started", "t_created", "units")


def upgrade_v1(d: dict) -> dict:
    """A ``station-journal/1`` object as ``/2`` writes it. /1 had two writers that disagreed: the engine wrote a
    sample's reading time as ``t_read`` (``t`` = append time), the jog UI as ``t``; the engine journaled
    write-backs with ``phase`` (before/written/verified), the jog UI with ``stage`` (pre-image/failed/done,
    ``verified`` meaning "read back"); the jog header's ``station`` was a dict (host, robot URL, options)."""
    d = dict(d)
    kind = d.get("type")
    if kind == "header":
        d["format"] = FORMAT
        st = d.get("station")
        if isinstance(st, dict):  # jog UI: {host, robot_url, identify, reference}
            d["station"] = str(st.get("host") or "")
            d.setdefault("url", str(st.get("robot_url") or ""))
            d["options"] = {**{k: v for k, v in st.items() if k not in ("host", "robot_url")},
                            **(d.get("options") or {})}
        if d.get("mode") not in ("procedure", "script", "technician"):
            d["mode"] = "procedure" if d.get("procedure_path") else "script"
        if d.get("procedure") == "jog":
            d["mode"] = "technician"
        for k in _V1_DROPPED_HEADER:
            d.pop(k, None)
        d["units"] = UNITS
        return _known_only(d, Header)
    if kind == "sample" and "t_read" not in d:
        d["t_read"] = d.get("t")  # the jog UI wrote the reading time as t
    elif kind == "step":
        info = {k: v for k, v in d.items() if k not in _field_names(Step) and k != "type"}
        d = {k: v for k, v in d.items() if k not in info}
        d["info"] = {**info, **(d.get("info") or {})}
        if d.get("status") == "ok":
            d["status"] = "done"
    elif kind == "writeback":
        if "stage" in d:  # jog UI
            stage = d.pop("stage")
            d["kind"] = "restore" if "restore" in str(d.get("note") or "") else "write"
            if stage == "done":
                ok = bool(d.get("verified"))
                d["phase"], d["applied"] = ("written", True) if ok else ("failed", False)
                if not ok:
                    d.setdefault("error", "the read-back differs from what was written")
                d["verified"] = False  # /1's verified was the read-back; no known-pose check was made
            else:
                d["phase"] = stage
        else:
            d["phase"] = _WB_PHASE_V1.get(d.get("phase"), d.get("phase"))
    elif kind == "end" and d.get("status") not in ("completed", "error", "interrupted"):
        d["status"] = "error"
    cls = EVENT_TYPES.get(kind)
    return _known_only(d, cls) if cls is not None else d


def _known_only(d: dict, cls) -> dict:
    names = _field_names(cls)
    return {k: v for k, v in d.items() if k == "type" or k in names}
