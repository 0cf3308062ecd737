"""``write_report(session, folder)``: report.json (SI) and a self-contained report.html (plots inline)."""

from __future__ import annotations

import json
import math
import os
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path

import jinja2

from station.report.content import build_report
from station.report.plots import all_plots
from station.units import human_of, joint_unit

_TEMPLATE = resources.files("station.report") / "template.html"  # package data: found in a wheel install too


def _num(v, digits: int = 4) -> str:
    if v is None or isinstance(v, (bool, jinja2.Undefined)):
        return ""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not math.isfinite(f):
        return ""
    if f.is_integer() and abs(f) < 1e6:  # counts and whole-number limits read as integers
        return str(int(f))
    return f"{f:.{digits}g}" if abs(f) >= 1e4 or (f != 0 and abs(f) < 1e-3) else f"{f:.{digits}f}"


def _human(v, unit: str) -> str:
    """SI -> mm / deg text for people."""
    if v is None or isinstance(v, jinja2.Undefined):
        return ""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return ""
    if not math.isfinite(f):
        return ""
    return f"{f * human_of(unit if unit in ('rad', 'm') else 'm')[1]:.4f}"


def _hunit(unit: str) -> str:
    return human_of(unit)[0]


def _band(v) -> str:
    if isinstance(v, jinja2.Undefined):
        return ""
    if v is True:
        return "yes"
    if v in (None, False):
        return ""
    return _num(v)


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("station")
    except Exception:  # noqa: BLE001 - a missing dist-info must not stop a report
        return "?"


def render_html(report: dict, session: dict) -> str:
    env = jinja2.Environment(autoescape=True, undefined=jinja2.ChainableUndefined, trim_blocks=True,
                             lstrip_blocks=True)
    template = env.from_string(_TEMPLATE.read_text(encoding="utf-8"))
    joints = report["coverage"]["joints"]
    samples = []
    pp = report["residuals"]["per_pose"]
    # per-sample errors line up with the samples only when recomputed for all of them
    by_seq = dict(zip(pp.get("seq") or [], zip(pp["before_m"], pp["after_m"], strict=False), strict=False)) \
        if len(pp.get("seq") or []) == len(pp["before_m"]) else {}
    for s in session.get("samples") or []:
        q = s.get("q") or []
        units = [joint_unit(j["kind"] == "revolute") for j in joints] or ["rad"] * len(q)
        samples.append({"seq": s.get("seq"), "pose": s.get("pose"), "point": s.get("point", ""),
                        "set": s.get("set", "fit"),
                        "before": _human(by_seq.get(s.get("seq"), (None, None))[0], "m"),
                        "after": _human(by_seq.get(s.get("seq"), (None, None))[1], "m"),
                        "q": "  ".join(_human(v, units[i] if i < len(units) else "rad") for i, v in enumerate(q))})
    return template.render(
        r=report, h=report["header"], plots=all_plots(report), samples=samples, num=_num, mm=lambda v: _human(v, "m"),
        human=_human, hunit=_hunit, band=_band, jointunit=lambda j: joint_unit(j["kind"] == "revolute"),
        version=_version(), generated=datetime.now(UTC).isoformat(timespec="seconds"))


def _write(path: Path, text: str) -> None:
    # write-then-rename: a crash leaves the old report or the new one, never half of one
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_report(session: dict, folder) -> Path:
    """Write ``report.json`` and ``report.html`` into ``folder`` (created); returns the HTML path."""
    folder = Path(folder)
    report = build_report(session)
    folder.mkdir(parents=True, exist_ok=True)
    html = render_html(report, session)
    _write(folder / "report.json", json.dumps(report, indent=1, allow_nan=False) + "\n")
    _write(folder / "report.html", html)
    return folder / "report.html"
