"""What the procedures that measure with an instrument share about the calibration they work on: the payload the
model carries (``--payload``) and a ``station solve`` result (``--calibration``), checked before anything moves,
journaled, and held to on a resume. Not a procedure itself (the leading underscore keeps it off the list)."""

import hashlib
import json
from pathlib import Path

import numpy as np

from station.engine.declare import Kind, Option, is_number, url
from station.robot.errors import ConfigError
from station.safeio import DuplicateKeyError, loads_strict
from station.solver.map import working_model


def _payload_value(text, flag: str, options: dict) -> dict:
    """``--payload 15kg[@x,y,z mm]`` (as ``station solve --payload``) as ``{"mass": kg, "com": [x, y, z] m}``."""
    from station.quantity import parse_payload

    mass, com = parse_payload(str(text))
    return {"mass": float(mass), "com": [float(c) for c in com]}


def _calibration_file(path, flag: str, options: dict) -> str:
    """``--calibration``: a readable ``station-calibration/1`` result (schema checked; its model name and
    parameters are checked against the robot's model once it is connected, before anything moves). A result with
    compliance parameters was solved under a payload: refused without the same ``--payload`` (read before it).
    The absolute path (journaled: a resume from another folder finds it)."""
    from station.kinematics.gravity import same_payload, show_payload
    from station.resultfile import CalibrationSchema
    from station.safeio import read_json
    from station.strict import check

    payload = options.get("payload")
    cal = check(CalibrationSchema, read_json(path, "calibration"), ConfigError, f"calibration {path}")
    compliance = [n for n, p in cal.parameters.items() if n.startswith("compliance.") and p.identifiable]
    if compliance and not payload:
        raise ConfigError(f"calibration {path}: parameters.{compliance[0]}: a compliance term (solved under a "
                          "payload, station solve --payload); give the same payload: --payload MASS (e.g. 15kg)")
    solved_under = (getattr(cal, "settings", None) or {}).get("payload")
    if compliance and solved_under is not None and not same_payload(solved_under, payload):
        raise ConfigError(f"calibration {path}: settings.payload: solved under {show_payload(solved_under)}, "
                          f"--payload gives {show_payload(payload)}; give the same --payload")
    return str(Path(path).resolve())


def _is_payload(v) -> bool:
    """A journaled payload: ``{"mass": kg, "com": [x, y, z] m}`` within what a station carries."""
    return (type(v) is dict and set(v) == {"mass", "com"} and is_number(v["mass"], 0, 10_000)
            and type(v["com"]) is list and len(v["com"]) == 3 and all(is_number(c, -10, 10) for c in v["com"]))


# the options of the procedures that measure with an instrument (declared once: correction_map, iso9283)
TRACKER = Option("tracker", "--tracker", url("tcp://127.0.0.1:5300"), "Measuring instrument URL, e.g. "
                 "tcp://127.0.0.1:5300 (station mock tracker).")
PAYLOAD = Option("payload", "--payload", Kind("a mass with its unit, optionally @x,y,z: 0.5kg@0,0,30mm", str,
                                              _payload_value, _is_payload, "{mass: kg 0..10000, com: [x, y, z] m}"),
                 "Mass at the tool, e.g. 0.1kg or 250g, optionally with its centre in the tool frame: 0.5kg@0,0,30mm "
                 "(loads the joints: compliance).", "kg", "none")
CALIBRATION = Option("calibration", "--calibration",
                     Kind("a station solve result JSON", Path, _calibration_file,
                          lambda v: type(v) is str and 0 < len(v) < 4096, "a file name"),
                     "A parametric calibration of the robot's model (result JSON of station solve) the procedure "
                     "works on top of.", None, "none (the nominal model)")


def _name(s) -> str:
    return str(s.journal.header.get("procedure") or "the procedure")


