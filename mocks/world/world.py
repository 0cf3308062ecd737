"""The simulated world: one robot with hidden kinematic errors, its joint motion, and a calibration cell.

Every emulator serves this object's state over its wire; tests read the hidden truth from it. All
public methods take one re-entrant lock, so emulator threads may call them concurrently.

Joint state is the motor/encoder position ``q`` (SI). The true joint value seen by the kinematics is
``q_joint = theta`` with ``theta = q - side * backlash/2 + C * tau(theta)`` (backlash, and gravity compliance
under the torque ``tau`` of the link masses and payload: ``physics.Gravity``; off by default), and the true
tip is ``truth.fk(q_joint)`` (``truth`` is rigid: its compliance parameters are zero).

A joint follows its motion profile (``motion.Track``) unless it is free (disabled without a brake),
torque-commanded, or position-controlled under a torque limit gravity exceeds: those are integrated by
``dynamics.Dynamics`` (``_integrate``) and their state overlays the profile's (``_state``)."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from station.mocks.world import dynamics, motion
from station.mocks.world.cell import DEFAULTS, Cell, CellPoint, KeepOutTruth
from station.mocks.world.faults import Faults
from station.mocks.world.physics import Gravity, Rigid
from station.mocks.world.worldfile import (
    FORMAT,
    TIME_MODES,
    WorldFileError,
    WorldSpec,
    load_world_doc,
    param_kind,
    spec_from_dict,
    spec_to_dict,
)

from station.kinematics import Model, load_model
from station.kinematics.modelfile import ModelFileError

log = logging.getLogger("station.mocks.world")
TRACK, FREE, TORQUE, SATURATED = 0, 1, 2, 3  # joint modes: on its profile, or integrated (dynamics.py)
WATCH_PERIOD = 0.01  # s of world time between two looks of the keep-out watch while the arm moves

# sigmas of the hidden errors of World.default (SI)
DEFAULT_SIGMAS = {"offsets": {"length": 0.1e-3, "angle": math.radians(0.1)},
                  "dh": {"length": 0.2e-3, "angle": math.radians(0.02)},
                  "tcp": {"length": 0.5e-3}}


def default_doc(model: str = "ur5e", seed: int = 0) -> dict:
    """The world document of ``World.default`` (SI units), before overrides."""
    doc: dict = {"format": FORMAT, "description": f"default world for {model}",
                 "units": {"length": "m", "angle": "rad", "time": "s", "mass": "kg"}, "seed": int(seed),
                 "robot": {"model": model},
                 "errors": {"random": {k: dict(v) for k, v in DEFAULT_SIGMAS.items()}},
                 "motion": {"time_mode": "instant", "time_scale": 1.0}}
    if model not in DEFAULTS:
        doc["cell"] = {"points": []}
    return doc


@dataclass(frozen=True)
class Snapshot:
    t: float  # world time, s
    q: np.ndarray  # encoder positions (SI), with encoder noise if configured
    qd: np.ndarray  # velocities (SI/s)
    moving: np.ndarray  # per joint: profile running
    contact: bool
    enabled: np.ndarray
    compliant: bool
    seated: str | None


def _hidden_errors(spec: WorldSpec, nominal: Model, g_err: np.random.Generator) -> dict[str, float]:
    """The robot's hidden errors (SI), non-zero ones in model order: one standard normal per model parameter,
    scaled by the sigma of the most specific selector that names it (neither the order of selectors nor adding
    one elsewhere changes a draw), then the world file's explicit values."""
    z = g_err.standard_normal(len(nominal.param_names))
    chosen: dict[str, tuple[int, str, float]] = {}
    for sel, sl, sa in spec.random:
        names = [n for n in nominal.select(sel) if not n.startswith("compliance.")]
        for name in names:
            sigma = (sl if param_kind(nominal, name) == "length" else sa) or 0.0
            key = (len(names), sel, sigma)
            if name not in chosen or key[:2] < chosen[name][:2]:
                chosen[name] = key
    errors = {n: float(z[nominal.index(n)] * c[2]) for n, c in chosen.items()}
    errors.update(spec.explicit)
    errors = {n: errors[n] for n in nominal.param_names if n in errors}  # model order
    return {n: v for n, v in errors.items() if v != 0.0}


