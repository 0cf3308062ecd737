"""Procedure engine: sessions and steps, runner with guaranteed teardown, pose plans, limits and verdicts,
the session journal and its event schema, resume, write-back. Imports the robot protocol/registry, solver and
kinematics only (never records, report, CLI, UI or a driver: tests/test_import_rules_engine.py).

Names are loaded on first use, so that ``station.engine.events`` and ``station.engine.journal`` stay cheap to
import for readers of a journal (records, report, tools) that need no numpy or kinematics."""

from importlib import import_module

_WHERE = {
    "Cell": "cell", "CellError": "cell", "RefPoint": "cell", "cell_from_dict": "cell", "load_cell": "cell",
    "Journal": "journal", "JournalError": "journal", "read_journal": "journal",
    "Limit": "limits", "Limits": "limits", "LimitsError": "limits", "load_limits": "limits",
    "PlanError": "plan", "PlannedPose": "plan", "PosePlan": "plan", "generate_plan": "plan",
    "plan_from_joints": "plan",
    "Procedure": "procedure", "ProcedureError": "procedure", "load_procedure": "procedure",
    "shipped_names": "procedure",
    "Outcome": "runner", "resume": "runner", "start": "runner",
    "ResumeMismatch": "session", "Session": "session",
    "session_from_events": "session_record", "session_from_journal": "session_record",
    "GuardedApproach": "touch", "ManualTouch": "touch", "SocketSeating": "touch", "TouchFailed": "touch",
    "TouchProvider": "touch",
}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(f"station.engine.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'station.engine' has no attribute {name!r}")


__all__ = sorted(_WHERE)
