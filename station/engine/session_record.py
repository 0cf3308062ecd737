"""Project a journal into the session record dict that ``station.records`` stores and ``station.report``
renders (see docs/architecture.md, "Samples, journal and records"). Pure: the journal is the truth."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from station.engine import events as ev
from station.engine.journal import read_journal
from station.engine.steps import summarize


def iso(t: float | None) -> str | None:
    if t is None:
        return None
    return datetime.fromtimestamp(float(t), UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def live_samples(events: list[ev.Event]) -> list[ev.Sample]:
    """Samples in journal order without the discarded ones (a retake discards the earlier sample)."""
    dropped = {e.sample for e in events if isinstance(e, ev.Discard)}
    return [e for e in events if isinstance(e, ev.Sample) and e.seq not in dropped]


def writeback_summary(events: list[ev.Event]) -> dict | None:
    """The session's write-back as the records keep it: the last phase, what the device held before and holds
    after (SI), and whether it was applied (read back) and verified (known-pose check)."""
    wb: dict | None = None
    for e in events:
        if not isinstance(e, ev.Writeback):
            continue
        wb = wb or {"before": None, "after": None, "applied": False, "verified": False}
        if e.phase == "pre-image":  # a new attempt (a write, or the restore after a failed one)
            for key in ("readback", "check", "error"):
                wb.pop(key, None)
        wb.update(phase=e.phase, kind=e.kind)
        for key in ("before", "after", "readback", "check", "error", "backup"):
            if getattr(e, key) is not None:
                wb[key] = getattr(e, key)
        if e.note:
            wb["note"] = e.note
        if e.files:
            wb["files"] = list(e.files)
        if e.phase == "written":
            wb["applied"] = True
        elif e.phase == "verified":
            wb["verified"] = e.verified
        else:
            wb["applied"], wb["verified"] = e.applied, e.verified
    return wb


def session_from_events(header: ev.Header, events: list[ev.Event]) -> dict:
    result = verdict = None
    finished = None
    end_status = None
    faults = []
    cmap = None  # the correction_map procedure's map (station-map/1) and instrument registration, if any
    iso9283 = None  # the iso9283 procedure's figures per model (station-iso9283/1), cube and registration
    for e in events:
        if isinstance(e, ev.Custom) and e.type == "correction_map":
            cmap = dict(e.data)
        elif isinstance(e, ev.Custom) and e.type == "iso9283":
            iso9283 = dict(e.data)
        elif isinstance(e, ev.Result):
            result = e.result
        elif isinstance(e, ev.Verdict):
            verdict = {"passed": e.passed, "measurements": e.measurements}
            if e.status:
                verdict["status"] = e.status  # NO LIMITS
        elif isinstance(e, ev.Fault):
            faults.append({"step": e.step, "error": e.error, "message": e.message})
        elif isinstance(e, ev.End):
            finished = iso(e.t)
            end_status = e.status
    record = {
        "session": header.session,
        "serial": header.serial,
        "procedure": header.procedure,
        "procedure_sha256": header.procedure_sha256,
        "procedure_version": header.procedure_version,
        "station": header.station,
        "operator": header.operator,
        "started": iso(header.t),
        "finished": finished,
        "status": end_status,
        "robot": header.robot,
        "model": header.model,
        "limits": header.limits,
        "samples": [s.to_dict() for s in live_samples(events)],
        "result": result,
        "verdict": verdict,
        "writeback": writeback_summary(events),
        "faults": faults,
        "steps": summarize(events, iso),
    }
    if cmap is not None:
        record["correction_map"] = cmap
    if iso9283 is not None:
        record["iso9283"] = iso9283
    return record


def session_from_journal(path: str | Path) -> dict:
    """The session record dict of a journal file (or of a session folder holding ``journal.jsonl``)."""
    path = Path(path)
    if path.is_dir():
        path = path / "journal.jsonl"
    header, events = read_journal(path)
    return session_from_events(header, events)
