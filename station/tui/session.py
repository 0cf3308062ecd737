"""The jog UI's session is an engine session in technician mode (``station.engine.runner.technician_session``):
the engine writes its journal (the truth) and the ``samples.csv`` that ``station solve`` reads directly, and the
UI journals every recorded sample through it (``Session.add_sample``, fsynced) before it reports the sample
recorded. Here: the header of such a session."""

from __future__ import annotations

import socket

from station.engine import events as ev
from station.engine.runner import operator_name, station_home, technician_session, versions
from station.samplesfile import joint_units

__all__ = ["joint_units", "session_header", "station_home", "technician_session"]


def session_header(*, identity, model_name: str, serial: str, identify: str, reference, url: str) -> ev.Header:
    """The journal header of a jog session: procedure ``jog``, mode ``technician``, the live solve's options."""
    ident = identity if isinstance(identity, dict) else {
        k: getattr(identity, k) for k in ("vendor", "model", "serial", "firmware", "url")}
    return ev.Header(
        session="", procedure="jog", mode="technician", serial=serial, operator=operator_name(),
        station=socket.gethostname(), url=url, model=model_name, robot=ident,
        options={"identify": identify, "reference": reference if isinstance(reference, str)
                 else {k: [float(x) for x in v] for k, v in reference.items()}},
        versions=versions())
