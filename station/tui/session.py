"""The jog UI's session folder: the engine's journal (the truth) plus a ``samples.csv`` that ``station solve``
reads directly. Every recorded sample is journaled (fsynced) before the UI reports it recorded."""

from __future__ import annotations

import getpass
import socket
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from station.engine import events as ev
from station.engine.runner import new_session_id, station_home
from station.robot.errors import ConfigError
from station.samplesfile import joint_units, write_samples_csv

__all__ = ["JogSession", "joint_units", "session_header", "station_home"]


@dataclass
class JogSession:
    session_id: str
    folder: Path
    journal: object  # station.engine.journal.Journal
    joint_units: list[str]  # "rad" | "m" per joint, for the samples.csv header
    samples: list[ev.Sample] = field(default_factory=list)  # kept samples, journal order
    _pose: int = 0

    @classmethod
    def create(cls, *, header: ev.Header | dict, joint_units: list[str], folder: Path | None = None,
               session_id: str | None = None) -> JogSession:
        from station.engine.journal import Journal, make_header

        header = make_header(header)
        sid = session_id or new_session_id("jog", str(header.serial or "unknown"))
        header.session = sid
        folder = Path(folder) if folder is not None else station_home() / "sessions" / sid
        if (folder / "journal.jsonl").exists():
            raise ConfigError(f"session folder {folder} already has a journal; choose a new --session folder")
        folder.mkdir(parents=True, exist_ok=True)
        journal = Journal.create(folder / "journal.jsonl", header)
        session = cls(sid, folder, journal, list(joint_units))
        session.write_samples_csv()
        return session

    @property
    def samples_csv(self) -> Path:
        return self.folder / "samples.csv"

    def event(self, event: ev.Event | dict) -> ev.Event:
        """Append any event (step, result, writeback, fault, end) to the journal; fsynced on return."""
        if isinstance(event, dict):
            event = {**event, "session": self.session_id}
        else:
            event.session = self.session_id
        return self.journal.append(event)

    def add_sample(self, q: np.ndarray, point: str, *, raw, raw_unit: str, t: float, t_device: float | None,
                   touch: bool | None, status: dict) -> ev.Sample:
        """Journal one touch; ``t`` is the host time the joints were read."""
        sample = self.event(ev.Sample(point=point, q=[float(v) for v in q], raw=list(raw), raw_unit=raw_unit,
                                      t_read=t, t_device=t_device, pose=self._pose,
                                      status={**status, "touch": touch}))
        self._pose += 1
        self.samples.append(sample)
        self.write_samples_csv()
        return sample

    def discard(self, sample: ev.Sample, reason: str) -> None:
        self.event(ev.Discard(sample=sample.seq, reason=reason))
        self.samples.remove(sample)
        self.write_samples_csv()

    def write_samples_csv(self) -> None:
        write_samples_csv(self.samples_csv, self.samples, self.joint_units,
                          comment=f"jog session {self.session_id}, kept samples")

    def close(self, status: str = "completed", passed: bool | None = None) -> None:
        """``end`` event; "completed" (the engine's word) also tells ``station resume`` there is nothing to do."""
        try:
            self.event(ev.End(status=status, passed=passed, n_samples=len(self.samples)))
        finally:
            close = getattr(self.journal, "close", None)
            if close is not None:
                close()


def session_header(*, identity, model_name: str, serial: str, identify: str, reference, url: str) -> ev.Header:
    from importlib.metadata import PackageNotFoundError, version

    try:
        station_version = version("station")
    except PackageNotFoundError:  # running from a source tree without install
        station_version = "unknown"
    ident = identity if isinstance(identity, dict) else {
        k: getattr(identity, k) for k in ("vendor", "model", "serial", "firmware", "url")}
    return ev.Header(
        session="", procedure="jog", mode="technician", serial=serial, operator=_operator(),
        station=socket.gethostname(), url=url, model=model_name, robot=ident,
        options={"identify": identify, "reference": reference if isinstance(reference, str)
                 else {k: [float(x) for x in v] for k, v in reference.items()}},
        versions={"station": station_version})


def _operator() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no login name in some containers
        return "unknown"
