"""Project a journal into the session record dict that ``station.records`` stores and ``station.report``
renders (see docs/architecture.md, "Samples, journal and records"). Pure: the journal is the truth."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

from station.engine.journal import read_journal


def iso(t: float | None) -> str | None:
    if t is None:
        return None
    return datetime.fromtimestamp(float(t), UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def live_samples(events: list[dict]) -> list[dict]:
    """Samples in journal order without the discarded ones (a retake discards the earlier sample)."""
    dropped = {e.get("sample") for e in events if e.get("type") == "discard"}
    return [e for e in events if e.get("type") == "sample" and e.get("seq") not in dropped]


def session_from_events(header: dict, events: list[dict]) -> dict:
    result = verdict = None
    writeback: dict | None = None
    finished = None
    end_status = None
    faults = []
    for e in events:
        kind = e.get("type")
        if kind == "result":
            result = e.get("result")
        elif kind == "verdict":
            verdict = {"passed": bool(e.get("passed")), "measurements": e.get("measurements", [])}
        elif kind == "writeback":
            writeback = writeback or {"before": None, "after": None, "applied": False, "verified": False}
            for key in ("before", "after", "applied", "verified", "readback", "check", "note", "files"):
                if key in e:
                    writeback[key] = e[key]
        elif kind == "fault":
            faults.append({"step": e.get("step"), "error": e.get("error"), "message": e.get("message")})
        elif kind == "end":
            finished = iso(e.get("t"))
            end_status = e.get("status")
    robot = header.get("robot") or {}
    return {
        "session": header.get("session"),
        "serial": header.get("serial"),
        "procedure": header.get("procedure"),
        "procedure_sha256": header.get("procedure_sha256"),
        "station": header.get("station"),
        "operator": header.get("operator"),
        "started": iso(header.get("t")),
        "finished": finished,
        "status": end_status,
        "robot": robot,
        "model": header.get("model"),
        "limits": header.get("limits"),
        "samples": live_samples(events),
        "result": result,
        "verdict": verdict,
        "writeback": writeback,
        "faults": faults,
    }


def session_from_journal(path: str | Path) -> dict:
    """The session record dict of a journal file (or of a session folder holding ``journal.jsonl``)."""
    path = Path(path)
    if path.is_dir():
        path = path / "journal.jsonl"
    header, events = read_journal(path)
    return session_from_events(header, events)