class World:
    """The truth behind every emulator. Build with :meth:`from_file`, :meth:`from_dict`, :meth:`default`."""

    def __init__(self, spec: WorldSpec) -> None:
        self.spec = spec
        self._lock = threading.RLock()
        nominal = load_model(spec.model, tip_link=spec.tip_link, base_link=spec.base_link)
        if spec.tool:
            nominal = nominal.with_params({f"tcp.{k}": v for k, v in spec.tool.items()})
        self.nominal: Model = nominal
        # independent streams, so that e.g. more seatings never change the hidden errors
        g_err, g_seat, g_survey, self._g_enc, self._g_pos = (
            np.random.default_rng(s) for s in np.random.SeedSequence(spec.seed).spawn(5))
        self._errors = _hidden_errors(spec, nominal, g_err)
        n = nominal.n_joints
        # the robot's own compliance (joints.compliance, else the model's compliance.jN) acts through physics:
        # the truth model itself is rigid
        self._compliance = np.zeros(n)
        for i in range(n):
            name = f"compliance.j{i + 1}"
            self._compliance[i] = spec.compliance.get(i, nominal.param(name) if name in nominal.param_names else 0.0)
        rigid = {c: 0.0 for c in nominal.param_names if c.startswith("compliance.")}
        self.truth: Model = nominal.with_params({**rigid, **{n_: nominal.param(n_) + v
                                                             for n_, v in self._errors.items()}})
        self.n_joints = n
        self._vmax = np.array([j.max_velocity for j in self.truth.joints])
        self._amax = np.array([j.max_acceleration for j in self.truth.joints])
        self.lower, self.upper = self.truth.lower, self.truth.upper
        self._backlash = np.zeros(n)
        self._pos_err = np.zeros(n)  # link vs encoder after the last move of each joint (noise.positioning)
        for i, b in spec.backlash.items():
            self._backlash[i] = b
        self.gravity = self._gravity_truth(spec, nominal)
        self.cell = Cell(spec, g_survey, g_seat)
        self.points: dict[str, CellPoint] = self.cell.points
        self.faults = Faults()
        self._arm_file_faults(spec.faults)
        self.keep_out = KeepOutTruth(self.truth, spec.keep_out)  # the floor and fixtures the links can hit
        self.collisions: list[str] = []  # every contact of a link with them, in order (the truth tests read)
        self.events: deque[tuple[float, str]] = deque(maxlen=500)
        # time
        if spec.time_mode not in TIME_MODES:
            raise WorldFileError(f"time_mode {spec.time_mode!r} is not one of {', '.join(TIME_MODES)}")
        self.time_mode = spec.time_mode
        self.time_scale = spec.time_scale
        self._t = 0.0
        self._mono0 = time.monotonic()
        self._init_joints(spec)

    def _init_joints(self, spec: WorldSpec) -> None:
        """The joints at the start: held on their profiles at ``motion.start`` (within the limits), enabled as
        the world file says, brakes, and the state of joints off their profile (dynamics.py)."""
        n = self.n_joints
        q0 = np.zeros(n) if spec.start is None else np.asarray(spec.start, dtype=float)
        q0 = np.clip(q0, self.lower, self.upper)
        self._version = 0
        self._cache: tuple | None = None  # (key, q_joint): FK-free reads while the arm stands still
        self._tracks = [motion.hold(0.0, float(x)) for x in q0]
        self._watched_q = q0.copy()  # where the keep-out watch last saw the arm, and when
        self._watched_t = 0.0
        self._watched_rest: int | None = None  # motion version at which the watch last saw the arm at rest
        self._enabled = np.full(n, bool(spec.enabled))
        self._compliant = False
        self._seated: str | None = None
        self._seat_target: np.ndarray | None = None
        self._seat_failed: np.ndarray | None = None
        self._joint_faults: dict[int, int] = {}
        self._pstop = False
        # brakes: the world file's joints.brakes; unsaid, every joint has one until the emulator states its
        # device's default (default_brakes: a DYNAMIXEL servo has none)
        self._brakes_said = spec.brakes is not None
        self._brakes = np.ones(n, dtype=bool) if spec.brakes is None else np.array(spec.brakes, dtype=bool)
        # joints off their profile (dynamics.py): mode per joint, their state, what the motor applies
        self._mode = np.full(n, TRACK)
        self._dyn_x = q0.copy()
        self._dyn_v = np.zeros(n)
        self._dyn_side = np.ones(n)
        self._dyn_t = 0.0
        self._dyn_rest = True  # every dynamic joint at rest while nothing else moves: no integration needed
        self._tau_cmd = np.zeros(n)  # torque mode set-points, N m
        self._tau_limit = np.full(n, np.inf)  # motor torque limits, N m (inf: none)
        self._tau_motor = np.zeros(n)  # what each free/torque/saturated joint's motor applied last, N m
        self.__dynamics: dynamics.Dynamics | None = None

    # ---- construction -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, doc: dict, where: str = "<world>") -> World:
        return cls(spec_from_dict(doc, where))

    @classmethod
    def from_file(cls, path: str | Path) -> World:
        return cls(spec_from_dict(load_world_doc(path), str(path)))

    @classmethod
    def default(cls, model: str = "ur5e", seed: int = 0, **overrides) -> World:
        """A default world for a built-in model. ``overrides``: ``time_mode``, ``time_scale``, ``start``
        (SI), ``enabled``, or whole sections of the world document (``errors``, ``cell``, ``noise``,
        ``joints``, ``buses``, ...) in SI units (m, rad)."""
        doc = default_doc(model, seed)
        for k, v in overrides.items():
            if k in ("time_mode", "time_scale", "start", "enabled"):
                doc["motion"][k] = list(np.asarray(v, dtype=float)) if k == "start" else v
            elif k in ("errors", "cell", "noise", "joints", "buses", "robot", "description", "motion"):
                doc[k] = v
            else:
                raise TypeError(f"World.default: unknown override {k!r}")
        try:
            return cls.from_dict(doc, f"<default world {model}>")
        except ModelFileError as e:
            raise WorldFileError(str(e)) from None

    def to_dict(self, length: str = "m", angle: str = "rad", *, frozen: bool = False) -> dict:
        """The world document (loads back to an identical world). ``frozen``: the drawn random errors
        written out as explicit errors, so the file no longer depends on the seed for its truth."""
        spec = self.spec
        if frozen:
            from dataclasses import replace

            spec = replace(spec, explicit=dict(self._errors), random=[])
        return spec_to_dict(spec, self.nominal, length, angle)

    # ---- time ---------------------------------------------------------------------------------
    def now(self) -> float:
        """World time (s): simulated in ``instant``/``sim`` mode, scaled wall clock in ``realtime``."""
        with self._lock:
            if self.time_mode == "realtime":
                return (time.monotonic() - self._mono0) * self.time_scale
            return self._t

    def set_time_scale(self, scale: float) -> None:
        """Change the realtime speed-up without a jump in world time."""
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"time_scale must be a positive number, got {scale!r}")
        with self._lock:
            t = self.now()
            self._mono0 = time.monotonic() - t / scale
            self.time_scale = float(scale)

    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds of simulated time pass (``sim`` and ``instant`` mode)."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"advance: dt must be a finite non-negative number of seconds, got {dt!r}")
        with self._lock:
            if self.time_mode == "realtime":
                raise RuntimeError("advance() is for sim/instant time; a realtime world follows the clock")
            self._t += dt
            self._update()

    def run_until_idle(self, max_time: float = 3600.0, step: float | None = None) -> float:
        """Advance simulated time to the end of the current motion (sim/instant); returns the time spent.
        In realtime mode, sleeps until motion ends (bounded by ``max_time`` world seconds)."""
        with self._lock:
            t0 = self.now()
            if self.time_mode != "realtime":
                end = max([tr.t_end for tr in self._tracks] + [t0])
                if step is None:
                    self._t = min(end, t0 + max_time)
                else:
                    while self._t < min(end, t0 + max_time):
                        self._t = min(self._t + step, end)
                self._update()
                # joints off their profiles (falling, pushed, sagging) come to rest in their own time
                while self._moving_now(self._t).any() and self._t - t0 < max_time:
                    self._t = min(self._t + (step or 0.05), t0 + max_time)
                    self._update()
                return self.now() - t0
        while self.is_moving() and self.now() - t0 < max_time:
            time.sleep(0.002)
        return self.now() - t0

    # ---- joint state --------------------------------------------------------------------------
    @property
    def _tracks(self) -> list[motion.Track]:
        return self.__tracks

    @_tracks.setter
    def _tracks(self, tracks: list[motion.Track]) -> None:
        # every change of motion goes through here (lists are replaced, never edited in place)
        self.__tracks = tracks
        self._version += 1

    def _state(self, t: float | None = None):
        """``(q, qd, side)`` at ``t``: the profiles, overlaid by the integrated joints' state (as of the last
        ``_integrate``, which every read runs first)."""
        t = self.now() if t is None else t
        st = np.array([tr.state(t) for tr in self._tracks])
        q, qd, side = st[:, 0], st[:, 1], st[:, 2]
        dyn = self._mode != TRACK
        if dyn.any():
            q, qd, side = (np.where(dyn, self._dyn_x, q), np.where(dyn, self._dyn_v, qd),
                           np.where(dyn, self._dyn_side, side))
        return q, qd, side

    def _moving_now(self, t: float) -> np.ndarray:
        """Per joint: on a running profile, or an integrated joint not at rest."""
        on_track = np.array([t < tr.t_end for tr in self._tracks])
        dyn = self._mode != TRACK
        if not dyn.any():
            return on_track
        loose = dyn & (np.abs(self._dyn_v) >= dynamics.REST_SPEED)
        saturated = (self._mode == SATURATED) & on_track  # its reference still moves
        return np.where(dyn, loose | saturated | (dyn & ~self._dyn_rest), on_track)

    def encoder_q(self) -> np.ndarray:
        """Motor/encoder positions (SI), as a device reads them before its own calibration offset."""
        with self._lock:
            self._update()
            q = self._state()[0]
            if self.spec.encoder_sigma > 0:
                q = q + self._g_enc.normal(0.0, self.spec.encoder_sigma, self.n_joints)
            return q

    def encoder_qd(self) -> np.ndarray:
        """Joint velocities (SI/s)."""
        with self._lock:
            return self._state()[1]

    def joint_q(self) -> np.ndarray:
        """True joint values (encoder + backlash + compliance deflection), SI."""
        with self._lock:
            self._update()
            return self._joint_q_now()[0].copy()

    def _joint_q_now(self) -> tuple[np.ndarray, np.ndarray]:
        """``(q_joint, tip)`` now; cached while the arm stands still (emulators poll contact() fast)."""
        t = self.now()
        key = (self._version, t if self._moving_now(t).any() else None)
        if self._cache is None or self._cache[0] != key:
            q, _, side = self._state(t)
            qj = self._deflect(q, side)
            self._cache = (key, qj, self.truth.position(qj))
        return self._cache[1], self._cache[2]

    def _gravity_truth(self, spec: WorldSpec, nominal: Model) -> Gravity | Rigid:
        """Link masses (the model's, replaced per link by joints.masses), payload (joints.payload, else the
        model's) on the TRUE geometry."""
        if getattr(nominal, "kind", "serial") == "parallel":
            return Rigid()
        n = nominal.n_joints
        load = nominal.load
        masses = {k: load.link_mass(k) for k in range(1, n + 1)} if load is not None else {}
        masses.update({k: (m, np.asarray(c, dtype=float)) for k, (m, c) in spec.masses.items()})
        if spec.payload is not None:
            payload = (spec.payload, np.asarray(spec.payload_com or (0.0, 0.0, 0.0), dtype=float))
        else:
            payload = load.payload if load is not None else (0.0, np.zeros(3))
        return Gravity(self.truth, masses, payload, spec.gravity, self._compliance)

    def _deflect(self, q: np.ndarray, side: np.ndarray) -> np.ndarray:
        return self.gravity.deflect(q - side * self._backlash / 2 + self._pos_err)

    def _undeflect(self, qj: np.ndarray, side: np.ndarray) -> np.ndarray:
        """Encoder positions that put the joints at ``qj`` (fixed point; the deflection is small)."""
        q = qj + side * self._backlash / 2 - self._pos_err
        for _ in range(5):
            q = q + (qj - self._deflect(q, side))
        return q

    def tip_true(self) -> np.ndarray:
        """TRUE tool tip position (m, base frame)."""
        with self._lock:
            self._update()
            return self._joint_q_now()[1].copy()

    def tip_pose_true(self) -> np.ndarray:
        with self._lock:
            return self.truth.fk(self.joint_q())

    def tip_nominal(self) -> np.ndarray:
        """Where the station believes the tip is: nominal model at the noise-free encoder reading."""
        with self._lock:
            return self.nominal.position(self._state()[0])

    def is_moving(self) -> bool:
        with self._lock:
            return bool(self._moving_now(self.now()).any())

    def joint_moving(self) -> np.ndarray:
        """Per joint: its profile is still running, or it moves on its own (free, torque, saturated)."""
        with self._lock:
            return self._moving_now(self.now())

    def snapshot(self) -> Snapshot:
        """Everything an emulator serves, evaluated at ONE instant (realtime mode moves between calls)."""
        with self._lock:
            self._update()
            t = self.now()
            q, qd, side = self._state(t)
            q_read = q
            if self.spec.encoder_sigma > 0:
                q_read = q + self._g_enc.normal(0.0, self.spec.encoder_sigma, self.n_joints)
            moving = self._moving_now(t)
            return Snapshot(t, q_read, qd, moving, self.touching() is not None, self._enabled.copy(),
                            self._compliant, self._seated)

    # ---- commands -----------------------------------------------------------------------------
    def _event(self, msg: str) -> None:
        self.events.append((self.now(), msg))
        log.info("world: %s", msg)

    def _vector(self, x, what: str) -> np.ndarray:
        a = np.asarray(x, dtype=float).reshape(-1)
        if a.shape != (self.n_joints,):
            raise ValueError(f"{what}: expected {self.n_joints} joint values, got {a.shape[0]}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{what}: not finite: {a.tolist()}")
        return a

    def _limits(self, cap, default: np.ndarray, what: str) -> np.ndarray:
        if cap is None:
            return default.copy()
        c = np.broadcast_to(np.asarray(cap, dtype=float), default.shape)
        if not np.all(np.isfinite(c)) or np.any(c <= 0):
            raise ValueError(f"{what}: must be positive, got {cap!r}")
        return np.minimum(c, default)

    def _refused(self, what: str) -> bool:
        if self._pstop:
            self._event(f"{what} ignored: protective stop")
            return True
        return False

    def command_q(self, q_target, speed=None, accel=None) -> np.ndarray:
        """Synchronised joint move to ``q_target`` (encoder positions, SI). ``speed``/``accel`` cap the
        per-joint velocity/acceleration (scalar or per joint, SI). Targets outside the joint limits are
        clamped (and logged in ``events``); disabled joints stay. Returns the target actually used."""
        with self._lock:
            q1 = self._vector(q_target, "command_q")
            vlim = self._limits(speed, self._vmax, "command_q speed")
            alim = self._limits(accel, self._amax, "command_q accel")
            target = np.clip(q1, self.lower, self.upper)
            if np.any(target != q1):
                bad = [self.truth.joints[i].name for i in np.flatnonzero(target != q1)]
                self._event(f"command_q clamped to joint limits: {', '.join(bad)}")
            if self._refused("command_q"):
                return self._state()[0]
            self._integrate()
            self._watch(force=True)  # the path so far, before the motion changes
            t = self.now()
            x, v, side = self._state(t)
            target = np.where(self._enabled, target, x)
            hit = self.keep_out.path(x, target)
            if hit is not None and self.spec.collision == "stop":
                # a synchronised move is a straight joint path: a controller that knows the cell stops before it
                self._collided(f"command_q refused: {hit.describe()}")
                return x
            if self.time_mode == "instant" and hit is None:
                self._watched_q = target.copy()  # checked just now: the watch need not scan it again
            if self.time_mode == "instant":
                new_side = np.where(np.abs(target - x) > motion.EPS, np.sign(target - x), side)
                tracks = [motion.hold(t, float(target[i]), float(new_side[i])) for i in range(self.n_joints)]
            else:
                vs, as_ = motion.synchronised_limits(target - x, vlim, alim)
                # a joint still moving keeps its full limits: braking it at a rate scaled down for a straight
                # joint path would carry it far past the new target (and past its joint limit)
                moving = np.abs(v) > motion.EPS
                vs = np.where(moving, np.broadcast_to(vlim, moving.shape), vs)
                as_ = np.where(moving, np.broadcast_to(alim, moving.shape), as_)
                tracks = [motion.plan(t, float(x[i]), float(v[i]), float(target[i]), vs[i], as_[i],
                                      float(side[i])) for i in range(self.n_joints)]
            self._mode[(self._mode == TORQUE) & self._enabled] = TRACK  # a position command ends torque mode
            self._set_tracks(tracks, x)
            return target

    def command_joint(self, i: int, x_target: float, speed: float | None = None,
                      accel: float | None = None) -> float:
        """Move one joint (its own trapezoid; the other joints keep their motion). Returns the target used."""
        with self._lock:
            if not 0 <= i < self.n_joints:
                raise ValueError(f"command_joint: no joint {i} (0..{self.n_joints - 1})")
            q = self._state()[0]
            q[i] = float(x_target)
            q1 = self._vector(q, "command_joint")[i]
            tgt = float(np.clip(q1, self.lower[i], self.upper[i]))
            if tgt != q1:
                self._event(f"command_joint clamped to joint limits: {self.truth.joints[i].name}")
            if self._refused("command_joint") or not self._enabled[i]:
                return float(self._state()[0][i])
            vl = float(self._limits(speed, self._vmax, "speed")[i])
            al = float(self._limits(accel, self._amax, "accel")[i])
            self._integrate()
            t = self.now()
            x, v, side = (float(a[i]) for a in self._state(t))
            if self._mode[i] == TORQUE:
                self._mode[i] = TRACK
            tracks = list(self._tracks)
            if self.time_mode == "instant":
                tracks[i] = motion.hold(t, tgt, math.copysign(1.0, tgt - x) if abs(tgt - x) > motion.EPS else side)
            else:
                tracks[i] = motion.plan(t, x, v, tgt, vl, al, side)
            self._set_tracks(tracks, self._state(t)[0])
            return tgt

    def command_qd(self, qd, accel=None) -> np.ndarray:
        """Velocity mode: each joint ramps to ``qd`` (SI/s, capped at its maximum) and keeps going until
        it stops at its joint limit (decelerating in time) or a new command arrives. Time passes with
        the clock (realtime) or :meth:`advance` (sim and instant mode). Returns the velocities used."""
        with self._lock:
            v1 = self._vector(qd, "command_qd")
            alim = self._limits(accel, self._amax, "command_qd accel")
            capped = np.clip(v1, -self._vmax, self._vmax)
            if np.any(capped != v1):
                self._event("command_qd capped at the joint velocity limits")
            if self._refused("command_qd"):
                return np.zeros(self.n_joints)
            self._integrate()
            capped = np.where(self._enabled, capped, 0.0)
            t = self.now()
            x, v, side = self._state(t)
            tracks = []
            for i in range(self.n_joints):
                if abs(capped[i]) < motion.EPS:
                    tracks.append(motion.brake(t, x[i], v[i], alim[i], side[i]))
                else:
                    end = self.upper[i] if capped[i] > 0 else self.lower[i]
                    tracks.append(motion.plan(t, x[i], v[i], end, abs(capped[i]), alim[i], side[i]))
            self._mode[(self._mode == TORQUE) & self._enabled] = TRACK  # so does a velocity command
            self._set_tracks(tracks, x)
            return capped

    def halt(self, joints=None) -> None:
        """Decelerate ``joints`` (index, list; None: all) to rest at the acceleration limit (controlled stop).
        A torque-commanded joint goes back to position control; a free joint has no power to stop it."""
        with self._lock:
            self._integrate()
            t = self.now()
            x, v, side = self._state(t)
            tracks = list(self._tracks)
            for i in self._joints(joints):
                if self._mode[i] == FREE:
                    continue
                tracks[i] = motion.brake(t, float(x[i]), float(v[i]), float(self._amax[i]), float(side[i]))
                if self._mode[i] == TORQUE:
                    self._mode[i] = TRACK
            self._tracks = tracks

    def _set_tracks(self, tracks: list[motion.Track], x_now: np.ndarray) -> None:
        each = np.array([abs(tr.x_end - x_now[i]) > 1e-12 or bool(tr.phases) for i, tr in enumerate(tracks)])
        moved = bool(each.any())
        if moved and self.spec.positioning_sigma > 0:  # a joint that moves ends a little elsewhere each time
            self._pos_err[each] = self._g_pos.normal(0.0, self.spec.positioning_sigma, int(each.sum()))
        self._tracks = tracks
        if moved and self._seated:
            self._event(f"left socket {self._seated}")
            self._seated = None
            self._seat_target = None
        self._update(watch=False)  # joint-by-joint commands of one move: watched when the arm is next observed

    def _arm_file_faults(self, items: list[dict]) -> None:
        """The world file's ``faults:`` (docs/world.md): armed now, on a wire event, or after a delay."""
        for f in items:
            at = dict(f.get("at") or {})
            delay = at.pop("after_s", None)
            args = dict(kind=f["do"], device=f.get("device"), count=f.get("count", 1), after=f.get("after", 0),
                        code=f.get("code"), trigger=at or None)
            if delay:
                t = threading.Timer(float(delay), lambda a=args: self.faults.inject(**a))
                t.daemon = True
                t.start()
            else:
                self.faults.inject(**args)

    # ---- power, compliance, faults ------------------------------------------------------------
    def _joints(self, joints) -> list[int]:
        if joints is None:
            return list(range(self.n_joints))
        idx = [int(joints)] if np.isscalar(joints) else [int(j) for j in joints]
        for i in idx:
            if not 0 <= i < self.n_joints:
                raise ValueError(f"no joint {i} (0..{self.n_joints - 1})")
        return idx

    def set_enabled(self, on: bool, joints=None) -> None:
        """Power/torque on or off for ``joints`` (index or list; None: all). A disabled joint ignores commands:
        with a brake (``brakes``) it is held where it is (stops at once); without one it is free and moves under
        gravity (and its own momentum) until friction or its end stop holds it. Enabling holds a joint where it
        is (position control, goal = present position)."""
        with self._lock:
            self._integrate()
            idx = self._joints(joints)
            t = self.now()
            x, v, side = self._state(t)
            tracks = list(self._tracks)
            for i in idx:
                if on and self._enabled[i]:
                    continue
                if on or self._brakes[i]:
                    tracks[i] = motion.hold(t, float(x[i]), float(side[i]))
                    self._mode[i] = TRACK
                else:
                    self._let_go(i, x, v, side)
            self._tracks = tracks
            self._enabled[idx] = bool(on)
            self._settle_instant()

    def enabled(self) -> np.ndarray:
        with self._lock:
            return self._enabled.copy()

    # ---- brakes, torque, joints off their profiles (dynamics.py) ------------------------------
    @property
    def brakes(self) -> np.ndarray:
        """Per joint: a brake holds it when it is disabled."""
        return self._brakes.copy()

    def default_brakes(self, has_brake) -> None:
        """The device's own default (a bool or one per joint), used only where the world file says nothing
        (``joints.brakes``): an emulator states what its hardware has. Parallel robots' screw legs self-lock."""
        with self._lock:
            if not self._brakes_said and not isinstance(self.gravity, Rigid):
                self._brakes = np.broadcast_to(np.asarray(has_brake, dtype=bool), (self.n_joints,)).copy()

    def command_torque(self, tau, joints=None) -> None:
        """Torque mode for ``joints`` (None: all): each applies ``tau`` (N m, N for prismatic; a scalar or one
        per joint named), within its torque limit; nothing holds position (CiA 402 profile torque). Disabled
        joints ignore it; a position command, ``halt`` or disabling ends it."""
        with self._lock:
            self._integrate()
            idx = self._joints(joints)
            tau = np.broadcast_to(np.asarray(tau, dtype=float), (len(idx),))
            if not np.all(np.isfinite(tau)):
                raise ValueError(f"command_torque: not finite: {tau.tolist()}")
            if self._refused("command_torque"):
                return
            x, v, side = self._state()
            for k, i in enumerate(idx):
                if not self._enabled[i]:
                    continue
                self._tau_cmd[i] = tau[k]
                if self._mode[i] != TORQUE:
                    self._let_go(i, x, v, side, TORQUE)
            self._dyn_rest = False
            self._settle_instant()

    def set_torque_limit(self, limit, joints=None) -> None:
        """Motor torque limit (N m, N for prismatic; None or inf: none) of ``joints`` (None: all). A position-
        controlled joint whose load needs more than its limit sags while its motor pushes the limit."""
        with self._lock:
            self._integrate()
            idx = self._joints(joints)
            lim = np.broadcast_to(np.asarray(np.inf if limit is None else limit, dtype=float), (len(idx),))
            if np.any(np.isnan(lim)) or np.any(lim < 0):
                raise ValueError(f"set_torque_limit: must be >= 0, got {lim.tolist()}")
            self._tau_limit[idx] = lim
            self._dyn_rest = False
            self._integrate()
            self._settle_instant()

    def torque_limit(self) -> np.ndarray:
        with self._lock:
            return self._tau_limit.copy()

    def joint_torque(self) -> np.ndarray:
        """The torque (N m, N for prismatic) each joint's motor applies now: holding its load on its profile,
        what a torque-commanded or saturated motor pushes, 0 with the power off (the brake, if any, holds)."""
        with self._lock:
            self._update()
            q = self._state()[0]
            tau_g, _ = self._dynamics.forces(q)
            held = (self._mode == TRACK) & self._enabled
            return np.where(held, -tau_g, np.where(self._mode == FREE, 0.0, self._tau_motor))

    def gravity_torque(self) -> np.ndarray:
        """The torque (N m, N for prismatic) gravity applies to each joint now (the truth's, with estimated
        masses where the world states none: dynamics.estimated_masses)."""
        with self._lock:
            self._update()
            return self._dynamics.forces(self._state()[0])[0]

    def dynamics_friction(self) -> np.ndarray:
        """Coulomb friction (N m, N for prismatic) of each joint off its profile (joints.dynamics.friction)."""
        with self._lock:
            return self._dynamics.friction.copy()

    @property
    def _dynamics(self) -> dynamics.Dynamics:
        if self.__dynamics is None:
            g = self.gravity
            if not isinstance(g, Gravity) or g.mass.sum() <= 0:
                payload = g.payload if isinstance(g, Gravity) else (0.0, np.zeros(3))
                g = Gravity(self.truth, dynamics.estimated_masses(self.truth) if isinstance(g, Gravity) else {},
                            payload, self.spec.gravity, np.zeros(self.n_joints))
            self.__dynamics = dynamics.Dynamics(self.truth, g, self.spec.dynamics)
        return self.__dynamics

    def _let_go(self, i: int, x, v, side, mode: int = FREE) -> None:
        """Joint ``i`` leaves its profile (free or torque mode) from its present state."""
        if self._mode[i] == TRACK:
            self._dyn_x[i], self._dyn_v[i], self._dyn_side[i] = x[i], v[i], side[i]
        self._mode[i] = mode
        self._dyn_rest = False
        self._version += 1

    def _check_saturation(self, q: np.ndarray) -> None:
        """Position-controlled joints whose load needs more torque than their limit leave their profile."""
        tau_g, _ = self._dynamics.forces(q)
        over = (self._mode == TRACK) & self._enabled & (np.abs(tau_g) > self._tau_limit * (1 + 1e-9))
        if over.any():
            _, v, side = self._state()
            for i in np.flatnonzero(over):
                self._let_go(i, q, v, side, SATURATED)
                self._event(f"{self.truth.joints[i].name}: load {abs(tau_g[i]):.3g} N m over the motor's torque "
                            f"limit {self._tau_limit[i]:.3g}: sags")

    def _integrate(self, t1: float | None = None, t0: float | None = None) -> None:
        """Bring the joints off their profiles from their last state to ``t1`` (default now). ``t0``: start the
        span there instead (instant mode settles a span of its own: the profiles then stand still)."""
        t1 = self.now() if t1 is None else t1
        if np.isfinite(self._tau_limit).any():
            self._check_saturation(self._state(t1)[0])
        dyn = self._mode != TRACK
        settling = t0 is not None  # instant mode's own span: the profiles stand still, done once the joints rest
        t0 = self._dyn_t if t0 is None else t0
        if not dyn.any() or t1 <= t0:
            self._dyn_t = max(self._dyn_t, t1)
            return
        # a moving profile changes the load on the others (and drives a saturated joint): integrate while it runs
        profiles_move = any(t0 < tr.t_end for tr in self._tracks)
        saturated = self._mode == SATURATED
        if self._dyn_rest and not profiles_move:
            self._dyn_t = t1
            return
        D = self._dynamics
        steps = int(min(dynamics.MAX_STEPS, max(1, math.ceil((t1 - t0) / dynamics.STEP))))
        h = (t1 - t0) / steps
        x, v = self._dyn_x.copy(), self._dyn_v.copy()
        rest = np.zeros(self.n_joints, dtype=bool)
        for k in range(steps):
            tm = t0 + (k + 1) * h
            ref = np.array([tr.state(tm) for tr in self._tracks])
            q, qd = np.where(dyn, x, ref[:, 0]), np.where(dyn, v, ref[:, 1])
            tau_g, inertia = D.forces(q)
            tau = np.where(self._mode == TORQUE, np.clip(self._tau_cmd, -self._tau_limit, self._tau_limit), 0.0)
            if saturated.any():
                pc = D.position_controller(q, qd, ref[:, 0], ref[:, 1], self._tau_limit, tau_g, inertia)
                tau = np.where(saturated, pc, tau)
            x_new, v_new, rest = D.step(q, qd, tau, h, dyn, self.lower, self.upper, tau_g, inertia)
            x, v = np.where(dyn, x_new, x), np.where(dyn, v_new, v)
            self._tau_motor = np.where(dyn, tau, self._tau_motor)
            if saturated.any():  # back on the profile once the controller holds it within its limit again
                back = saturated & (np.abs(tau) < self._tau_limit) & (np.abs(x - ref[:, 0]) < 1e-7) \
                    & (np.abs(v - ref[:, 1]) < 1e-5)
                if back.any():
                    self._mode[back] = TRACK
                    dyn, saturated = self._mode != TRACK, self._mode == SATURATED
            if (rest | ~dyn).all() and (settling or tm >= max([tr.t_end for tr in self._tracks] + [t0])):
                break
        moved = np.abs(v) >= dynamics.REST_SPEED
        self._dyn_side = np.where(moved, np.sign(v), self._dyn_side)
        self._dyn_x, self._dyn_v = x, v
        self._dyn_rest = bool((rest | ~dyn).all())
        self._dyn_t = max(self._dyn_t, t1)
        self._version += 1

    def _settle_instant(self) -> None:
        """Instant mode completes moves at once: a joint let go comes to rest at once too (at most
        ``dynamics.SETTLE_TIME`` of its own motion; the profiles stand still meanwhile)."""
        if self.time_mode == "instant" and (self._mode != TRACK).any():
            t = self.now()
            self._integrate(t1=t, t0=t - dynamics.SETTLE_TIME)

    def set_compliant(self, on: bool) -> None:
        """Compliant (torque-limited / freedrive) mode. Entering it with the true tip inside a socket's
        capture radius seats the tip in the socket; leaving it keeps the seated position."""
        with self._lock:
            self._compliant = bool(on)
            self._update()

    @property
    def compliant(self) -> bool:
        return self._compliant

    @property
    def seated(self) -> str | None:
        """Label of the socket the tip sits in, or None."""
        with self._lock:
            self._update()
            return self._seated

    def fault_joint(self, i: int, code: int = 1) -> None:
        """A device fault on joint ``i``: every joint halts, joint ``i`` is disabled (brake) until
        :meth:`clear_fault` and re-enable."""
        with self._lock:
            self._joints(i)
            self.halt()
            self.set_enabled(False, i)
            self._joint_faults[i] = int(code)
            self._event(f"fault on joint {self.truth.joints[i].name} (code {code}): halted, disabled")

    def joint_fault(self, i: int) -> int | None:
        with self._lock:
            return self._joint_faults.get(i)

    def clear_fault(self, i: int | None = None) -> None:
        with self._lock:
            if i is None:
                self._joint_faults.clear()
            else:
                self._joint_faults.pop(i, None)

    def protective_stop(self, reason: str = "protective stop") -> None:
        """Halt and refuse motion commands until :meth:`clear_protective_stop`."""
        with self._lock:
            self.halt()
            self._pstop = True
            self._event(reason)

    def clear_protective_stop(self) -> None:
        with self._lock:
            self._pstop = False

    @property
    def protective_stopped(self) -> bool:
        return self._pstop

    # ---- cell ---------------------------------------------------------------------------------
    def _update(self, watch: bool = True) -> None:
        """Lazy world rules evaluated whenever state is read: socket seating while compliant, and (``watch``)
        the links against the floor and keep-outs."""
        self._integrate()
        if watch:
            self._watch()
        if self._compliant and self._seated is None and not self.is_moving():
            self._try_seat()

    def _watch(self, force: bool = False) -> None:
        """The links along the path the arm took since it was last observed (a straight joint path: exact for
        an instant move, the trajectory sampled every ``WATCH_PERIOD`` while moving; ``force``: look now).
        Every contact is recorded; with ``collision: stop`` the arm also stops where it is and the world is in
        protective stop (a UR controller reports it; other buses see their moves refused)."""
        if self._watched_rest == self._version:
            return  # no command since the arm was last seen at rest where it is
        t = self.now()
        moving = self.is_moving()
        if not force and moving and self.time_mode != "instant" and t - self._watched_t < WATCH_PERIOD:
            return  # emulators read many times per ms of motion: look every WATCH_PERIOD (the path in between)
        q = self._state(t)[0]
        self._watched_t = t
        self._watched_rest = None if moving else self._version
        if np.array_equal(q, self._watched_q):
            return
        hit = self.keep_out.path(self._watched_q, q)
        self._watched_q = q
        if hit is None:
            return
        if self.spec.collision == "stop":
            t = self.now()
            self._tracks = [motion.hold(t, float(x), float(sd)) for x, sd in zip(q, self._state(t)[2], strict=True)]
            self._watched_q = self._state(t)[0]
        self._collided(f"collision: {hit.describe()}")

    def _collided(self, msg: str) -> None:
        self.collisions.append(msg)
        if self.spec.collision == "stop":
            self._pstop = True
        self._event(msg)

    def _try_seat(self) -> None:
        q, _, side = self._state()
        qj, tip = self._joint_q_now()
        p = self.cell.capturing(tip)
        if p is None or not self._enabled.any():
            return
        if self._seat_failed is not None and np.array_equal(self._seat_failed, q):
            return
        target = self.cell.settling_point(p)
        res = self.truth.ik(target, qj, position_only=True, weights=self._enabled.astype(float), tol_pos=1e-9)
        if res.position_error[0] > 1e-7:
            if self._seat_failed is None or not np.array_equal(self._seat_failed, q):
                self._event(f"socket {p.label}: the arm cannot settle (IK {res.position_error[0]:.2e} m)")
            self._seat_failed = q  # do not retry (and log) on every read until the arm moves
            return
        q_new = self._undeflect(res.q[0], side)
        t = self.now()
        self._tracks = [motion.hold(t, float(q_new[i]), float(side[i])) for i in range(self.n_joints)]
        self._seated = p.label
        self._seat_target = target
        self._event(f"seated in socket {p.label}")

    def contact(self) -> bool:
        """The cell's contact input: true tip within a needle's contact radius, or seated in a socket."""
        return self.touching() is not None

    def touching(self) -> str | None:
        """Label of the point in contact (needle within its radius, or the socket the tip is seated in)."""
        with self._lock:
            self._update()
            if self._seated:
                return self._seated
            return self.cell.needle_touched(self.tip_true())

    def station_cell(self) -> dict:
        """The cell as the integrator knows it (``station-cell/1``, ``Cell.station_doc``): true positions plus
        survey error."""
        return self.cell.station_doc(self.nominal)

    # ---- truth --------------------------------------------------------------------------------
    def errors(self) -> dict[str, float]:
        """Hidden errors: true minus nominal value of every perturbed parameter (SI)."""
        return dict(self._errors)

    def hidden(self) -> dict[str, float]:
        """TRUE values of every perturbed parameter (SI), and always every ``offset.jN`` (the true zero
        offsets, 0.0 where not perturbed); with gravity deflection, ``compliance.jN`` of the compliant
        revolute joints."""
        names = [n for n in self.truth.param_names if n in self._errors or n.startswith("offset.j")]
        out = {n: self.truth.param(n) for n in names}
        if self.gravity.active:  # the true gravity compliance of every compliant revolute joint (rad per N m)
            out.update({f"compliance.j{i + 1}": float(c) for i, (c, j) in
                        enumerate(zip(self._compliance, self.truth.joints, strict=True)) if c and j.revolute})
        return out

    def true_offsets(self) -> np.ndarray:
        """True zero offsets ``(n,)`` (SI): ``theta_i = q_i + offset_i`` on the true robot."""
        return np.array([self.truth.param(f"offset.j{i + 1}") for i in range(self.n_joints)])

    def truth_report(self, length: str = "mm", angle: str = "deg") -> str:
        """Human-readable hidden truth: every perturbed parameter, the cell points, the mechanics."""
        from station.mocks.world.report import truth_report

        return truth_report(self, length, angle)

    def bus_config(self, name: str) -> dict:
        """The ``buses.<name>`` mapping of the world file, passed through unchanged ({} if absent)."""
        import copy

        return copy.deepcopy(self.spec.buses.get(name, {}))

    def __repr__(self) -> str:
        return (f"World(model={self.nominal.name!r}, seed={self.spec.seed}, time_mode={self.time_mode!r}, "
                f"{len(self._errors)} hidden errors, points={list(self.points)})")
