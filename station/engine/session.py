"""``Session``: the vocabulary procedures are written in (the scripted API). Every step journals what it did;
replaying a procedure on a resumed session skips what the journal already holds (recorded samples, the plan,
a write-back in progress) after re-verifying the robot."""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from station.engine import events as ev
from station.engine import steps
from station.engine.cell import Cell, RefPoint
from station.engine.journal import Journal
from station.engine.limits import NO_LIMITS, Limit, LimitsError
from station.engine.plan import PlannedPose, PosePlan, generate_plan, plan_from_joints
from station.engine.procedure import Question, terminal_prompt
from station.engine.session_record import live_samples, session_from_events
from station.engine.steps import Steps
from station.engine.touch import TouchProvider, provider_for
from station.kinematics import Model
from station.robot.capabilities import CalibrationStore, Compliant, ContactSensor
from station.robot.errors import ConfigError, DeviceFault, SafetyStop, StationError
from station.robot.protocol import adopt_serial
from station.units import human, param_quantity

APPROACH_TOOL_SPEED = 0.10  # m/s at the tool on the last centimetres to a reference (seating, contact)
# plan-time check: a touch noise better than any cell achieves (seating repeatability is ~10 um), so a refused
# plan is one that cannot pass, not one that might not
PLAN_NOISE_M = 5e-6


class ResumeMismatch(StationError):
    """The robot is not in the state the journal left it in: resuming would mix samples of two states."""


