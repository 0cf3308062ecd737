"""Why a unit ended the way it did, in the operator's words: what happened, what to do now, and the technical
line for the technician. Shared by the panel's page and the line's ``LastResult`` (OPC UA).

The error's *type* decides the words (``station.robot.errors`` and the engine's errors), never a match on the
driver's text: the drivers word their messages for technicians and may change them. ``kind`` groups the causes
the line handles differently (``serial``: the wrong unit or label; ``setup``: the station's configuration;
``robot``: the robot or its bus; ``station``: anything else; ``operator``: stopped on purpose)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

RESUME, TRY_AGAIN = "press RESUME", "press TRY AGAIN"


@dataclass(frozen=True)
class Reason:
    text: str  # what happened, one sentence, no jargon
    action: str  # what the operator does now
    detail: str  # the technical line (error type and message), for the technician
    kind: str  # serial | setup | robot | station | operator

    def to_dict(self) -> dict:
        return asdict(self)


def _detail(err: BaseException | None) -> str:
    if err is None:
        return ""
    text = " ".join(str(err).split())
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


def _again(resumable: bool) -> str:
    return RESUME if resumable else TRY_AGAIN


def explain(err: BaseException | None, *, serial: str | None = None, resumable: bool = False,
            reached: bool = True) -> Reason:
    """The plain reason for an error that ended (or refused) a unit. ``resumable``: the unit's session can be
    continued (RESUME), else the operator starts it again (TRY AGAIN); ``reached``: the station had connected
    to the robot (a session exists), else a lost connection is one never made."""
    go, detail = _again(resumable), _detail(err)
    reason = (_unit_reason(err, serial, resumable, detail) or _robot_reason(err, go, detail, reached)
              or _setup_reason(err, go, detail))
    if reason is not None:
        return reason
    return Reason("The station hit an unexpected problem.",
                  f"{go[0].upper() + go[1:]}. If it happens again, call the technician.", detail, "station")




def _unit_reason(err, serial: str | None, resumable: bool, detail: str) -> Reason | None:
    """Stopped on purpose, or not the unit (or robot type) the station expects."""
    from station.engine.runner import Aborted
    from station.robot import errors

    if isinstance(err, KeyboardInterrupt):  # Aborted, SIGTERM, Ctrl-C: stopped on purpose
        said = str(err) if isinstance(err, Aborted) and str(err) else "stopped (the station was interrupted)"
        return Reason(f"{said[:1].upper()}{said[1:]}.", "Scan the next unit" + (", or press RESUME to finish this one."
                                                                    if resumable else "."), detail, "operator")
    if isinstance(err, errors.SerialMismatch):
        given = err.given or serial or "?"
        return Reason(f"The unit in the cell is not {given}: the robot reports serial {err.reported}.",
                      "Scan the label of the unit that is clamped in the cell.", detail, "serial")
    if isinstance(err, errors.IdentityMismatch):
        return Reason("The robot in the cell is not the robot type this station is set up for.",
                      "Nothing moved. Call the technician.", detail, "setup")
    return None


def _robot_reason(err, go: str, detail: str, reached: bool) -> Reason | None:
    """The robot or its connection: what the operator can check on the robot."""
    from station.engine.writeback import WriteBackError
    from station.robot import errors

    if isinstance(err, errors.BusError) and not reached:
        return Reason("The station cannot reach the robot.",
                      f"Check that the robot is switched on and its cable is plugged in, then {go}. If it still "
                      "fails, call the technician (robot address or port).", detail, "robot")
    if isinstance(err, errors.ConnectionLost):
        return Reason("The robot stopped answering.",
                      "Check that the robot is switched on, its emergency stop is released and its cable is "
                      f"plugged in, then {go}.", detail, "robot")
    if isinstance(err, errors.BusError):
        return Reason("The connection to the robot stalled or was disturbed.",
                      f"The robot was stopped. Check its cable, then {go}. If it happens again, call the technician "
                      "(the station PC may be overloaded or the cable faulty).", detail, "robot")
    if isinstance(err, errors.SafetyStop):
        return Reason("The robot stopped for safety (protective or emergency stop).",
                      f"Make sure the cell is clear, release the stop on the robot, then {go}.", detail, "robot")
    if isinstance(err, WriteBackError):
        return Reason("Writing the calibration into the robot did not finish.",
                      f"The robot keeps a backup. {go[0].upper() + go[1:]} to write it again; if it fails again, "
                      "call the technician.", detail, "robot")
    if isinstance(err, errors.DeviceFault):
        return Reason("The robot reported a fault.",
                      f"Read the fault on the robot, clear it, then {go}. If it comes back, call the technician.",
                      detail, "robot")
    return None


def _setup_reason(err, go: str, detail: str) -> Reason | None:
    """The station's own set-up or its PC: for the technician."""
    from station.engine.journal import JournalError
    from station.engine.plan import PlanError
    from station.engine.runner import DiskError
    from station.engine.session import ResumeMismatch
    from station.records.store import RecordsError
    from station.robot import errors

    if isinstance(err, errors.LimitError):
        return Reason("A planned move was outside the robot's limits; it was not sent.",
                      "Call the technician.", detail, "setup")
    if isinstance(err, ResumeMismatch):
        return Reason("The robot is not in the state the interrupted run left it in.",
                      "Check it is the same unit, untouched since the run stopped; else start it again. Call the "
                      "technician if unsure.", detail, "setup")
    if isinstance(err, (DiskError, JournalError)):
        return Reason("The station PC could not save the measurements (disk full or not writable).",
                      f"Call the technician to free disk space, then {go}.", detail, "setup")
    if isinstance(err, RecordsError):
        return Reason("The records database cannot be reached.", "Call the technician.", detail, "setup")
    if isinstance(err, PlanError):
        return Reason("The station cannot plan the measuring poses for this cell.", "Nothing moved. Call the "
                      "technician (cell or limits setting).", detail, "setup")
    if isinstance(err, errors.ConfigError):
        return Reason("The station is not set up correctly for this unit.", "Call the technician.", detail,
                      "setup")
    return None