def payload(s) -> tuple[float, list] | None:
    """``--payload MASS[@x,y,z]`` (``{"mass": kg, "com": [x, y, z] m in the tool frame}``, journaled with the
    session's options: a resume uses the same one): the model carries it, so it has the compliance parameters
    ``compliance.jN`` of a ``station solve --payload`` calibration and deflects its joints under that load the way
    the calibration was solved. Nominal compliance is zero: without a calibration the payload changes nothing."""
    p = s.options.get("payload")
    if p is None:
        return None
    if not hasattr(s.model, "with_payload"):  # a parallel robot's model has no joint compliance
        raise ConfigError(f"{_name(s)}: --payload: model {s.model.name} ({getattr(s.model, 'kind', '?')}) has "
                          "no compliance terms for a payload to load; leave --payload out")
    try:
        mass, com = float(p["mass"]), [float(c) for c in p["com"]]
        if len(com) != 3 or not all(np.isfinite([mass, *com])):
            raise ValueError
        s.model = s.model.with_payload(mass, com)
    except (KeyError, TypeError, ValueError):
        raise ConfigError(f"{_name(s)}: payload {p!r}: expected {{mass: kg >= 0, com: [x, y, z] m}}") from None
    return mass, com


def calibration(s) -> dict | None:
    """``--calibration result.json``: the identified model parameters of a ``station solve`` result for this
    robot's model, checked (readable, trusted, model name and parameters) before anything moves and journaled
    as a ``calibration`` event with the file's sha256. A resumed session uses the journaled values and refuses
    the file if it changed since (the summands measured so far belong to the journaled calibration)."""
    path = s.options.get("calibration")
    if not path:
        return None
    old = s.events("calibration")
    with s.step("calibration", path=str(path)):
        try:
            data = Path(path).read_bytes()
        except OSError as e:
            raise ConfigError(f"calibration {path}: cannot read ({e.strerror or e})") from None
        sha = hashlib.sha256(data).hexdigest()
        if old:
            if sha != old[-1].data.get("sha256"):
                raise ConfigError(f"calibration {path} changed since session {s.id} started (sha256 differs): the "
                                  "samples so far belong to the journaled calibration; restore the file or start a "
                                  "new session")
            return dict(old[-1].data["parameters"])
        from station.resultfile import load_calibration
        from station.solver import CalibrationResult

        try:
            doc = loads_strict(data, f"calibration {path}")
        except DuplicateKeyError as e:
            raise ConfigError(str(e)) from None
        except ValueError:
            doc = None  # load_calibration says what is wrong with the file, in one line
        given = doc.get("parameters") if isinstance(doc, dict) else None
        compliance = sorted(n for n, p in (given if isinstance(given, dict) else {}).items()
                            if str(n).startswith("compliance.") and isinstance(p, dict) and p.get("identifiable")
                            and n not in s.model.param_names)
        if compliance:  # solved under a payload the session was not given: its deflection would be left out
            raise ConfigError(
                f"calibration {path}: parameters.{compliance[0]}: a compliance term (solved under a payload, station "
                f"solve --payload); give the same payload: --payload MASS (e.g. 15kg)"
                + ("" if s.options.get("payload") is None else ", not 0"))
        solved_under = (doc.get("settings") or {}).get("payload") if isinstance(doc, dict) else None
        if solved_under is not None and any(str(n).startswith("compliance.") for n in given or {}):
            from station.kinematics.gravity import same_payload, show_payload

            if not same_payload(solved_under, s.options.get("payload")):  # its compliance holds under that load only
                raise ConfigError(f"calibration {path}: settings.payload: solved under "
                                  f"{show_payload(solved_under)}, this session has "
                                  f"{show_payload(s.options.get('payload'))}; give the same --payload")
        load_calibration(path, s.model)  # one line naming file and field: format, model name, parameter names
        res = CalibrationResult.from_dict(json.loads(data))
        if not res.trusted:
            raise ConfigError(f"calibration {path}: the result is not trusted ({res.failure or 'see the solve'}); "
                              f"what {_name(s)} builds on it would hide that")
        params = {k: float(v) for k, v in res.values("model").items()}
        s.event({"type": "calibration", "path": str(path), "sha256": sha, "model": res.model,
                 "parameters": params, "identified": len(params), "payload": s.options.get("payload")})
    return params


def journaled_calibration(s) -> dict | None:
    """The journaled calibration's parameters (None: the session works on the nominal model)."""
    old = s.events("calibration")
    return dict(old[-1].data["parameters"]) if old else None


def working(s):
    """The model the session works with: nominal, or the journaled parametric calibration of it."""
    return working_model(s.model, journaled_calibration(s))