class Session:
    """One calibration session on one robot. Build it with ``station.connect``/``station.engine.runner``;
    procedures receive it as ``s``. A technician's session (``station jog``, header ``mode: technician``,
    ``runner.technician_session``) is the same object: the jog UI drives the robot itself and journals what it
    records through :meth:`add_sample`, :meth:`discard` and :meth:`step`; its ``samples.csv`` is rewritten
    after every change."""

    def __init__(self, journal: Journal, robot, *, limits: dict[str, Limit] | None = None,
                 limits_version: str | None = None, cell: Cell | None = None, options: dict | None = None,
                 replay: list[dict] | None = None, progress: Callable[[int, int, str], None] | None = None,
                 touch: TouchProvider | str | None = None, log: Callable[[str], None] | None = None,
                 prompt: Callable[[Question], str] | None = None, model: Model | None = None) -> None:
        self.journal = journal
        self.robot = robot
        self.model: Model = model if model is not None else robot.model
        if cell is not None and cell.tool:
            # the cell names the mounted tool: plans and solves start from it (the driver knows the arm only)
            self.model = self.model.with_params({f"tcp.{k}": v for k, v in cell.tool.items()})
        self.limits = limits or {}
        self.limits_version = limits_version
        self.cell = cell
        self.options = dict(options or {})
        # options the caller gave (--poses...), not the procedure's DEFAULTS: only those are held to rules such
        # as "poses >= unknowns" (a procedure's own default is its author's choice, e.g. verify does not solve)
        self.given: set[str] = set()
        # what the procedure declares it measures (station.engine.declare), by name; None: not declared
        self.declared: dict | None = None
        self.replay: list[ev.Event] = list(replay or [])  # events of the interrupted run (resume)
        self.progress = progress or (lambda done, total, text: None)
        self.log = log or (lambda text: None)
        self.prompt = prompt or terminal_prompt  # the operator's side of s.ask (terminal, panel)
        self._touch = touch
        self.current_plan: PosePlan | None = None
        self.result = None  # CalibrationResult of the last solve
        self.measurements: list[dict] = []
        self.verdict: dict | None = None
        self._events: list[ev.Event] = list(self.replay)
        self._aim: dict[str, list[np.ndarray]] = {}
        self.instruments: dict[str, object] = {}  # session option -> open instrument (closed by the teardown)
        self.steps = Steps(self.event)  # the running steps (station.engine.steps): name faults, aborts, moves
        # a technician's samples.csv follows every record and discard (the jog UI shows its path: station solve
        # reads it while the session is open); a procedure's is written when the run ends
        self.live_csv = journal.header.mode == "technician"

    # ---- journal ---------------------------------------------------------------------------------
    @property
    def id(self) -> str:
        return str(self.journal.header.get("session"))

    @property
    def folder(self) -> Path:
        return self.journal.path.parent

    @property
    def resumed(self) -> bool:
        return bool(self.replay)

    def event(self, event: ev.Event | dict) -> ev.Event:
        """Journal one event (a typed ``station.engine.events`` record, or a dict of one; a dict of a type the
        schema does not know is kept as a custom event). Fsynced when it returns."""
        if isinstance(event, dict):
            event = {**event, "session": self.id}
        else:
            event.session = self.id
        e = self.journal.append(event)
        self._events.append(e)
        return e

    def events(self, kind: str | None = None) -> list[ev.Event]:
        return [e for e in self._events if kind is None or e.type == kind]

    def record_dict(self) -> dict:
        """The session record (what ``station.records`` stores), projected from the journal so far."""
        return session_from_events(self.journal.header, self._events)

    def step(self, name: str, /, **info) -> contextlib.AbstractContextManager[steps.RunningStep]:
        """A step (``station.engine.steps``): journaled start with its arguments ``info``, then ``done`` or
        ``failed`` with its duration; a fault inside it is named after it. The decorator
        ``station.engine.steps.step`` makes a whole function one."""
        return self.steps.run(name, info)

    def end(self, status: str = "completed", passed: bool | None = None) -> None:
        """Journal the session's ``end`` (with the kept samples' count), then close the journal."""
        try:
            self.event(ev.End(status=status, passed=passed, n_samples=len(self.samples())))
        finally:
            self.journal.close()

    # ---- the operator ----------------------------------------------------------------------------
    def ask(self, question: Question | str, kind: str = "confirm", **spec) -> str | float:
        """Ask the operator (``Question``: confirm, number with unit and range, text with a pattern, choice)
        and return the checked value. The front end validates as the operator types; the answer is checked
        here again whatever gave it (the terminal and the panel ask again until it is valid; a front end that
        hands on a refused answer stops the run with ``BadAnswer``). An answer with a
        ``key`` is journaled, and a resumed session reuses it instead of asking again."""
        q = question if isinstance(question, Question) else Question(question, kind, **spec)
        if q.key:
            for e in reversed(self.events("answer")):
                if e["key"] == q.key:
                    return e["value"]
        value = q.check(self.prompt(q))
        if q.key:
            self.event({"type": "answer", "key": q.key, "question": q.text, "kind": q.kind, "unit": q.unit,
                        "value": value})
        return value

    # ---- connect and check -----------------------------------------------------------------------
    @steps.step()
    def connect(self) -> dict:
        """Connect and identify: the robot must be the one the session is for (serial, model)."""
        ident = adopt_serial(self.robot.identity(), self.journal.header.get("serial"))
        d = _identity_dict(ident)
        first = self.events("identity")
        if first and (first[0].robot.get("serial"), first[0].robot.get("model")) != (d["serial"], d["model"]):
            raise ResumeMismatch(f"resume: robot is {d['model']} {d['serial']!r}, the session was recorded on "
                                 f"{first[0].robot.get('model')} {first[0].robot.get('serial')!r}")
        self.event(ev.Identity(robot=d))
        return d

    @steps.step()
    def check_state(self) -> dict:
        """Check state: no fault/stop, powered, and (on resume) the device calibration unchanged since the
        samples were taken."""
        st = self.robot.status()
        if st.estop or st.protective_stop:
            raise SafetyStop(f"robot is in {'emergency' if st.estop else 'protective'} stop; clear it first")
        if st.faults:
            # latched faults a re-enable clears (e.g. a bus watchdog that tripped when the previous run died
            # mid-move) are journaled and cleared once; anything that persists stops the session
            self.event(ev.Warn(step="check_state", message="clearing faults: " + "; ".join(st.faults)))
            self.robot.enable()
            st = self.robot.status()
            if st.faults:  # some drives re-arm on the next command: hold where it stands (no motion)
                with contextlib.suppress(StationError):
                    self.robot.move_joints(self.robot.joint_positions().q)
                st = self.robot.status()
            if st.faults:
                raise DeviceFault(f"robot reports faults: {', '.join(st.faults)}")
        if not st.enabled:
            self.robot.enable()
        if st.compliant:
            self.robot.set_compliant(False)
        cal = self._read_calibration()
        q = self.robot.joint_positions().q
        prior = self.events("state")
        if prior and cal is not None and prior[0].calibration is not None:
            allowed = self._expected_calibrations(prior[0].calibration)
            mismatch = [[k for k, v in exp.items() if abs(cal.get(k, math.nan) - v) > self.cal_tolerance(k)]
                        for exp in allowed]
            if all(mismatch) and not self._write_cut(cal):
                k = mismatch[0][0]
                raise ResumeMismatch(f"resume: device calibration {k} is {cal.get(k)!r}, the journal expects "
                                     f"{allowed[0][k]!r}; the recorded samples no longer apply")
        out = {"enabled": True, "calibration": cal, "q": q.tolist()}
        self.event(ev.State(**out))
        return out

    def _read_calibration(self) -> dict[str, float] | None:
        if not isinstance(self.robot, CalibrationStore):
            return None
        cal = self.robot.read_calibration()
        return {k: float(v) for k, v in (cal or {}).items()} or None

    def _expected_calibrations(self, first: dict) -> list[dict]:
        """What the device may hold now: after a journaled write, the new values; while a write was under way
        (pre-image journaled, outcome not), either the pre-image or the new values."""
        wb = [e for e in self.events("writeback") if e.kind == "write"]
        if any(e.phase in ("written", "verified") for e in wb):
            return [dict(next(e.after for e in reversed(wb) if e.after))]
        pending = [e for e in wb if e.phase == "pre-image"]
        if pending:
            return [dict(pending[-1].before), dict(pending[-1].after)]
        return [dict(first)]

    def _write_cut(self, cal: dict) -> bool:
        """A write-back cut in the middle (kill -9, power loss): each joint holds its old or its new value. The
        write-back step finishes it; the samples were taken before it began."""
        from station.engine.writeback import finished_writes, resume_point

        wb = self.events("writeback")
        return not finished_writes(wb) and resume_point(wb, cal, self.cal_tolerance)[1] == "partial"

    def cal_tolerance(self, name: str) -> float:
        """How far a device calibration read now may be from one journaled earlier: one count plus rounding."""
        from station.engine.writeback import count_tolerance

        return count_tolerance(self.model, name, 1.5)

    def readback_tolerance(self, name: str) -> float:
        """How far a written value may read back: one encoder count (devices store whole counts)."""
        from station.engine.writeback import count_tolerance

        return count_tolerance(self.model, name, 1.0)

    # ---- measuring instruments (plugs the runner closes) ------------------------------------------
    def instrument(self, option: str = "tracker"):
        """The measuring instrument at the URL of the session option ``option`` (``--tracker URL``; a resume
        may give it a new address), opened through the ``station.instruments`` entry points and identified.
        Its identity is journaled (``instrument`` event); a resumed session refuses another instrument (it
        measures in another frame). Opened once per session; the runner closes it in its teardown."""
        from station.instruments.registry import open_instrument, url_examples

        inst = self.instruments.get(option)
        if inst is not None and not inst.closed:
            return inst
        url = self.options.get(option)
        if not url:
            raise ConfigError(f"{self.journal.header.get('procedure') or 'this procedure'} needs a measuring "
                              f"instrument: --{option} {url_examples()}")
        first = next((e for e in self.events("instrument") if e.data.get("option", "tracker") == option), None)
        with self.step(f"connect_{option}", url=url):
            inst = open_instrument(url)
            self.instruments[option] = inst  # from here on the teardown closes it, whatever fails next
            ident = inst.identity()
            if first is not None and not ident.same_as(first.data):
                was = first.data.get("model") or (first.data.get("spec") or {}).get("model")
                was = f"serial {first.data.get('serial')!r}" + (f" model {was!r}" if was else "")
                raise ConfigError(f"instrument at {url} is {ident.describe()}, the session started with {was}: "
                                  "another instrument measures in another frame; reconnect that one, or start a "
                                  "new session")
            self.event({"type": "instrument", "option": option, "url": url, **ident.to_dict()})
        return inst

    @steps.step("measure", args=("pose",))
    def measure_pose(self, pose: PlannedPose, instrument=None, **status) -> ev.Sample:
        """Read all joints, then the instrument (it answers once the probe stands still), then the joints
        again: a robot that moved in between is a fault, not a sample. The 6-DoF reading (instrument frame) is
        journaled with the joints (fsynced) before the next move. ``instrument``: an open instrument or the
        option it was opened for (default: the only one open)."""
        inst = self._instrument_for(instrument)
        snap = self.robot.joint_positions()
        reading = inst.measure()
        again = self.robot.joint_positions()
        q, q2 = np.asarray(snap.q, float), np.asarray(again.q, float)
        if not np.all(np.isfinite(q)) or np.max(np.abs(q2 - q)) > 1e-6:
            raise DeviceFault(f"measure: the robot moved while the instrument measured pose {pose.index} "
                              f"(joints changed by {np.max(np.abs(q2 - q)):.3g})")
        return self.add_sample(snap, pose.point, pose=pose, status=status, reading=reading,
                               instrument=inst.identity().serial)

    def _instrument_for(self, which):
        if which is not None and not isinstance(which, str):
            return which
        if isinstance(which, str):
            return self.instrument(which)
        open_ = [i for i in self.instruments.values() if not i.closed]
        if len(open_) != 1:
            raise ConfigError(f"measure_pose: {len(open_)} instruments are open; say which one")
        return open_[0]

    def close_instruments(self) -> list[str]:
        """Close every instrument this session opened (teardown: each is tried; failures are returned)."""
        problems = []
        for option, inst in list(self.instruments.items()):
            try:
                inst.close()
            except Exception as e:  # teardown must try everything; the caller journals what failed
                problems.append(f"{option} instrument close: {type(e).__name__}: {e}")
        return problems

    def instrument_sigma(self, distance):
        """The per-axis noise (1 sigma, m) the session's instrument states for itself at ``distance`` (m, a number
        or an array) from it: ``sigma0_m + sigma_per_m * distance`` of its journaled identity's ``spec``; None when
        it states none (nothing to compare with)."""
        spec = next((e.data.get("spec") or {} for e in reversed(self.events("instrument"))), {})
        try:
            return float(spec["sigma0_m"]) + float(spec["sigma_per_m"]) * np.asarray(distance, float)
        except (KeyError, TypeError, ValueError):
            return None

    # ---- reference points and plans -------------------------------------------------------------
    @property
    def keep_out(self):
        """The cell's mounting plane and keep-out volumes; None without a cell (nothing below the base plane)."""
        return self.cell.keep_out if self.cell else None

    def checker(self):
        """A collision checker of the robot's links against :attr:`keep_out` (``station.kinematics.collision``)."""
        from station.engine.plan import keep_out_checker

        return keep_out_checker(self.model, self.keep_out)

    def point(self, label: str) -> RefPoint:
        if self.cell is None:
            raise ConfigError("this procedure needs a cell file (--cell FILE or $STATION_CELL or ./cell.yaml)")
        return self.cell.point(label)

    def points(self, kind: str | None = None, labels: list[str] | None = None) -> list[RefPoint]:
        if self.cell is None:
            raise ConfigError("this procedure needs a cell file (--cell FILE or $STATION_CELL or ./cell.yaml)")
        if labels:
            return [self.cell.point(lb) for lb in labels]
        pts = list(self.cell.points.values()) if kind is None else self.cell.of_kind(kind)
        if not pts:
            raise ConfigError(f"cell {self.cell.path} has no {kind or ''} reference point".replace("  ", " "))
        return pts

    def journaled_plan(self) -> PosePlan | None:
        """The plan this session journaled (a resumed session reuses exactly the same poses; also a procedure that
        plans its own), now ``current_plan``; None before one is journaled. A plan for another number of joints
        than the robot's is one line."""
        old = self.events("plan")
        if not old:
            return None
        plan = PosePlan.from_dict(old[-1].plan)  # its shapes and bounds were checked when it was read
        n = self.model.n_joints
        bad = next((p for p in plan.poses if len(p.q) != n), None)
        if bad is not None:
            raise ConfigError(f"journal {self.journal.path}: plan event {old[-1].seq}: pose {bad.index} has "
                              f"{len(bad.q)} joint values, the robot's model {self.model.name} has {n}; the "
                              "journaled plan is not for this robot")
        self.current_plan = plan
        return plan

    def plan(self, points: list[RefPoint] | None = None, *, identify: str = "offsets", n_fit: int | None = None,
             n_holdout: int | None = None, listed: list[dict] | None = None, **kw) -> PosePlan:
        """The pose plan: generated for ``points`` (or ``listed`` joint positions); journaled, so a resumed
        session reuses exactly the same poses."""
        journaled = self.journaled_plan()
        if journaled is not None:
            return journaled
        identify = self.identify(identify)
        with self.step("plan"):
            q0 = self.robot.joint_positions().q
            opt = self.options
            n_fit = n_fit or opt.get("n_fit")
            n_holdout = opt.get("n_holdout", 4) if n_holdout is None else n_holdout
            rotate = kw.pop("rotate_joint", None)
            kw.setdefault("keep_out", self.keep_out)
            if listed is None and "n_fit" in self.given:  # --poses: at least one pose per unknown
                pts = [(points or self.points("socket"))[0]] if rotate is not None else (
                    points or self.points("socket")[:1])
                self.check_poses(int(opt["n_fit"]), identify, pts)
            if rotate is not None:
                from station.engine.plan import generate_rotation_plan

                plan = generate_rotation_plan(self.model, (points or self.points("socket"))[0], q0, joint=rotate,
                                              n_fit=n_fit or 8, n_holdout=n_holdout, **kw)
            elif listed is not None:
                plan = plan_from_joints(self.model, listed, self.cell.points if self.cell else {}, q_start=q0,
                                        keep_out=kw["keep_out"])
            else:
                for key in ("cone_deg", "clearance", "roll_deg", "margin_deg"):
                    if key in opt:
                        kw.setdefault(key, float(opt[key]))
                plan = generate_plan(self.model, points or self.points("socket")[:1], q0, identify=identify,
                                     n_fit=n_fit, n_holdout=n_holdout, seed=int(opt.get("seed", 0)), **kw)
            self.check_plan(plan, identify)  # before anything moves: can these poses meet the limits at all?
            self.event(ev.Plan(plan=plan.to_dict()))
        self.current_plan = plan
        return plan

    def identify(self, group: str) -> str:
        """The group a plan or solve is for: the procedure's ``group``, or what the run was given
        (``station run --identify GROUPS``, journaled with the options: a resume solves for the same)."""
        given = self.options.get("identify")
        if not given:
            return group
        try:
            self.model.select(str(given))
        except KeyError as e:
            raise ConfigError(f"--identify {given!r}: {e.args[0]}") from None
        return str(given)

    def check_poses(self, n_fit: int, identify: str, points: list[RefPoint]) -> None:
        """``--poses`` must be at least the unknowns of the procedure's group (its model parameters plus the
        coordinates of every reference point solved as unknown): fewer poses leave the fit without the
        redundancy that tells a bad touch from a good one. One line, before anything moves (ConfigError)."""
        known = self.options.get("reference") == "cell" and self.cell is not None
        names = self.model.select(identify) if identify else []
        n_points = 0 if known else len(points)
        need = len(names) + 3 * n_points
        if n_fit < need:
            raise ConfigError(f"--poses {n_fit}: the procedure identifies {identify!r}: {need} unknowns "
                              f"({len(names)} model parameters + {3 * n_points} reference point coordinates); give "
                              f"--poses {need} or more (nothing moved)")

    def check_plan(self, plan: PosePlan, identify: str) -> None:
        """Plan-time check (docs/solver.md, "prediction"): the posterior the planned fit poses would give, with
        an optimistic touch noise (``options["plan_noise_m"]``, default PLAN_NOISE_M: a refusal must mean "cannot
        pass", never "might not"), against the procedure's ``identified`` and ``offset_std_max`` limits. A plan
        that cannot meet them is refused in one line naming what stays unseen and what would fix it, before the
        robot moves (ConfigError, exit 2)."""
        lim_n, lim_std = self.limits.get("identified"), self.limits.get("offset_std_max")
        fit = [p for p in plan.poses if p.set == "fit"]
        if (lim_n is None and lim_std is None) or not fit:
            return
        from station.solver import SolverInputError, predict

        ref = self.options.get("reference", "unknown")
        if ref == "cell":
            ref = {lb: p.position for lb, p in self.cell.points.items()} if self.cell else "unknown"
        noise = float(self.options.get("plan_noise_m", PLAN_NOISE_M))
        try:
            pred = predict(self.model, np.array([p.q for p in fit]), [p.point for p in fit], identify, ref,
                           noise=noise)
        except SolverInputError as e:
            raise ConfigError(f"plan: {e}") from None
        seen = {n: p for n, p in pred.parameters.items() if p.identifiable}
        problems = []
        if lim_n is not None and lim_n.low is not None:
            have = lim_n.judge(float(len(seen)), "number")
            if not have["passed"]:
                missing = "; ".join(f"{n}: {why}" for n, why in pred.missing.items())
                problems.append(f"these poses can identify {len(seen)} parameter(s), the limits need "
                                f"{lim_n.low:g} ({missing})")
        rev = {n: p.std for n, p in seen.items() if n.startswith("offset.") and p.std is not None
               and param_quantity(n, self.model) == "angle"}
        if lim_std is not None and rev:
            name = max(rev, key=rev.get)
            worst = lim_std.judge(rev[name], "angle")
            if not worst["passed"]:
                problems.append(f"offset_std_max would be at least {worst['value']:.3g} {worst['unit']} ({name}) "
                                f"even at {noise * 1e6:g} um touch noise, limit {lim_std.high:g} {lim_std.unit} ("
                                + self._std_fix(fit, identify, ref, noise, name, lim_std) + ")")
        if problems:
            raise ConfigError("plan: the planned poses cannot meet the limits, nothing moved: " + "; ".join(problems))

    def _std_fix(self, fit: list, identify: str, ref, noise: float, name: str, lim_std: Limit) -> str:
        """What would bring ``name``'s std inside the limit. A joint zero seen only through a short lever (a
        tool tip a fraction of a millimetre off the last axis) is the tool's rotation about that axis in
        disguise: solved together with the tool it is named unidentifiable, and every other zero keeps its
        std. Checked on the same poses before it is offered."""
        from station.solver import SolverInputError, predict

        if "tcp" not in identify.split(","):
            group = f"{identify},tcp"
            try:
                pred = predict(self.model, np.array([p.q for p in fit]), [p.point for p in fit], group, ref,
                               noise=noise)
                stds = [p.std for n, p in pred.parameters.items() if n.startswith("offset.") and p.identifiable
                        and p.std is not None and param_quantity(n, self.model) == "angle"]
                if stds and lim_std.judge(max(stds), "angle")["passed"]:
                    return f"{name} is seen through the tool's lever only: solve it with the tool, --identify {group}"
            except (SolverInputError, KeyError):
                pass
        return "more poses, a wider pose spread (--cone), or a known reference position"

    def todo(self, plan: PosePlan | None = None) -> Iterator[PlannedPose]:
        """The poses not yet recorded, in plan order (a resumed session does not repeat recorded samples)."""
        plan = plan or self.current_plan
        total = len(plan)
        for pose in plan.poses:
            done = self._recorded_poses()
            self.progress(len(done), total, f"pose {pose.index + 1}/{total} ({pose.point}, {pose.set})")
            if pose.index in done:
                continue
            yield pose
        self.progress(total, total, "all poses recorded")

    def _recorded_poses(self) -> set[int]:
        return {s.pose for s in live_samples(self._events)}

    # ---- motion ----------------------------------------------------------------------------------
    def check_space(self, what: str) -> None:
        """Enough free space for the journal before ``what`` moves the robot (docs/reliability.md)."""
        from station.engine.journal import check_space

        check_space(self.folder, f"not starting {what}")

    def _references(self) -> tuple:
        """The cell's reference points: bodies the tool's tip stays out of on moves between poses."""
        return tuple(self.cell.points.values()) if self.cell is not None else ()

    def move_to(self, q, speed: float | None = None) -> None:
        self.check_space("a move")
        self.robot.move_joints(np.asarray(q, float), speed=speed)

    def move_along(self, targets: list, what: str) -> None:
        """Through ``targets`` (joint positions, in order) from where the arm stands, along a path clear of the
        keep-outs (vias where a straight one is blocked; refused in one line naming ``what`` if none is clear:
        ``station.engine.plan.route_from``), each move by :meth:`move_to`."""
        from station.engine.plan import route_from

        for q in route_from(self.model, self.keep_out, self.robot.joint_positions().q, targets, what=what,
                            points=self._references()):
            self.move_to(q)

    @steps.step(args=("pose",))
    def approach(self, pose: PlannedPose) -> None:
        """Move above the reference (approach pose of the plan) through the plan's via poses; the path from where
        the arm stands (e.g. after a resume) is checked against the keep-outs first, refused in one line."""
        from station.engine.plan import route_from

        self.check_space(f"the approach to pose {pose.index}")
        for q in route_from(self.model, self.keep_out, self.robot.joint_positions().q, [*pose.via, pose.approach_q],
                            what=f"pose {pose.index}", points=self._references()):
            self.robot.move_joints(q)

    def touch_speed(self, q_from, q_to) -> float:
        from station.robot.motion import joint_speed_for_tool_cap

        return joint_speed_for_tool_cap(self.model, q_from, q_to, None, cap=APPROACH_TOOL_SPEED)

    def aimed_q(self, pose: PlannedPose) -> np.ndarray:
        """Touch target corrected by where earlier seatings put this point in the nominal model."""
        seen = self._aim.get(pose.point) or [self.model.position(np.asarray(s.q))
                                             for s in live_samples(self._events) if s.point == pose.point]
        if not seen or self.cell is None or pose.point not in self.cell.points:
            return pose.q_arr
        self._aim[pose.point] = list(seen)
        target = self.model.fk(pose.q_arr)
        target[:3, 3] = np.mean(seen, axis=0)
        full = self.model.n_joints >= 6
        r = self.model.ik(target if full else target[:3, 3], pose.q_arr, position_only=not full)
        if not r.ok[0] or np.max(np.abs(r.q[0] - pose.q_arr)) > 0.1:
            return pose.q_arr
        return r.q[0]

    @property
    def toucher(self) -> TouchProvider:
        if self._touch is None or isinstance(self._touch, str):
            kind = "socket"
            if self.current_plan and self.current_plan.poses and self.cell:
                kind = self.cell.point(self.current_plan.poses[0].point).kind
            self._touch = provider_for(kind, self._touch if isinstance(self._touch, str) else
                                       self.options.get("touch"))
        return self._touch

    @steps.step(args=("pose",))
    def seat(self, pose: PlannedPose) -> None:
        """Bring the tip onto the reference (socket seating, guarded contact or the technician)."""
        self.check_space(f"seating at pose {pose.index}")
        self.toucher.bring_to(self, pose)

    @steps.step(args=("pose",))
    def leave(self, pose: PlannedPose) -> None:
        """Leave the reference: compliance off, back to the approach pose."""
        self.toucher.release(self, pose)

    # ---- samples ---------------------------------------------------------------------------------
    @steps.step(args=("pose",))
    def record(self, pose: PlannedPose | None = None, point: str | None = None, measured=None) -> ev.Sample:
        """Read all joints in one transaction and journal the sample (fsynced before the next motion)."""
        snap = self.robot.joint_positions()
        touch = self.robot.touch() if isinstance(self.robot, ContactSensor) else None
        if touch is False:
            raise DeviceFault(f"record: touch indicator is off at pose {pose.index if pose else '?'}; the tip is "
                              "not on the reference")
        return self.add_sample(snap, point or (pose.point if pose else "A"), pose=pose, status={"touch": touch},
                               measured=measured)

    def add_sample(self, snap, point: str, *, pose: PlannedPose | int | None = None, status: dict | None = None,
                   reading=None, instrument: str | None = None, measured=None) -> ev.Sample:
        """Journal one sample taken from the joint reading ``snap`` (fsynced when it returns): the one way a
        sample reaches a journal (``record``, ``measure_pose`` and the jog UI come here; the event is built by
        ``events.Sample.from_snapshot``). ``pose``: the planned pose (its index and set; its point's aim) or a
        technician's touch number; ``status``: what the taker knows of the touch; ``reading``/``instrument``/
        ``measured``: an instrument's measurement. A joint reading that is not finite is a device fault."""
        q = np.asarray(snap.q, float)
        if not np.all(np.isfinite(q)):
            raise DeviceFault(f"record: joint reading is not finite: {q.tolist()}")
        planned = pose if isinstance(pose, PlannedPose) else None
        sample = self.event(ev.Sample.from_snapshot(
            snap, point, pose=planned.index if planned else pose, set=planned.set if planned else "fit",
            status=status, reading=reading, instrument=instrument, measured=measured))
        if planned is not None:
            self._aim.setdefault(planned.point, []).append(self.model.position(q))
        if self.live_csv:
            self.write_samples_csv()
        return sample

    def discard(self, sample: ev.Sample | int, reason: str = "") -> None:
        """Leave a recorded sample (or the sample with journal sequence number ``sample``) out of solves and
        records; journaled, never erased."""
        self.event(ev.Discard(sample=int(sample.seq if isinstance(sample, ev.Sample) else sample), reason=reason))
        if self.live_csv:
            self.write_samples_csv()

    @property
    def samples_csv(self) -> Path:
        return self.folder / "samples.csv"

    def write_samples_csv(self) -> None:
        """The kept samples as ``samples.csv`` beside the journal (``station solve --samples`` reads it)."""
        from station.samplesfile import joint_units, write_samples_csv

        write_samples_csv(self.samples_csv, self.samples(), joint_units(self.model),
                          comment=f"session {self.id}, model {self.model.name}")

    def samples(self, which: str | None = None) -> list[ev.Sample]:
        """The kept samples (``station.engine.events.Sample``), of one set (``fit``/``holdout``) if given."""
        return [s for s in live_samples(self._events) if which is None or s.set == which]

    # ---- solve, measure, judge ------------------------------------------------------------------
    def observations(self, which: str = "fit"):
        from station.solver import Observations

        smp = self.samples(which)
        if not smp:
            return None
        meas = [s.measured for s in smp]
        measured = np.array(meas, float) if all(m is not None for m in meas) else None
        return Observations(np.array([s.q for s in smp]), np.array([s.point for s in smp], dtype=object), measured)

    def solve(self, identify: str = "offsets", reference: str | dict | None = None, **kw):
        """Identify ``identify`` from the fit samples, check on the held-out samples; journals the result."""
        from station.solver import solve

        identify = self.identify(identify)
        with self.step("solve", identify=identify):
            fit = self.observations("fit")
            if fit is None:
                raise ConfigError("solve: no fit samples recorded")
            ref = reference or self.options.get("reference", "unknown")
            if ref == "cell":
                ref = {lb: p.position for lb, p in self.cell.points.items()} if self.cell else "unknown"
            if self.cell is not None:  # the cell's known distances and planes (station/engine/cell.py) among
                touched = set(fit.labels)  # the points this procedure touched
                kw.setdefault("distances", [d for d in getattr(self.cell, "distances", None) or []
                                            if d[0] in touched and d[1] in touched] or None)
                kw.setdefault("planes", [p for p in getattr(self.cell, "planes", None) or [] if p in touched] or None)
            self.result = solve(self.model, fit, identify=identify, reference=ref,
                                holdout=self.observations("holdout"), **kw)
            self.event(ev.Result(result=self.result.to_dict()))
        return self.result

    def measure(self, name: str, value_si: float | None, quantity: str = "length") -> dict:
        """A measurement, judged against the limits file (a measurement without a limit is informational). A
        procedure that declares its measurements (``@measures``) measures only those, in their quantity."""
        if self.declared is not None:
            d = self.declared.get(name)
            if d is None or d.quantity != quantity:
                raise ConfigError(f"procedure {self.journal.header.procedure}: measures {name!r} ({quantity}), "
                                  + ("which it does not declare (@measures)" if d is None else
                                     f"declared as a {d.quantity} ({d.unit})"))
        lim = self.limits.get(name)
        if lim is not None:
            m = lim.judge(value_si, quantity)
        else:
            unit, k = human(quantity)
            m = {"name": name, "value": None if value_si is None else value_si * k, "unit": unit,
                 "low": None, "high": None, "marginal": False, "passed": True, "note": "no limit (informational)"}
        m["quantity"] = quantity
        self.measurements = [x for x in self.measurements if x["name"] != name] + [m]
        self.event({"type": "measurement", **m})  # checked against events.Measurement
        return m

    def measure_result(self, result=None) -> list[dict]:
        """The standard measurements of a solve: fit and holdout residuals, identified offsets and their
        uncertainty, how many parameters the data identified."""
        res = result or self.result
        r = res.residuals
        out = [self.measure("samples", float(res.n_samples), "number"),
               self.measure("fit_rms", r.get("rms_after_m")), self.measure("fit_max", r.get("max_after_m")),
               self.measure("identified", float(len([n for n, p in res.parameters.items()
                                                      if p.identifiable and p.kind == "model"])), "number")]
        if res.holdout:
            out += [self.measure("holdout_rms", res.holdout.get("rms_m")),
                    self.measure("holdout_max", res.holdout.get("max_m"))]
        offs = {n: p for n, p in res.parameters.items() if n.startswith("offset.") and p.identifiable}
        rev = [p for n, p in offs.items() if param_quantity(n, self.model) == "angle"]
        if rev:
            out.append(self.measure("offset_abs_max", max(abs(p.value - p.nominal) for p in rev), "angle"))
            out.append(self.measure("offset_std_max", max(p.std or 0.0 for p in rev), "angle"))
        return out

    def measure_consistency(self) -> list[dict]:
        """Held-out check without solving: with the robot's current calibration, the nominal model must put
        the tip on the same spot at every touch of a point (spread about each point's centroid)."""
        d = []
        for label in dict.fromkeys(s.point for s in self.samples()):
            q = np.array([s.q for s in self.samples() if s.point == label])
            P = self.model.position(q)
            d.extend(np.linalg.norm(P - P.mean(axis=0), axis=1).tolist())
        if not d:
            raise ConfigError("verify: no samples recorded")
        return [self.measure("samples", float(len(d)), "number"),
                self.measure("verify_rms", float(np.sqrt(np.mean(np.square(d))))),
                self.measure("verify_max", float(np.max(d)))]

    @steps.step()
    def judge(self) -> dict:
        """Verdict: every limit of this procedure and model must be measured and inside its bounds."""
        names = {m["name"] for m in self.measurements}
        for name, lim in self.limits.items():
            if name not in names:
                try:
                    self.measurements.append({**lim.judge(None, lim.quantity), "quantity": lim.quantity})
                except LimitsError:
                    raise
        if not self.limits:  # informational measurements only: nothing a quality engineer could sign
            self.verdict = {"passed": None, "status": NO_LIMITS, "measurements": self.measurements,
                            "limits_version": self.limits_version}
        else:
            self.verdict = {"passed": all(m["passed"] for m in self.measurements),
                            "measurements": self.measurements, "limits_version": self.limits_version}
        self.event(ev.Verdict(**self.verdict))
        return self.verdict

    # ---- write-back ------------------------------------------------------------------------------
    def write_back(self, check_pose: PlannedPose | None = None) -> dict | None:
        """Two-phase write of the identified joint offsets into the devices (only with ``apply``): journal the
        pre-image, write, read back, then verify with a touch at a known pose."""
        from station.engine.writeback import write_back

        if not self.options.get("apply"):
            self.steps.skip("write_back", "not requested (--apply)")
            return None
        if self.verdict is not None and not self.verdict["passed"]:
            self.steps.skip("write_back", f"verdict {self.verdict.get('status') or 'FAIL'}")
            return None
        with self.step("write_back"):
            return write_back(self, check_pose)

    # ---- teardown --------------------------------------------------------------------------------
    def safe_state(self) -> list[str]:
        """Stop motion, leave compliant mode. Best effort: every action is tried, failures are returned."""
        problems = []
        actions = [("stop", self.robot.stop)]
        if isinstance(self.robot, Compliant):
            actions.append(("compliance off", lambda: self.robot.set_compliant(False)))
        for what, fn in actions:
            try:
                fn()
            except Exception as e:  # teardown must try everything; the caller journals what failed
                problems.append(f"{what}: {type(e).__name__}: {e}")
        return problems


def _identity_dict(ident) -> dict:
    from dataclasses import asdict

    d = asdict(ident)
    d["devices"] = [dict(x) for x in d.get("devices") or ()]
    return d


def wait_idle(robot, timeout: float = 30.0) -> None:
    end = time.monotonic() + timeout
    while robot.status().moving and time.monotonic() < end:
        time.sleep(0.005)
