"""Where a calibration comes from for ``station model export --calibration REF``: a session id, a session
folder, a journal, a result JSON (``station solve --out``, a session's ``result.json``) or a session's
``report.json``. Each is read into one shape: the result's parameters (``station-calibration/1``) and, for a
session, the model its robot URL names (``model=``, ``tip_link=``, ``base_link=``), so that the export needs no
model argument."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from station.robot.errors import ConfigError


@dataclass
class CalibrationSource:
    result: dict  # {"model": name, "parameters": {name: {value, nominal, identifiable, kind, ...}}}
    what: str  # for the exported file's note and messages
    model: str | None = None  # the session's model (built-in name or file), None for a bare result
    tip_link: str | None = None
    base_link: str | None = None

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

    def apply(self, model):
        if self.result.get("model") not in (None, model.name):
            raise ConfigError(f"--calibration {self.what}: the calibration is for model {self.result['model']!r}, "
                              f"not {model.name!r}")
        unknown = [n for n, p in self.result["parameters"].items() if isinstance(p, dict) and p.get("identifiable")
                   and p.get("kind", "model") == "model" and n not in model.param_names]
        if unknown:
            raise ConfigError(f"--calibration {self.what}: parameters.{unknown[0]}: model {model.name!r} has no such "
                              "parameter")
        return model.with_params(self.values(model))


def calibration_source(ref: str) -> CalibrationSource:
    path = Path(ref)
    if path.is_dir() or path.name == "journal.jsonl" or not path.exists():
        return _from_session(ref)
    from station.safeio import read_json

    doc = read_json(path, "calibration")
    fmt = doc.get("format") if isinstance(doc, dict) else None
    if fmt == "station-report/1":
        return _from_report(doc, path)
    if fmt != "station-calibration/1" or not isinstance(doc.get("parameters"), dict):
        raise ConfigError(f"--calibration {ref}: format: expected a result (station-calibration/1, station solve "
                          f"--out) or a report (station-report/1), got {fmt!r}")
    journal = path.parent / "journal.jsonl"  # a session's result.json: the session names the model
    if journal.is_file():
        src = _from_session(str(journal))
        return CalibrationSource(doc, str(path), src.model, src.tip_link, src.base_link)
    return CalibrationSource(doc, str(path), doc.get("model"))


def _from_report(doc: dict, path: Path) -> CalibrationSource:
    """A report lists its parameters as rows (name, value, nominal, identifiable, kind, unit): the same facts."""
    rows = doc.get("parameters")
    if not isinstance(rows, list) or not rows:
        raise ConfigError(f"--calibration {path}: parameters: the report holds no solve result (a verify or a "
                          "failed session); export from a session that solved")
    params = {}
    for i, r in enumerate(rows):
        if not isinstance(r, dict) or not isinstance(r.get("name"), str):
            raise ConfigError(f"--calibration {path}: parameters[{i}]: expected a row with a name")
        params[r["name"]] = {k: r.get(k) for k in ("value", "nominal", "identifiable", "kind", "std", "unit")}
    model = ((doc.get("result") or {}).get("model")) or (doc.get("header") or {}).get("model")
    result = {"model": model, "parameters": params}
    journal = path.parent / "journal.jsonl"
    if journal.is_file():
        src = _from_session(str(journal))
        return CalibrationSource(result, str(path), src.model, src.tip_link, src.base_link)
    return CalibrationSource(result, str(path), model)


def _from_session(ref: str) -> CalibrationSource:
    from station.engine.journal import read_journal
    from station.engine.runner import find_session
    from station.engine.session_record import session_from_journal

    journal = find_session(ref)
    header, _ = read_journal(journal)
    result_file = journal.parent / "result.json"
    if result_file.is_file():
        from station.safeio import read_json

        result = read_json(result_file, "calibration")
    else:  # a session from before result.json: the journal's result event
        result = session_from_journal(journal).get("result")
    if not result or not isinstance(result.get("parameters"), dict):
        raise ConfigError(f"--calibration {ref}: session {header.session} ({header.procedure}) holds no solve "
                          "result; export from a session that solved (zero_offsets, dh_full, ...)")
    query = {k: v[-1] for k, v in parse_qs(urlsplit(str(header.url or "")).query).items()}
    return CalibrationSource(result, f"session {header.session}", query.get("model") or header.model,
                             query.get("tip_link"), query.get("base_link"))
