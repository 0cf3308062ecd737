"""Strict schemas for the station's files (pydantic v2), and their errors as one line
``FILE:LINE: FIELD: what is wrong``.

Every reader declares the shape of its format as ``Strict`` models: unknown keys are refused (``alfa:`` is not
``alpha``), numbers must be numbers (``true`` is not 1, ``"1"`` is not 1), finite and within ``ABSURD`` of zero
in the file's units. ``check`` validates parsed data (a ``station.yamlfile.YamlDoc`` carries the lines) and raises
the reader's own error class. Pure: no I/O."""

from __future__ import annotations

import math
from typing import Annotated, Any, get_args

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from station.yamlfile import YamlDoc, dotted

ABSURD = 1e9  # no length, angle, time or mass in any unit the station accepts is this large


class Strict(BaseModel):
    """A format's mapping: unknown keys refused, no type coercion, no NaN/Infinity."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, frozen=True)


Num = Annotated[float, Field(ge=-ABSURD, le=ABSURD)]
NonNeg = Annotated[float, Field(ge=0, le=ABSURD)]
Pos = Annotated[float, Field(gt=0, le=ABSURD)]
Vec3 = Annotated[list[Num], Field(min_length=3, max_length=3)]  # strict mode: a YAML list is not a tuple
Pair = Annotated[list[Num], Field(min_length=2, max_length=2)]
Text = Annotated[str, Field(max_length=10_000)]
Name = Annotated[str, Field(min_length=1, max_length=200)]


def _short(v: Any) -> str:
    r = repr(v)
    return r if len(r) <= 40 else r[:37] + "..."


def _number_message(kind: str, v: Any, err: dict, field: str) -> str | None:
    """What is wrong with a number: not one, not finite, absurd (a unit slip), of the wrong sign."""
    if isinstance(v, bool) and kind in ("float_type", "int_type", "greater_than", "less_than_equal"):
        return f"expected a number, got {v!r} (a boolean is not a number)"
    if kind in ("float_type", "int_type"):
        if isinstance(v, int):  # an integer too large for a float
            return "number out of range"
        return f"expected a number, got {_short(v)}"
    if kind == "finite_number":
        return f"not a finite number ({_short(v)})"
    if kind in ("greater_than_equal", "less_than_equal") and isinstance(v, float | int) and abs(v) > ABSURD:
        return f"absurd value {v:g} (beyond ±{ABSURD:g}); wrong units?"
    if kind == "greater_than_equal" and err.get("ctx", {}).get("ge") == 0:
        return f"a {field} cannot be negative, got {_short(v)}" if field == "mass" else \
            f"must not be negative, got {_short(v)}"
    if kind == "greater_than" and err.get("ctx", {}).get("gt") == 0:
        return f"must be positive, got {_short(v)}"
    return None


def _shape_message(kind: str, v: Any, err: dict) -> str | None:
    """What is wrong with a container or a choice: a mapping or list expected, a wrong length, not a choice."""
    if kind in ("dict_type", "model_type"):
        return f"expected a mapping, got {_short(v)}"
    if kind in ("list_type", "tuple_type"):
        return f"expected a list, got {_short(v)}"
    ctx = err.get("ctx", {})
    sizes = (ctx.get("min_length"), ctx.get("max_length"))
    if kind in ("too_short", "too_long") and isinstance(v, list) and 3 in sizes:
        return f"expected [x, y, z], got {_short(v)}"
    if kind == "literal_error":
        choices = ctx.get("expected", "").replace("'", "")
        return f"only {choices}, got {_short(v)}" if " or " not in choices and "," not in choices else \
            f"expected {choices}, got {_short(v)}"
    if kind == "too_short" and isinstance(v, list | tuple | str):
        return f"too short ({len(v)} items): {err['msg'][0].lower()}{err['msg'][1:]}"
    if kind == "too_long" and isinstance(v, list | tuple):
        return f"too long ({len(v)} items): {err['msg'][0].lower()}{err['msg'][1:]}"
    return None


def _message(err: dict, field: str = "value") -> str:
    kind, v = err["type"], err.get("input")
    if kind == "extra_forbidden":
        return "unknown key (not part of the format: misspelt? see docs/formats.md)"
    if kind == "missing":
        return "missing (required)"
    known = _number_message(kind, v, err, field) or _shape_message(kind, v, err)
    if known is not None:
        return known
    msg = err["msg"].removeprefix("Value error, ").removeprefix("Assertion failed, ")
    msg = msg[0].lower() + msg[1:] if msg else kind
    return f"{msg}, got {_short(v)}" if "input" in err and kind != "value_error" else msg


def _real_path(data: Any, loc: tuple) -> tuple:
    """The part of pydantic's error location that indexes ``data`` (drops union/tagged branch names)."""
    out: list = []
    for part in loc:
        in_dict = isinstance(data, dict) and part in data
        if in_dict or (isinstance(data, list | tuple) and isinstance(part, int) and 0 <= part < len(data)):
            data = data[part]
        elif isinstance(data, dict) and isinstance(part, str) and "[" not in part:
            out.append(part)  # a missing key: name it, no deeper
            break
        else:
            continue  # a union branch name ("function-after[...]", "tuple[...]")
        out.append(part)
    return tuple(out)


def _find_model(tp):
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return tp
    for a in get_args(tp):
        found = _find_model(a)
        if found:
            return found
    return None


def _model_at(schema: type[BaseModel], path: tuple):
    """The schema class of the mapping holding the last key of ``path``."""
    cur = schema
    for part in path[:-1]:
        if isinstance(part, int):
            continue
        if cur is None or part not in cur.model_fields:
            return None
        cur = _find_model(cur.model_fields[part].annotation)
    return cur


def check(schema: type[BaseModel], doc: YamlDoc | Any, error: type[Exception], name: str = "<data>"):
    """``schema`` validated from ``doc`` (a ``YamlDoc`` or plain data), or ``error`` in one line naming the
    file, line and field of the first problem."""
    if not isinstance(doc, YamlDoc):
        doc = YamlDoc(name, doc)
    try:
        return schema.model_validate(doc.data)
    except ValidationError as e:
        errs = e.errors(include_url=False)
        err = errs[0]
        path = _real_path(doc.data, err["loc"])
        last = [p for p in path if isinstance(p, str)]
        msg = _message(err, last[-1] if last else "value")
        if err["type"] == "extra_forbidden" and path:
            model = _model_at(schema, path)
            line = doc.line(path)
            if model:
                msg = f"expected a mapping of {', '.join(model.model_fields)}; unknown key {path[-1]!r} (misspelt?)"
            else:
                msg = f"unknown key {path[-1]!r} (misspelt? the keys are listed in docs/formats.md)"
            path = path[:-1]
            if line:
                raise error(f"{doc.name}:{line}: {dotted(path) or '(top level)'}: {msg}") from None
        elif err["type"] == "missing" and path:
            path, msg = path[:-1], f"expected key {path[-1]!r} (missing)"
        elif path and isinstance(path[-1], int) and not isinstance(err.get("input"), dict | list):
            path, msg = path[:-1], f"{msg} (item {path[-1] + 1})"  # name the list, count the item
        raise error(f"{doc.where(path)}: {msg}") from None


def finite(x: float) -> bool:
    return isinstance(x, float | int) and not isinstance(x, bool) and math.isfinite(x)
