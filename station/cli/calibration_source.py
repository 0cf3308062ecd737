"""The one reader of ``--calibration REF`` for the commands that apply a calibration to a model (``station model
export``, ``station compensate``): a session id, a session folder, a journal, a result JSON (``station solve
--out``, a session's ``result.json``) or a session's ``report.json`` (with its journal beside it: that session).
Each is read into one shape: the result's parameters (``station-calibration/1``), for a session the model its
robot URL names (``model=``, ``tip_link=``, ``base_link=``: the export needs no model argument) and its fit
samples (what ``compensate`` weighs the uncertainty by). Every refusal is one line naming ``--calibration REF``
and the field."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from station.robot.errors import ConfigError


@dataclass
class CalibrationSource:
    result: dict  # {"model": name, "parameters": {name: {value, nominal, identifiable, kind, std, unit, ...}}}
    what: str  # for the exported file's note and messages
    model: str | None = None  # the session's model (built-in name or file), None for a bare result
    tip_link: str | None = None
    base_link: str | None = None
    samples: list[dict] | None = None  # a session's fit samples (journaled), None for a file
    file: Path | None = None  # a result file (station-calibration/1): its settings.samples may name its samples
    report: bool = False  # parameters from a report's rows alone: standard deviations, no correlations

    def values(self, model) -> dict[str, float]:
        """Every model parameter the result lists: its estimate where identified, else the value the session
        solved with (``nominal``): a session whose model came from the robot (a UR controller's factory
        calibration) exports that model, not the catalogue's."""
        out = {}
        for name, p in self.result["parameters"].items():
            if not isinstance(p, dict) or p.get("kind", "model") != "model" or name not in model.param_names:
                continue
            value = p.get("value") if p.get("identifiable") else p.get("nominal")
            if value is not None:
                out[name] = float(value)
        return out

    def check(self, model) -> None:
        """The calibration belongs to ``model``: its name, every identified parameter a parameter of it, and a
        result file's schema and physical bounds (``station.resultfile``)."""
        if self.result.get("model") not in (None, model.name):
            raise ConfigError(f"--calibration {self.what}: the calibration is for model {self.result['model']!r}, "
                              f"not {model.name!r}")
        unknown = [n for n, p in self.result["parameters"].items() if isinstance(p, dict) and p.get("identifiable")
                   and p.get("kind", "model") == "model" and n not in model.param_names]
        if unknown:
            raise ConfigError(f"--calibration {self.what}: parameters.{unknown[0]}: model {model.name!r} has no such "
                              "parameter")
        if self.file is not None:
            from station.resultfile import load_calibration

            load_calibration(self.file, model)

    def apply(self, model):
        """``model`` with the calibration's values (:meth:`values`), checked first."""
        self.check(model)
        return model.with_params(self.values(model))

    def calibration_result(self, model):
        """The calibration as a ``CalibrationResult`` checked against ``model``; from a report's rows alone its
        covariance is the parameters' variances (correlations unknown, said in its notes)."""
        from station.solver.result import CalibrationResult

        self.check(model)
        if self.report:
            return _result_of_rows(self.result, self.what)
        try:
            return CalibrationResult.from_dict(self.result)
        except (KeyError, TypeError, ValueError) as e:
            raise ConfigError(f"--calibration {self.what}: {e}") from None


def calibration_source(ref: str) -> CalibrationSource:
    path = Path(ref)
    if path.is_dir() or path.name == "journal.jsonl" or not path.exists():
        return _from_session(ref)
    from station.safeio import read_json

    doc = read_json(path, "calibration")
    fmt = doc.get("format") if isinstance(doc, dict) else None
    journal = path.parent / "journal.jsonl"  # a session's result.json or report.json: the session names the model
    if fmt == "station-report/1":
        return _from_session(str(journal)) if journal.is_file() else _from_report(doc, path)
    if fmt != "station-calibration/1" or not isinstance(doc.get("parameters"), dict):
        raise ConfigError(f"--calibration {ref}: format: expected a result (station-calibration/1, station solve "
                          f"--out) or a report (station-report/1), got {fmt!r}")
    if journal.is_file():
        src = _from_session(str(journal))
        return CalibrationSource(doc, str(path), src.model, src.tip_link, src.base_link, file=path)
    return CalibrationSource(doc, str(path), doc.get("model"), file=path)


def _from_report(doc: dict, path: Path) -> CalibrationSource:
    """A report lists its parameters as rows (name, value, nominal, std, identifiable, kind, unit): the same
    facts without their correlations."""
    rows = doc.get("parameters")
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"--calibration {path}: parameters: the report holds no solve result (a verify or a "
                          "failed session); give a session that solved")
    params = {}
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not isinstance(r.get("name"), str):
            raise ConfigError(f"--calibration {path}: parameters[{i}]: expected a row with a name")
        params[r["name"]] = {k: r.get(k) for k in ("value", "nominal", "identifiable", "kind", "std", "unit",
                                                   "reason")}
    model = ((doc.get("result") or {}).get("model")) or (doc.get("header") or {}).get("model")
    return CalibrationSource({"model": model, "parameters": params}, str(path), model, report=True)


def _result_of_rows(result: dict, what: str):
    """A ``CalibrationResult`` of a report's parameter rows: values and standard deviations only."""
    import numpy as np

    from station.solver.result import CalibrationResult, ParameterEstimate

    params = {}
    for name, row in result["parameters"].items():
        try:
            params[name] = ParameterEstimate(name, float(row["value"]), float(row["nominal"]),
                                             None if row.get("std") is None else float(row["std"]),
                                             bool(row["identifiable"]), row.get("reason") or "",
                                             row.get("kind") or "model", row.get("unit") or "m")
        except (KeyError, TypeError, ValueError):
            raise ConfigError(f"--calibration {what}: parameters: {row!r} is not a parameter row") from None
    res = CalibrationResult(str(result.get("model")), params, {}, 0, len(params), True, 0)
    std = [params[n].std for n in res.identified]
    if all(s is not None for s in std):
        res.covariance = np.diag(np.square(std))
    res.notes.append("from a report: standard deviations only, correlations unknown")
    return res


def _from_session(ref: str) -> CalibrationSource:
    from station.engine.journal import read_journal
    from station.engine.runner import find_session
    from station.engine.session_record import session_from_events

    journal = find_session(ref)
    try:
        header, events = read_journal(journal)
    except (ValueError, OSError) as e:
        raise ConfigError(f"--calibration {ref}: {e}") from None
    rec = session_from_events(header, events)
    result_file = journal.parent / "result.json"
    if result_file.is_file():
        from station.safeio import read_json

        result = read_json(result_file, "calibration")
    else:  # a session from before result.json: the journal's result event
        result = rec.get("result")
    if not isinstance(result, dict) or not isinstance(result.get("parameters"), dict):
        raise ConfigError(f"--calibration {ref}: session {header.session} ({header.procedure}) holds no solve "
                          "result; give a session that solved (zero_offsets, dh_full, ...) or a station solve result")
    query = {k: v[-1] for k, v in parse_qs(urlsplit(str(header.url or "")).query).items()}
    fit = [s for s in rec.get("samples") or [] if s.get("set", "fit") == "fit"]
    return CalibrationSource(result, f"session {header.session}", query.get("model") or header.model,
                             query.get("tip_link"), query.get("base_link"), samples=fit)
