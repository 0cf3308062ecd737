"""The jog UI's session folder: the engine's journal (the truth) plus a ``samples.csv`` that ``station solve``
reads directly. Every recorded sample is journaled (fsynced) before the UI reports it recorded."""

from __future__ import annotations

import csv
import getpass
import os
import socket
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from station.robot.errors import ConfigError


def station_home() -> Path:
    return Path(os.environ.get("STATION_HOME") or "./station-data")


def new_session_id(serial: str) -> str:
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in serial) or "unknown"
    return f"jog-{safe}-{stamp}"


@dataclass
class JogSample:
    """One recorded touch as the UI shows it; ``seq`` is its journal sequence number."""

    seq: int
    point: str
    q: np.ndarray  # SI, as the device reported it
    t: float
    touch: bool | None
    pose: int


def joint_units(model) -> list[str]:
    return ["rad" if j.revolute else "m" for j in model.joints]


@dataclass
class JogSession:
    session_id: str
    folder: Path
    journal: object  # station.engine.journal.Journal
    joint_units: list[str]  # "rad" | "m" per joint, for the samples.csv header
    samples: list[JogSample] = field(default_factory=list)
    _pose: int = 0

    @classmethod
    def create(cls, *, header: dict, joint_units: list[str], folder: Path | None = None,
               session_id: str | None = None) -> JogSession:
        from station.engine.journal import Journal

        sid = session_id or new_session_id(str(header.get("serial") or "unknown"))
        folder = Path(folder) if folder is not None else station_home() / "sessions" / sid
        if (folder / "journal.jsonl").exists():
            raise ConfigError(f"session folder {folder} already has a journal; choose a new --session folder")
        folder.mkdir(parents=True, exist_ok=True)
        journal = Journal.create(folder / "journal.jsonl", {**header, "session": sid})
        session = cls(sid, folder, journal, list(joint_units))
        session.write_samples_csv()
        return session

    @property
    def samples_csv(self) -> Path:
        return self.folder / "samples.csv"

    def event(self, event: dict) -> dict:
        """Append any event (step, result, writeback, fault, end) to the journal; fsynced on return."""
        return self.journal.append({"session": self.session_id, **event})

    def add_sample(self, q: np.ndarray, point: str, *, raw, raw_unit: str, t: float, t_device: float | None,
                   touch: bool | None, status: dict) -> JogSample:
        ev = self.event({"type": "sample", "point": point, "q": [float(v) for v in q],
                         "raw": [_plain(v) for v in raw], "raw_unit": raw_unit, "t": t, "t_device": t_device,
                         "measured": None, "pose": self._pose, "set": "fit",
                         "status": {**status, "touch": touch}})
        sample = JogSample(int(ev["seq"]), point, np.asarray(q, dtype=float).copy(), t, touch, self._pose)
        self._pose += 1
        self.samples.append(sample)
        self.write_samples_csv()
        return sample

    def discard(self, sample: JogSample, reason: str) -> None:
        self.event({"type": "discard", "sample": sample.seq, "reason": reason})
        self.samples.remove(sample)
        self.write_samples_csv()

    def write_samples_csv(self) -> None:
        """Rewrite the kept samples atomically (temp file + fsync + rename): a crash leaves the old or the new
        file, never a torn one; the journal stays the truth either way."""
        tmp = self.samples_csv.with_suffix(".csv.tmp")
        with open(tmp, "w", newline="") as f:
            f.write(f"# station jog session {self.session_id}: kept samples, joints in rad (m if prismatic); "
                    "seq = journal sequence number\n")
            w = csv.writer(f)
            w.writerow([f"q{i + 1}[{u}]" for i, u in enumerate(self.joint_units)] + ["point", "seq"])
            for s in self.samples:
                w.writerow([repr(float(v)) for v in s.q] + [s.point, s.seq])
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, self.samples_csv)

    def close(self, status: str = "completed") -> None:
        """``end`` event; "completed" (the engine's word) also tells ``station resume`` there is nothing to do."""
        try:
            self.event({"type": "end", "status": status, "n_samples": len(self.samples)})
        finally:
            close = getattr(self.journal, "close", None)
            if close is not None:
                close()


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    return v


def session_header(*, identity, model_name: str, serial: str, identify: str, reference, url: str) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        station_version = version("station")
    except PackageNotFoundError:  # running from a source tree without install
        station_version = "unknown"
    ident = identity if isinstance(identity, dict) else {
        k: getattr(identity, k) for k in ("vendor", "model", "serial", "firmware", "url")}
    return {
        "procedure": "jog", "procedure_sha256": None, "mode": "technician",
        "station": {"host": socket.gethostname(), "robot_url": url, "identify": identify,
                    "reference": reference if isinstance(reference, str)
                    else {k: [float(x) for x in v] for k, v in reference.items()}},
        "robot": ident, "model": model_name, "serial": serial, "operator": _operator(),
        "versions": {"station": station_version}, "started": datetime.now(UTC).isoformat(),
        "units": "SI (m, rad)", "t_created": time.time(),
    }


def _operator() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no login name in some containers
        return "unknown"
