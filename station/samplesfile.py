"""CSV files of touch samples and joint readings, with units in the headers: the reader (text in, SI arrays
out) and the one writer of a session's ``samples.csv`` (the engine and the jog UI).

Columns: ``q1..qN`` (joint readings; radians or metres unless the header says ``q1[deg]``, ``q3[mm]``),
optional ``point`` (label of the reference point touched; default ``A``), optional ``x,y,z`` (instrument
measurement of the tip; metres unless ``x[mm]``), optional ``weight`` (per-touch weight, 1/variance scale:
a touch of weight 4 is trusted as having half the noise; default 1), optional ``fixture`` (the fixture position
label: touches at different positions are on different points; see docs/formats.md). Other columns are
ignored; lines starting with ``#`` are comments.
Errors name the file, the line and the column: ``samples.csv:7: column 'q3': not a number``."""

from __future__ import annotations

import csv
import io
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from station.lazy import lazy_module
from station.units import ANGLE_UNITS, LENGTH_UNITS, joint_unit

np = lazy_module("numpy")  # imported on first use (station.lazy: start-up of every command)

_HEADER = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_.]*)\s*(?:\[\s*([A-Za-z]+)\s*\])?\s*$")
_JOINT = re.compile(r"^q(\d+)$")


MAX_BYTES = 256 * 1024 * 1024  # 100k samples are ~10 MB; beyond this a file is refused, not read
_NUMBER = re.compile(r"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?|[-+]?(?:nan|inf|infinity)", re.I | re.A)


class SamplesFileError(ValueError):
    """A samples/joints file cannot be read; the message is one line naming file, line and column."""


@dataclass(frozen=True)
class Column:
    name: str  # base name, lower case: "q3", "x", "point"
    unit: str | None  # as written in the header, lower case
    header: str  # as written


@dataclass
class Table:
    path: str
    columns: dict[str, tuple[int, Column]]  # base name -> (field index, column)
    rows: list[list[str]]
    lines: list[int]  # file line number of each row
    header_line: int = 1
    warnings: list[str] = field(default_factory=list)  # accepted, but worth one line each (readings beyond limits)

    def where(self, i: int) -> str:
        return f"{self.path}:{self.lines[i]}"


@dataclass
class Samples:
    q: np.ndarray  # (N, n) SI
    point: np.ndarray  # (N,) labels
    measured: np.ndarray | None  # (N, 3) m
    lines: list[int]  # file line of each sample
    path: str
    weight: np.ndarray | None = None  # (N,) per-touch weights (1/variance scale), None: all 1
    fixture: np.ndarray | None = None  # (N,) fixture position labels, None: one position
    warnings: list[str] = field(default_factory=list)  # one line each: readings beyond the joint limits


def _row(path: str, line: int, text: str) -> list[str]:
    try:
        return next(csv.reader(io.StringIO(text)))
    except (csv.Error, StopIteration) as e:  # e.g. a field beyond csv.field_size_limit(): not a samples file
        raise SamplesFileError(f"{path}:{line}: not a CSV row ({str(e).splitlines()[0][:80] or 'empty'})") from None