def refused(text: str, procedure: bool = False) -> Reason:
    """A start the station refused before anything ran: a malformed serial, or (``procedure``) a procedure the
    station does not have."""
    if procedure:
        return Reason(f"Not started: {text}.", "The line asked for a procedure this station does not run; call the "
                      "technician.", text, "setup")
    return Reason(f"Not started: {text}.", "Scan the unit's label again.", text, "serial")


# the limits file's measurement names (procedures/limits.yaml) as an operator reads them
MEASUREMENTS = {"samples": "points measured", "identified": "calibration parameters determined",
                "fit_rms": "fit error (rms)", "holdout_rms": "check-point error (rms)",
                "holdout_max": "largest check-point error", "offset_abs_max": "largest zero offset",
                "offset_std_max": "largest zero-offset uncertainty (1σ)"}
# operator units: lengths in mm, angles in degrees, counts without a unit
TO_OPERATOR = {"m": (1e3, "mm"), "um": (1e-3, "mm"), "µm": (1e-3, "mm"), "rad": (57.29577951308232, "deg"),
               "mrad": (0.05729577951308232, "deg"), "urad": (5.729577951308232e-05, "deg"),
               "µrad": (5.729577951308232e-05, "deg"), "count": (1.0, "")}


def plain_failure(m: dict) -> str:
    """A failing verdict measurement in words and units an operator reads: ``Fit error (rms): 0.0123 mm,
    above the limit of 0.001 mm``."""
    name = MEASUREMENTS.get(str(m.get("name")), str(m.get("name") or "?").replace("_", " "))
    scale, unit = TO_OPERATOR.get(str(m.get("unit") or ""), (1.0, str(m.get("unit") or "")))
    value, lo, hi = (None if x is None else float(x) * scale for x in (m.get("value"), m.get("low"), m.get("high")))
    name = name[:1].upper() + name[1:]
    if value is None:
        return f"{name}: no value could be measured"
    u = f" {unit}" if unit else ""
    if hi is not None and value > hi:
        return f"{name}: {value:.4g}{u}, above the limit of {hi:.4g}{u}"
    if lo is not None and value < lo:
        return f"{name}: {value:.4g}{u}, below the limit of {lo:.4g}{u}"
    return f"{name}: {value:.4g}{u}, outside its limits"


def where(samples: int, planned: int) -> str:
    """How far the unit got, for the operator: ``Stopped after 4 of 14 points; all 4 are kept.``"""
    if not planned:
        return "Stopped before the robot measured anything."
    if not samples:
        return f"Stopped before the first of {planned} points was measured."
    kept = "it is kept" if samples == 1 else f"all {samples} are kept"
    return f"Stopped after {samples} of {planned} points; {kept}."
