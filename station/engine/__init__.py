"""Procedure engine: sessions and steps, runner with guaranteed teardown, pose plans, limits and verdicts,
the session journal and resume. Imports the robot protocol/registry, solver and kinematics only."""

from station.engine.cell import Cell, CellError, RefPoint, cell_from_dict, load_cell
from station.engine.journal import Journal, JournalError, read_journal
from station.engine.limits import Limit, Limits, LimitsError, load_limits
from station.engine.plan import PlanError, PlannedPose, PosePlan, generate_plan, plan_from_joints
from station.engine.procedure import Procedure, ProcedureError, load_procedure, shipped_names
from station.engine.runner import Outcome, resume, start
from station.engine.session import ResumeMismatch, Session
from station.engine.session_record import session_from_events, session_from_journal
from station.engine.touch import GuardedApproach, ManualTouch, SocketSeating, TouchFailed, TouchProvider

__all__ = [
    "Cell", "CellError", "GuardedApproach", "Journal", "JournalError", "Limit", "Limits", "LimitsError",
    "ManualTouch", "Outcome", "PlanError", "PlannedPose", "PosePlan", "Procedure", "ProcedureError", "RefPoint",
    "ResumeMismatch", "Session", "SocketSeating", "TouchFailed", "TouchProvider", "cell_from_dict",
    "generate_plan", "load_cell", "load_limits", "load_procedure", "plan_from_joints", "read_journal", "resume",
    "session_from_events", "session_from_journal", "shipped_names", "start",
]