def parse_table(text: str, path: str = "<text>") -> Table:
    lines = text.splitlines()
    body = [(i + 1, ln) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if not body:
        raise SamplesFileError(f"{path}: empty file (expected a header line with q1..qN)")
    head_line, head = body[0]
    fields = _row(path, head_line, head)
    columns: dict[str, tuple[int, Column]] = {}
    for k, h in enumerate(fields):
        m = _HEADER.match(h)
        if not m:
            raise SamplesFileError(f"{path}:{head_line}: column {k + 1} {h.strip()!r}: not a column name "
                                   f"(expected e.g. q1, q1[deg], x[mm], point)")
        name, unit = m.group(1).lower(), (m.group(2) or "").lower() or None
        if name in columns:
            raise SamplesFileError(f"{path}:{head_line}: column {name!r} appears twice")
        columns[name] = (k, Column(name, unit, h.strip()))
    rows, nums = [], []
    for ln, text_line in body[1:]:
        row = _row(path, ln, text_line)
        if len(row) != len(fields):
            raise SamplesFileError(f"{path}:{ln}: {len(row)} fields, the header has {len(fields)}")
        rows.append([c.strip() for c in row])
        nums.append(ln)
    return Table(path, columns, rows, nums, head_line)


def read_table(path: str | Path) -> Table:
    from station.textfile import decode, read_capped

    p = Path(path)
    if not p.exists() and not p.is_symlink():
        raise SamplesFileError(f"{p}: no such file")
    text = decode(read_capped(p, SamplesFileError, str(p), MAX_BYTES), SamplesFileError, str(p))
    return parse_table(text, str(p))


def _kinds(joints) -> list[str]:
    if hasattr(joints, "joints"):
        joints = joints.joints
    return [j if isinstance(j, str) else j.kind for j in joints]


def _factor(t: Table, col: Column, kind: str, what: str) -> float:
    where = f"{t.path}:{t.header_line}"
    if col.unit is None:
        return 1.0
    table = ANGLE_UNITS if kind == "revolute" else LENGTH_UNITS
    if col.unit in table:
        return table[col.unit]
    other = LENGTH_UNITS if kind == "revolute" else ANGLE_UNITS
    if col.unit in other:
        expect = "an angle (rad, deg, mrad)" if kind == "revolute" else "a length (m, mm, cm, um)"
        raise SamplesFileError(f"{where}: column {col.header!r}: {what} is {kind}, its unit must be {expect}")
    raise SamplesFileError(f"{where}: column {col.header!r}: unknown unit {col.unit!r}")


def _number(t: Table, i: int, col: Column, k: int) -> float:
    s = t.rows[i][k]
    try:
        if not _NUMBER.fullmatch(s):  # float() would take "1_0" and Arabic-Indic digits
            raise ValueError(s)
        v = float(s)
    except ValueError:
        raise SamplesFileError(f"{t.where(i)}: column {col.header!r}: not a number ({s!r})") from None
    if not math.isfinite(v):
        raise SamplesFileError(f"{t.where(i)}: column {col.header!r}: not a finite number ({s!r})")
    return v


def column_si(t: Table, name: str, quantity: str) -> np.ndarray:
    """Column ``name`` of every row in SI: ``quantity`` "length" (m unless the header says ``x[mm]``) or
    "angle" (rad unless ``rx[deg]``); a unit of the other quantity, an unknown unit or a cell that is not a
    finite number is one line naming file, line and column."""
    k, col = t.columns[name]
    table, other = (ANGLE_UNITS, LENGTH_UNITS) if quantity == "angle" else (LENGTH_UNITS, ANGLE_UNITS)
    f = 1.0
    if col.unit is not None:
        if col.unit not in table:
            expect = "an angle (rad, deg, mrad)" if quantity == "angle" else "a length (m, mm, cm, um)"
            why = f"it is {quantity == 'angle' and 'an angle' or 'a length'}, its unit must be {expect}" \
                if col.unit in other else f"unknown unit {col.unit!r}"
            raise SamplesFileError(f"{t.path}:{t.header_line}: column {col.header!r}: {why}")
        f = table[col.unit]
    return np.array([_number(t, i, col, k) for i in range(len(t.rows))]) * f


def joint_matrix(t: Table, joints) -> np.ndarray:
    """``(N, n)`` joint readings in SI from columns ``q1..qn``; the joint count must match exactly."""
    kinds = _kinds(joints)
    n = len(kinds)
    qcols = sorted(int(m.group(1)) for name in t.columns if (m := _JOINT.match(name)))
    model = f"the model has {n} joints"
    if any(k > n for k in qcols) or any(k < 1 for k in qcols):
        raise SamplesFileError(f"{t.path}: wrong joint count: joint columns {', '.join(f'q{k}' for k in qcols)} "
                               f"but {model} (q1..q{n})")
    for k in range(1, n + 1):
        if f"q{k}" not in t.columns:
            raise SamplesFileError(f"{t.path}: missing column 'q{k}' ({model}: q1..q{n})")
    if not t.rows:
        raise SamplesFileError(f"{t.path}: no data rows")
    q = np.zeros((len(t.rows), n))
    for j in range(n):
        k, col = t.columns[f"q{j + 1}"]
        f = _factor(t, col, kinds[j], f"joint {j + 1}")
        for i in range(len(t.rows)):
            q[i, j] = _number(t, i, col, k) * f
    _check_limits(t, joints, q)
    return q


def _check_limits(t: Table, joints, q: np.ndarray) -> None:
    """Readings are data: a reading beyond the model's joint limits is what the robot reported (a URDF's limits
    are often tighter than the joint's travel, encoders overshoot), so it is used, with one warning line per
    joint naming how many readings and how far (``t.warnings``); limits bind motion only. Only a column that
    looks like a unit slip is refused: readings that cannot be radians (beyond a full turn and the limits) but fit
    the limits as degrees, or metres that fit as millimetres (ten times beyond the travel)."""
    js = getattr(joints, "joints", joints)
    if not all(hasattr(j, "lower") and hasattr(j, "upper") for j in js):
        return
    for j, jt in enumerate(js):
        lo, hi = float(jt.lower), float(jt.upper)
        rev = jt.kind == "revolute"
        margin = max(0.05 * (hi - lo), math.radians(5) if rev else 0.005)
        col = q[:, j]
        bad = np.flatnonzero((col < lo - margin) | (col > hi + margin))
        if bad.size == 0:
            continue
        unit = "rad" if rev else "m"
        peak = float(np.max(np.abs(col)))
        if rev:
            slip = peak > max(2 * math.pi, abs(lo), abs(hi)) + margin and bool(
                np.all((np.radians(col) >= lo - margin) & (np.radians(col) <= hi + margin)))
            hint = "degrees in a radian column?"
        else:
            slip = peak > 10 * max(abs(lo), abs(hi), 0.01) and bool(
                np.all((col * 1e-3 >= lo - margin) & (col * 1e-3 <= hi + margin)))
            hint = "mm in a metre column?"
        i = int(bad[np.argmax(np.abs(col[bad]))])
        v = q[i, j]
        if slip:
            more = f" ({bad.size} rows like it)" if bad.size > 1 else ""
            raise SamplesFileError(f"{t.where(i)}: row {i + 1}: q{j + 1} = {v:.6g} {unit} is outside the joint limits "
                                   f"[{lo:.4g}, {hi:.4g}] {unit} — {hint}{more}")
        beyond = float(max(lo - v, v - hi))
        deg = f" ({math.degrees(beyond):.3g} deg)" if rev else ""
        t.warnings.append(f"{t.path}: q{j + 1} ({jt.name}): {bad.size} of {len(col)} readings beyond the joint limits "
                          f"[{lo:.4g}, {hi:.4g}] {unit}, by up to {beyond:.4g} {unit}{deg} (line {t.lines[i]}); "
                          f"used as recorded: limits bind motion, not readings")


def read_joints(path: str | Path, joints) -> tuple[np.ndarray, Table]:
    """Joint readings only (``station fk`` input)."""
    t = read_table(path)
    return joint_matrix(t, joints), t


def read_samples(path: str | Path, joints) -> Samples:
    """Touch samples: joint readings, point labels, optional instrument measurements."""
    t = read_table(path)
    q = joint_matrix(t, joints)
    if "point" in t.columns:
        k, col = t.columns["point"]
        labels = []
        for i in range(len(t.rows)):
            s = t.rows[i][k]
            if not s:
                raise SamplesFileError(f"{t.where(i)}: column 'point': empty label")
            if not re.fullmatch(r"[A-Za-z0-9_-]+", s):
                raise SamplesFileError(f"{t.where(i)}: column 'point': label {s!r} (use letters, digits, _ or -)")
            labels.append(s)
        point = np.array(labels, dtype=object)
    else:
        point = np.full(len(t.rows), "A", dtype=object)
    have = [a for a in "xyz" if a in t.columns]
    measured = None
    if have:
        if len(have) != 3:
            missing = [a for a in "xyz" if a not in have]
            raise SamplesFileError(f"{t.path}: missing column {missing[0]!r} (instrument measurements need x, y, z)")
        measured = np.zeros((len(t.rows), 3))
        for a, axis in enumerate("xyz"):
            k, col = t.columns[axis]
            f = _factor(t, col, "prismatic", f"measurement {axis}")
            for i in range(len(t.rows)):
                measured[i, a] = _number(t, i, col, k) * f
    weight = None
    if "weight" in t.columns:
        k, col = t.columns["weight"]
        if col.unit not in (None, "1"):
            raise SamplesFileError(f"{t.path}:{t.header_line}: column {col.header!r}: a weight has no unit")
        weight = np.array([_number(t, i, col, k) for i in range(len(t.rows))])
        bad = np.flatnonzero(weight <= 0)
        if bad.size:
            i = int(bad[0])
            raise SamplesFileError(f"{t.where(i)}: column 'weight': {t.rows[i][k]!r} must be > 0 (1/variance scale; "
                                   "drop the row to exclude a touch)")
    fixture = None
    if "fixture" in t.columns:
        k, col = t.columns["fixture"]
        labels = []
        for i in range(len(t.rows)):
            s = t.rows[i][k]
            if not re.fullmatch(r"[A-Za-z0-9_-]+", s):
                raise SamplesFileError(f"{t.where(i)}: column 'fixture': label {s!r} (use letters, digits, _ or -)")
            labels.append(s)
        fixture = np.array(labels, dtype=object)
    return Samples(q, point, measured, list(t.lines), t.path, weight, fixture, list(t.warnings))


# ---- writing a session's samples.csv ----------------------------------------------------------------------
def joint_units(model) -> list[str]:
    """SI unit of each joint's column: rad, or m for a prismatic joint."""
    return [joint_unit(j.revolute) for j in model.joints]


def write_samples_csv(path: str | Path, samples, units: list[str], *, comment: str) -> Path:
    """A session's kept samples (``station.engine.events.Sample``) as the file ``station solve --samples``
    reads: ``q1[rad]..qN[..], point, seq, set`` and ``x[m], y[m], z[m]`` when every sample has an instrument
    measurement. Rewritten whole and atomically (temp file, fsync, rename): a crash leaves the old or the new
    file, never a torn one; the journal stays the truth either way."""
    path = Path(path)
    samples = list(samples)
    meas = bool(samples) and all(x.measured is not None for x in samples)
    extra = [c for c in ("weight", "fixture") if any(getattr(x, c, None) is not None for x in samples)]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as fh:
        fh.write(f"# station samples: {comment}; joints in rad (m if prismatic), measured x,y,z in m; "
                 "seq = journal sequence number, set = fit|holdout\n")
        w = csv.writer(fh)
        w.writerow([f"q{i + 1}[{u}]" for i, u in enumerate(units)] + ["point", "seq", "set"]
                   + (["x[m]", "y[m]", "z[m]"] if meas else []) + extra)
        defaults = {"weight": 1.0, "fixture": "1"}
        for x in samples:
            w.writerow([repr(float(v)) for v in x.q] + [x.point, x.seq, x.set]
                       + ([repr(float(v)) for v in x.measured] if meas else [])
                       + [getattr(x, c, None) if getattr(x, c, None) is not None else defaults[c] for c in extra])
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path
