"""The Franka emulator's simulator process: franka-sim's FCI server (``FrankaSimServer``, libfranka protocol
version 10, its communication-constraint and motion-limit checks enforced) on MuJoCo, serving the TRUE arm
of a station world.

Runs in the franka-sim environment (``.venv-franka-sim``: franka-sim pins numpy 1.26 and MuJoCo < 3.3) and
imports no station module: ``station mock franka`` (``station.mocks.franka.cli``) reads the world, writes the
scene file (JSON, SI units) and starts ``PYTHON simhost.py --scene FILE``. Prints one line
``franka-sim ready on HOST:1337`` once the server listens, then serves until SIGTERM/SIGINT.

What the scene becomes (compiled by MuJoCo, never downloaded: ``$FR3_MJCF`` is not used):
- the arm: the world's TRUE URDF (hidden geometric errors folded into the joint origins, meshes none), the
  ball on its tool link, and per compliant joint a second hinge on the same axis with stiffness 1/C that the
  gravity of the outboard links bends (the encoder reads the joint before it: ``theta = q + C tau``);
- the cell: each socket a nest of eight small spheres around the true socket centre, so a ball seats by
  contact physics; the nest moves by the world's seating noise between two seatings (the ball never sits
  exactly alike twice).

What this process adds to franka-sim 1.1.7 (each named in docs/hardware-franka.md with the reason):
- ``O_T_EE`` from the controller's own model (the URDF it serves: nominal, flange = ``link8``), at the measured
  joints, as the robot computes it; franka-sim reports the simulated body ``link7`` of the true model;
- the internal controllers' laws: joint impedance with the stiffness of ``SetJointImpedance`` and Cartesian
  impedance with that of ``SetCartesianImpedance`` (franka-sim acknowledges both and servoes every joint-position
  motion with its fixed gains, and runs no physics for a Cartesian-impedance joint-position motion);
- the external torque and wrench estimates (``tau_ext_hat_filtered``, ``O_F_ext_hat_K``, ``K_F_ext_hat_K``) from
  the contact forces on the arm, with noise (franka-sim publishes zeros);
- the asynchronous position motion generator (``Move.use_async_motion_generator``, libfranka >= 0.18): the
  robot moves to the last target it received within the velocities of the ``Move``, at the rate the client
  chooses (franka-sim ignores the flag and judges the sparse targets as a 1 kHz stream);
- the collision reflexes: franka-sim acknowledges ``SetCollisionBehavior`` and does nothing with it; here the
  upper thresholds are kept and a motion whose estimated external torque or wrench exceeds them is aborted with
  ``joint_reflex`` / ``cartesian_reflex``, as the robot does (libfranka robot.h, ``setCollisionBehavior``);
- a push on the tool staged from outside (SIGUSR1: ``PUSH_FORCE`` N sideways for ``PUSH_S``; a person who
  bumps into the arm), felt by the physics and by the external force estimate: the device fault a test bench
  can stage, which the collision reflex answers during a motion."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import re
import signal
import struct
import sys
import threading

import mujoco
import numpy as np
from franka_sim.control_modes import ControlMode
from franka_sim.franka_protocol import (
    ControllerMode,
    LibfrankaControllerMode,
    MotionGeneratorMode,
    RobotMode,
    SetCollisionBehaviorCommand,
)
from franka_sim.franka_sim_server import FrankaSimServer
from franka_sim.mujoco_franka_sim import ARM_POSITION_KD, ARM_POSITION_KP, DEFAULT_DT, MujocoFrankaSim
from franka_sim.robot_state import RobotState
from franka_sim.sim_common import FR3_FORCE_LIMITS

log = logging.getLogger("station.franka-sim")

# Cartesian impedance: damping for a 4 kg mass / a 0.05 kg m^2 rotor per axis (about what the arm moves at the
# tool: near critical damping), and the
# null space held to the generator's joint positions by a joint spring (the 7th DOF must not drift)
CART_MASS, CART_INERTIA = 4.0, 0.05
NULL_K, NULL_D = 100.0, 20.0
ARMATURE = np.array([0.15, 0.15, 0.15, 0.15, 0.15, 0.15, 0.15])  # kg m^2 per joint: reflected motor inertia
DAMPING = 1.0  # N m s/rad: viscous joint friction
D_STABLE = 1.5 * ARMATURE / DEFAULT_DT  # the damping an explicit step of the joint law keeps stable
ELASTIC_DAMPING = 20.0  # N m s/rad on a compliant joint's elastic hinge: it rings down within a few ms
PUSH_FORCE = 60.0  # N on the tool, horizontal: a firm bump, above every collision threshold the driver sets
PUSH_S = 0.3  # s of simulated time
EST_ALPHA = 0.95  # low-pass of the external torque estimate per 1 ms cycle (~20 ms time constant)
ASYNC_ACCELERATION = 4.0  # rad/s^2 of the asynchronous generator (FR3: 10 rad/s^2 at most)
# positions of the collision reflexes in the 41-entry error arrays of the robot state (libfranka errors.h,
# research_interface::robot::Error: ..., force_control_safety_violation = 5, joint_reflex, cartesian_reflex)
JOINT_REFLEX_INDEX, CARTESIAN_REFLEX_INDEX = 6, 7


def _strip_urdf(text: str) -> str:
    """A URDF for MuJoCo's compiler: no meshes, every frame its own body (the tool link stays addressable)."""
    text = re.sub(r"<visual\b.*?</visual>|<collision\b.*?</collision>", "", text, flags=re.S)
    compiler = ('<mujoco><compiler fusestatic="false" discardvisual="true" balanceinertia="true" '
                'boundinertia="0.001" boundmass="0.001"/></mujoco>')
    return re.sub(r"(<robot\b[^>]*>)", r"\1" + compiler, text, count=1)


def _frame(z) -> np.ndarray:
    z = np.asarray(z, float) / np.linalg.norm(z)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = helper - z * (helper @ z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _quat(R: np.ndarray) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q.tolist()


class ControllerModel:
    """The controller's own kinematic model (the URDF the robot serves, compiled by MuJoCo): what the robot
    reports ``O_T_EE`` and the external wrench in. Used from the physics thread only."""

    def __init__(self, urdf_text: str, flange: str = "link8") -> None:
        self.model = mujoco.MjModel.from_xml_string(_strip_urdf(urdf_text))
        self.data = mujoco.MjData(self.model)
        self.flange = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, flange)
        if self.flange < 0:
            raise ValueError(f"the served URDF has no body {flange!r} (libfranka's flange link)")
        names = [f"joint{i}" for i in range(1, 8)]
        self.qadr = np.array([self.model.jnt_qposadr[self.model.joint(n).id] for n in names])
        self.dadr = np.array([self.model.jnt_dofadr[self.model.joint(n).id] for n in names])
        self._jp = np.zeros((3, self.model.nv))
        self._jr = np.zeros((3, self.model.nv))

    def flange_pose(self, q) -> np.ndarray:
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self.flange].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self.flange]
        return T

    def jacobian(self, point) -> np.ndarray:
        """6x7 geometric Jacobian (linear rows first) of ``point`` (world) fixed to the flange, at the joints of
        the last ``flange_pose`` call."""
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_jac(self.model, self.data, self._jp, self._jr, np.asarray(point, float), self.flange)
        return np.vstack([self._jp[:, self.dadr], self._jr[:, self.dadr]])


class StationArm(MujocoFrankaSim):
    """franka-sim's MuJoCo backend with the station world's true arm and cell, the internal controllers'
    impedance laws, the external force estimate and the controller-model ``O_T_EE``."""

    def __init__(self, scene: dict) -> None:
        super().__init__(enable_vis=False, model_path=None, enable_hand=False)
        self.scene = scene
        self.rng = np.random.default_rng(int(scene.get("seed", 0)))
        self.controller_model = ControllerModel(scene["served_urdf_text"])
        self.start_q = np.asarray(scene["start_q"], float)
        self.latest_joint_positions = self.start_q.copy()
        self._position_feedforward.reset(self.start_q)
        self.controller = "joint"  # the internal controller of the running motion: "joint" | "cartesian"
        self.generator: AsyncGenerator | None = None  # the running asynchronous position motion
        self.K_theta = ARM_POSITION_KP.copy()  # until SetJointImpedance
        self.K_x = np.array([3000.0, 3000.0, 3000.0, 300.0, 300.0, 300.0])  # until SetCartesianImpedance
        self.EE_T_K = np.eye(4)
        self.force_noise = float(scene.get("force_noise", 0.2))
        self._noise = np.zeros(6)
        self._tau_ext = np.zeros(7)
        self._cart_ref: np.ndarray | None = None  # x_d of the joint target, true model (set per step)
        self._nests: list[dict] = []
        self._elastic_dofs = np.zeros(0, dtype=np.intp)
        self.seated: dict[str, bool] = {}
        self._push_until = -1.0  # simulated time (s) a staged push on the tool lasts until
        self._push_tau = np.zeros(7)  # N m: its generalized force on the arm's joints (environment -> robot)

    # ---- model --------------------------------------------------------------------------------------------
    def initialize_simulation(self) -> None:
        sc = self.scene
        spec = mujoco.MjSpec.from_string(_strip_urdf(sc["true_urdf_text"]))
        spec.option.timestep = DEFAULT_DT
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
        for i, j in enumerate(spec.joints):
            j.armature, j.damping, j.frictionloss = float(ARMATURE[i % 7]), DAMPING, 0.0
        self._inertials_from_description(spec)
        elastic = []
        owner = {j.name: b for b in spec.bodies for j in b.joints}
        for i, c in enumerate(sc.get("compliance") or []):
            if c and c > 0:  # a second hinge on the same axis after the measured one: the joint bends there
                body = owner[f"joint{i + 1}"]
                src = next(j for j in body.joints if j.name == f"joint{i + 1}")
                e = body.add_joint()
                e.name = f"joint{i + 1}_elastic"
                e.type = mujoco.mjtJoint.mjJNT_HINGE
                e.axis, e.pos = list(src.axis), list(src.pos)
                e.stiffness, e.damping, e.armature = 1.0 / float(c), ELASTIC_DAMPING, 0.01
                elastic.append(e.name)
        for b in spec.bodies:
            b.gravcomp = 1.0  # the controller compensates gravity (franka-sim's contract); the elastic hinges
            # get it back below
        tool = spec.find_body(sc["tool_link"])
        R = float(sc["ball_radius"])
        ball = tool.add_geom()
        ball.name, ball.type, ball.size = "ball", mujoco.mjtGeom.mjGEOM_SPHERE, [R, 0, 0]
        contact = dict(friction=[float(sc.get("friction", 0.15)), 0.005, 0.0001], solref=[0.002, 1.0],
                       solimp=[0.99, 0.999, 0.0005, 0.5, 2.0])
        for k, v in contact.items():
            setattr(ball, k, v)
        nest = sc["nest"]
        r, n, half = float(nest["sphere_radius"]), int(nest["spheres"]), math.radians(float(nest["half_angle_deg"]))
        for s in sc["sockets"]:
            body = spec.worldbody.add_body()
            body.name, body.mocap = f"socket_{s['label']}", True
            body.pos = list(s["position"])
            body.quat = _quat(_frame(s["approach"]))
            for k in range(n):
                phi = 2 * math.pi * k / n
                g = body.add_geom()
                g.type, g.size = mujoco.mjtGeom.mjGEOM_SPHERE, [r, 0, 0]
                g.pos = [(R + r) * math.sin(half) * math.cos(phi), (R + r) * math.sin(half) * math.sin(phi),
                         -(R + r) * math.cos(half)]
                for key, v in contact.items():
                    setattr(g, key, v)
            self._nests.append({"label": s["label"], "centre": np.asarray(s["position"], float)})
        ground = spec.worldbody.add_geom()
        ground.name, ground.type, ground.size = "ground_plane", mujoco.mjtGeom.mjGEOM_PLANE, [0, 0, 0.05]
        self.model = spec.compile()
        self.data = mujoco.MjData(self.model)
        self.prefix = ""
        self._bind_model()
        self._elastic_dofs = np.array([self.model.jnt_dofadr[self.model.joint(n).id] for n in elastic],
                                      dtype=np.intp)
        self._tool_body = self.model.body(sc["tool_link"]).id
        self._ball = self.model.geom("ball").id
        self._ball_radius = R
        for k, nst in enumerate(self._nests):
            nst["mocap"] = int(self.model.body_mocapid[self.model.body(f"socket_{nst['label']}").id])
            self._jitter(k)
        self.data.qpos[self.arm_qpos_adr] = self.start_q
        mujoco.mj_forward(self.model, self.data)
        for _ in range(100):
            self._apply_control()
            mujoco.mj_step(self.model, self.data)
        self._read_and_publish_state()
        log.info("scene compiled: %d dofs (%d elastic), %d sockets", self.model.nv, len(elastic), len(self._nests))

    def _inertials_from_description(self, spec) -> None:
        """Each link ``link1``..``link7`` gets the mass, centre and inertia of the same link of the description the
        robot serves (franka_description), moved into the true URDF's link frame: the two frames are found at
        q = 0 in both compiled models (they differ by where the URDF writer puts a link's frame on its joint
        axis, and by the hidden errors)."""
        true = spec.compile()
        td = mujoco.MjData(true)
        mujoco.mj_kinematics(true, td)
        cm = self.controller_model
        cm.flange_pose(np.zeros(7))
        m, d = cm.model, cm.data
        for k in range(1, 8):
            name = f"link{k}"
            bt = mujoco.mj_name2id(true, mujoco.mjtObj.mjOBJ_BODY, name)
            bs = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
            body = spec.find_body(name)
            if bt < 0 or bs < 0 or body is None:
                continue
            Rt, pt = td.xmat[bt].reshape(3, 3), td.xpos[bt]
            Rs, ps = d.xmat[bs].reshape(3, 3), d.xpos[bs]
            R_rel = Rt.T @ Rs  # served link frame in the true link frame
            p_rel = Rt.T @ (ps - pt)
            Ri = np.zeros(9)
            mujoco.mju_quat2Mat(Ri, m.body_iquat[bs])
            body.mass = float(m.body_mass[bs])
            body.ipos = (R_rel @ m.body_ipos[bs] + p_rel).tolist()
            body.iquat = _quat(R_rel @ Ri.reshape(3, 3))
            body.inertia = m.body_inertia[bs].tolist()
            body.explicitinertial = True

    def _jitter(self, k: int) -> None:
        """Move nest ``k`` to its socket centre plus the world's seating noise (m per axis)."""
        nst = self._nests[k]
        self.data.mocap_pos[nst["mocap"]] = nst["centre"] + self.rng.normal(0.0, self.scene["seating_sigma"], 3)
        self.seated[nst["label"]] = False

    # ---- control ------------------------------------------------------------------------------------------
    def set_joint_impedance(self, K) -> None:
        self.K_theta = np.asarray(K, float)

    def set_cartesian_impedance(self, K) -> None:
        self.K_x = np.asarray(K, float)

    def set_stiffness_frame(self, EE_T_K) -> None:
        self.EE_T_K = np.asarray(EE_T_K, float).reshape(4, 4).T

    def arm_control_torque(self) -> np.ndarray:
        if self.control_mode is not ControlMode.POSITION:
            return super().arm_control_torque()
        q = self.data.qpos[self.arm_qpos_adr]
        dq = self.data.qvel[self.arm_dofs_idx]
        target = self.latest_joint_positions
        dq_c = self._position_feedforward.step(target, self.dt)
        if self.controller == "cartesian":
            tau = self._cartesian_law(q, dq, target, dq_c)
        else:
            K = self.K_theta
            # franka-sim's damping for its stiffness, scaled with the square root of the stiffness asked for
            # (the same damping ratio), at most what an explicit 1 ms step keeps stable on the joint's armature
            D = np.minimum(ARM_POSITION_KD * np.sqrt(np.maximum(K, 0.0) / ARM_POSITION_KP), D_STABLE)
            tau = K * (target - q) + D * (dq_c - dq)
        return np.clip(tau, -FR3_FORCE_LIMITS, FR3_FORCE_LIMITS)

    def _k_frame(self, d) -> tuple[np.ndarray, np.ndarray]:
        """Position and rotation of the stiffness frame K (tool link of the true arm, then ``EE_T_K``)."""
        T = np.eye(4)
        T[:3, :3] = d.xmat[self._tool_body].reshape(3, 3)
        T[:3, 3] = d.xpos[self._tool_body]
        T = T @ self.EE_T_K
        return T[:3, 3].copy(), T[:3, :3].copy()

    def _cartesian_law(self, q, dq, target, dq_c) -> np.ndarray:
        """Cartesian impedance about the pose the joint target gives (the generator streams joints): a spring
        ``K_x`` (in frame K) between that pose and the measured one, critically damped, and the null space
        held to the target joints by a weak spring."""
        m, d = self.model, self.data
        probe = getattr(self, "_probe", None)
        if probe is None:
            probe = self._probe = mujoco.MjData(m)
        probe.qpos[:] = d.qpos
        probe.qpos[self.arm_qpos_adr] = target
        mujoco.mj_kinematics(m, probe)
        xd, Rd = self._k_frame(probe)
        x, Rm = self._k_frame(d)
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jp, jr, x, self._tool_body)
        J = np.vstack([jp[:, self.arm_dofs_idx], jr[:, self.arm_dofs_idx]])
        v = J @ dq
        vd = J @ dq_c
        Kt, Kr = self.K_x[:3], self.K_x[3:]
        Kt_w = Rm @ np.diag(Kt) @ Rm.T
        Kr_w = Rm @ np.diag(Kr) @ Rm.T
        e_rot = 0.5 * sum(np.cross(Rm[:, i], Rd[:, i]) for i in range(3))
        Dt = Rm @ np.diag(2 * np.sqrt(np.maximum(Kt, 0) * CART_MASS)) @ Rm.T
        Dr = Rm @ np.diag(2 * np.sqrt(np.maximum(Kr, 0) * CART_INERTIA)) @ Rm.T
        F = np.concatenate([Kt_w @ (xd - x) + Dt @ (vd[:3] - v[:3]), Kr_w @ e_rot + Dr @ (vd[3:] - v[3:])])
        tau = J.T @ F
        N = np.eye(7) - J.T @ np.linalg.pinv(J.T)
        return tau + N @ (NULL_K * (target - q) + NULL_D * (dq_c - dq))

    def _apply_control(self) -> None:
        gen = self.generator
        if gen is not None and self.control_mode is ControlMode.POSITION:
            # the robot-side generator advances with the simulation (1 ms a step), whatever the wall clock does
            self.latest_joint_positions = gen.step(self.dt)[0].copy()
        super()._apply_control()
        self._apply_push()
        if self._elastic_dofs.size:  # gravity bends the elastic hinges: gravcomp is taken back there
            self.data.qfrc_applied[self._elastic_dofs] -= self.data.qfrc_gravcomp[self._elastic_dofs]

    def push(self) -> None:
        """Stage a push on the tool (from the signal handler: only two numbers change here; the physics thread
        applies it at its next step)."""
        self._push_until = float(self.data.time) + PUSH_S

    def _apply_push(self) -> None:
        """While a staged push lasts: ``PUSH_FORCE`` N horizontally, perpendicular to the arm's plane, on the
        tool point, as a generalized force on the arm's joints (and kept for the external force estimate)."""
        if self.data is None or self.data.time > self._push_until:
            self._push_tau = np.zeros(7)
            return
        m, d = self.model, self.data
        x = d.xpos[self._tool_body]
        side = np.cross([0.0, 0.0, 1.0], x)
        n = float(np.linalg.norm(side))
        F = PUSH_FORCE * (side / n if n > 1e-6 else np.array([0.0, 1.0, 0.0]))
        jp = np.zeros((3, m.nv))
        mujoco.mj_jac(m, d, jp, np.zeros((3, m.nv)), x, self._tool_body)
        self._push_tau = jp[:, self.arm_dofs_idx].T @ F
        d.qfrc_applied[self.arm_dofs_idx] += self._push_tau

    # ---- state --------------------------------------------------------------------------------------------
    # franka-sim's physics step publishes a fresh snapshot dict for the network threads to read; the station's
    # fields are put in before it is stored, so no reader ever sees a snapshot without them
    @property
    def _state_snapshot(self) -> dict:
        return self._snapshot

    @_state_snapshot.setter
    def _state_snapshot(self, snap: dict) -> None:
        if getattr(self, "_ball", None) is not None and self.data is not None:
            snap = self._station_fields(dict(snap))
        self._snapshot = snap

    def _station_fields(self, snap: dict) -> dict:
        q = snap["q"]
        cm = self.controller_model
        O_T_EE = cm.flange_pose(q) @ self._f_t_ee
        O_T_K = O_T_EE @ self.EE_T_K
        # external torque: what the contacts (and joint limits) push on the measured joints; the robot reports
        # what it exerts on the environment (libfranka robot_state.h: robot -> environment positive)
        tau = -np.asarray(self.data.qfrc_constraint[self.arm_dofs_idx], float) - self._push_tau
        self._tau_ext = EST_ALPHA * self._tau_ext + (1 - EST_ALPHA) * tau
        J = cm.jacobian(O_T_K[:3, 3])
        self._noise = EST_ALPHA * self._noise + math.sqrt(1 - EST_ALPHA ** 2) * self.rng.normal(
            0.0, self.force_noise, 6) * np.array([1, 1, 1, 0.05, 0.05, 0.05])
        sv = np.linalg.svd(J, compute_uv=False)
        if sv[-1] < 1e-3:  # near a singularity the robot reports zero (robot_state.h)
            F = np.zeros(6)
            tau_est = self._tau_ext
        else:
            F = np.linalg.lstsq(J.T, self._tau_ext, rcond=None)[0] + self._noise
            tau_est = J.T @ F
        R = O_T_K[:3, :3]
        snap["O_T_EE"] = O_T_EE.T.flatten()
        snap["tau_ext_hat_filtered"] = tau_est.tolist()
        snap["O_F_ext_hat_K"] = F.tolist()
        snap["K_F_ext_hat_K"] = np.concatenate([R.T @ F[:3], R.T @ F[3:]]).tolist()
        self._watch_nests()
        return snap

    def _watch_nests(self) -> None:
        """A nest the ball has left moves by the seating noise before the next seating."""
        ball = self.data.geom_xpos[self._ball]
        for k, nst in enumerate(self._nests):
            d = float(np.linalg.norm(ball - self.data.mocap_pos[nst["mocap"]]))
            if d < 0.5e-3:
                self.seated[nst["label"]] = True
            elif self.seated.get(nst["label"]) and d > self._ball_radius + 5e-3:
                self._jitter(k)


class AsyncGenerator:
    """The robot-side asynchronous position generator: towards the last target, all joints arriving together,
    within the ``Move``'s maximum velocities and ``ASYNC_ACCELERATION``."""

    def __init__(self, q, vmax) -> None:
        self.p = np.asarray(q, float).copy()
        self.v = np.zeros(7)
        self.a = np.zeros(7)
        self.vmax = np.minimum(np.abs(np.asarray(vmax, float)), FR3_VMAX)
        self.target: np.ndarray | None = None
        self._vlim = self.vmax.copy()
        self._alim = np.full(7, ASYNC_ACCELERATION)

    def set_target(self, q) -> None:
        q = np.asarray(q, float)
        if self.target is not None and np.array_equal(q, self.target):
            return
        e = np.abs(q - self.p)
        if e.max() >= 1e-12:
            # the joint that needs longest sets the pace; the others scale down with their distance
            t = e / self.vmax + self.vmax / ASYNC_ACCELERATION
            k = int(np.argmax(np.where(e > 1e-9, t, 0.0)))
            scale = np.where(e > 1e-12, e / max(e[k], 1e-12), 0.0)
            self._vlim = np.maximum(self.vmax[k] * scale, 1e-6)
            self._alim = np.maximum(ASYNC_ACCELERATION * scale, 1e-6)
        self.target = q.copy()  # last: the physics thread steps towards it from now on

    def step(self, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        target = self.target
        if target is None:
            return self.p, self.v, np.zeros(7)
        e = target - self.p
        v_des = np.sign(e) * np.minimum(self._vlim, np.sqrt(2 * self._alim * np.abs(e)))
        # within the robot's position-based velocity envelope (with a margin for the arm's tracking error)
        lo, up = velocity_envelope(self.p)
        v_des = np.clip(v_des, 0.9 * lo, 0.9 * up)
        a = np.clip((v_des - self.v) / dt, -self._alim, self._alim)
        v = self.v + a * dt
        # a joint within one step of its target at the speed it may still have there arrives and stops (a
        # discrete braking law otherwise dithers about the target)
        arrive = np.abs(e) <= np.maximum(np.abs(v), 2 * self._alim * dt) * dt
        self.v = np.where(arrive, 0.0, v)
        self.p = np.where(arrive, target, self.p + v * dt)
        self.a = np.where(arrive, 0.0, a)
        return self.p, self.v, self.a


FR3_VMAX = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])  # rad/s, Franka's FR3 limits
# the position-based velocity envelope (Franka, "Limits for Franka Research 3"; libfranka rate_limiting.h)
FR3_QMIN = np.array([-2.7501, -1.7918, -2.9065, -3.0481, -2.8101, 0.54092, -3.0196])
FR3_QMAX = np.array([2.7501, 1.7918, 2.9065, -0.1458, 2.8101, 4.5205, 3.0196])
FR3_VOFFSET = np.array([0.30, 0.20, 0.20, 0.30, 0.35, 0.35, 0.35])
FR3_DECEL = np.array([6.0, 2.585, 3.5, 4.0, 17.0, 5.5, 17.0])


def velocity_envelope(q) -> tuple[np.ndarray, np.ndarray]:
    up = np.minimum(FR3_VMAX, np.maximum(0.0, -FR3_VOFFSET + np.sqrt(np.maximum(0.0, 2 * FR3_DECEL * (FR3_QMAX - q)))))
    lo = np.maximum(-FR3_VMAX, np.minimum(0.0, FR3_VOFFSET - np.sqrt(np.maximum(0.0, 2 * FR3_DECEL * (q - FR3_QMIN)))))
    return lo, up


class _State(RobotState):
    """The published state: the controller mode the client asked for (the server runs a Cartesian-impedance
    joint-position motion through franka-sim's joint-impedance path)."""

    cartesian = False

    def pack_state(self) -> bytes:
        if self.cartesian and self.state["controller_mode"] == LibfrankaControllerMode.kJointImpedance:
            self.state["controller_mode"] = LibfrankaControllerMode.kCartesianImpedance
            try:
                return super().pack_state()
            finally:
                self.state["controller_mode"] = LibfrankaControllerMode.kJointImpedance
        return super().pack_state()


class StationServer(FrankaSimServer):
    """franka-sim's FCI server with the robot-side behaviour the station needs (module docstring)."""

    def __init__(self, scene: dict, host: str) -> None:
        self.physics_sim = StationArm(scene)
        self._async: AsyncGenerator | None = None
        self._pending: AsyncGenerator | None = None
        self._async_lock = threading.Lock()
        self._final_state_id = 0
        self.upper_torque: list[float] | None = None  # N m per joint; None until the client sets them
        self.upper_force: list[float] | None = None  # N, N m per Cartesian axis
        self._peak, self._peak_log = 0.0, os.environ.get("FRANKA_SIM_PEAK_LOG", "")
        super().__init__(host=host, physics_sim=self.physics_sim, urdf_path=scene["served_urdf"],
                         enable_gripper=False, enforce_comm_constraints=bool(scene.get("enforce_comm", True)),
                         enforce_motion_limits=bool(scene.get("enforce_limits", True)))

    def reset_state(self):
        super().reset_state()
        s = _State()
        s.state, s._message_id = self.robot_state.state, self.robot_state._message_id
        self.robot_state = s
        with self._async_lock:
            self._async = None
            self.physics_sim.generator = None
        self.physics_sim.controller = "joint"
        self._final_state_id = 0  # the id of the state that ended the last finished motion

    # ---- Move: controller mode and the asynchronous generator ----------------------------------------------
    def handle_move_command(self, client_socket, header, payload: bytes) -> None:
        cartesian = False
        gen = None
        try:
            controller, generator = struct.unpack("<II", payload[:8])
            if controller == ControllerMode.kCartesianImpedance and generator == MotionGeneratorMode.kJointPosition:
                # franka-sim runs no physics for this pair: it is handed on as joint impedance (its limit and
                # communication checks then apply) and the Cartesian law runs in StationArm
                cartesian = True
                payload = struct.pack("<II", ControllerMode.kJointImpedance, generator) + payload[8:]
            if len(payload) >= 57 + 56 and payload[56] and generator == MotionGeneratorMode.kJointPosition:
                vmax = struct.unpack("<7d", payload[57:57 + 56])
                gen = AsyncGenerator(self.physics_sim.get_robot_state()["q"], vmax)
        except struct.error:
            pass
        self.robot_state.cartesian = cartesian
        self.physics_sim.controller = "cartesian" if cartesian else "joint"
        # pending before the Move is answered (the client sends its first target right after kMotionStarted),
        # running once it is accepted; ending the previous motion inside the Move clears only the running one
        with self._async_lock:
            self._pending = gen
        if os.environ.get("FRANKA_SIM_DEBUG"):
            log.warning("Move id %s async %s cartesian %s", header.command_id, gen is not None, cartesian)
        try:
            super().handle_move_command(client_socket, header, payload)
        finally:
            with self._async_lock:
                accepted = self.robot_state.state["robot_mode"] == 2  # kMove
                self._async = gen if gen is not None and accepted else None
                self._pending = None
                self.physics_sim.generator = self._async

    def _absorb_within_motion_limits(self, command, *, fresh: bool) -> bool:
        with self._async_lock:
            gen = self._async or self._pending
        if gen is None:
            return super()._absorb_within_motion_limits(command, fresh=fresh)
        gen.set_target(command["q_c"])  # a target, not a 1 kHz waypoint: the generator moves there
        return False

    def _account_for_communication_cycle(self) -> None:
        with self._async_lock:
            gen = self._async or self._pending
        if gen is None:
            return super()._account_for_communication_cycle()
        # variable rate: the client sends targets when it likes; the robot generates every cycle (in the physics
        # thread) and reports what it commands
        self.robot_state.state["q_d"] = gen.p.tolist()
        self.robot_state.state["dq_d"] = gen.v.tolist()
        self.robot_state.state["ddq_d"] = gen.a.tolist()
        self.robot_state.state["control_command_success_rate"] = 1.0

    def _finish_motion(self, command) -> None:
        """libfranka sends one more finishing command after the state that says the motion is over (it receives,
        then sends, then checks); it echoes the id of that final state. franka-sim ends whatever motion runs when
        that late one arrives after the next ``Move`` was accepted (its stale test, ``id < epoch``, misses it:
        the final state is sent outside the publish loop that sets the epoch), answers that ``Move`` kSuccess
        right behind kMotionStarted, and libfranka, which keeps one response per command id, then waits for
        ever. A real robot drops a command that echoes an old state (the 1 ms constraint). Here: a finishing
        command that echoes the final state of the motion finished before, or an older one, is that motion's."""
        if command["message_id"] <= self._final_state_id:
            if os.environ.get("FRANKA_SIM_DEBUG"):
                log.warning("late finish of the motion before (id %s <= %s) ignored", command["message_id"],
                            self._final_state_id)
            return
        generation = self._motion_generation
        super()._finish_motion(command)
        if self._motion_generation == generation and self.robot_state.state["robot_mode"] != 2:
            self._final_state_id = int(self.robot_state.state["message_id"])

    def _engage_idle_hold(self, reason, motion_id=None) -> None:
        if os.environ.get("FRANKA_SIM_DEBUG"):
            log.warning("idle hold: %s (motion %s)", reason, motion_id)
        with self._async_lock:
            self._async = None
            self.physics_sim.generator = None
        super()._engage_idle_hold(reason, motion_id)

    # ---- collision reflexes ---------------------------------------------------------------------------------
    def handle_set_collision_behavior_command(self, client_socket, header, payload: bytes):
        with contextlib.suppress(struct.error, ValueError):
            cmd = SetCollisionBehaviorCommand.from_bytes(payload)
            # the acceleration and the nominal set apply in different phases of a motion, which the robot does
            # not publish: the lower of the two is the strictest reading of both
            self.upper_torque = [min(a, b) for a, b in zip(cmd.upper_torque_thresholds_acceleration,
                                                           cmd.upper_torque_thresholds_nominal, strict=True)]
            self.upper_force = [min(a, b) for a, b in zip(cmd.upper_force_thresholds_acceleration,
                                                          cmd.upper_force_thresholds_nominal, strict=True)]
        super().handle_set_collision_behavior_command(client_socket, header, payload)

    def _run_safety_velocity_check(self, sim_state) -> None:
        super()._run_safety_velocity_check(sim_state)
        self._run_collision_reflex(sim_state)

    def _run_collision_reflex(self, sim_state) -> None:
        """Once per published state: a motion that pushes harder than the upper collision thresholds stops with
        the reflex, latched in ``current_errors``/``last_motion_errors``, the ``Move`` answered kReflexAborted
        (libfranka then raises ``ControlException``), until ``AutomaticErrorRecovery``."""
        moving = self.robot_state.state["robot_mode"] == RobotMode.kMove
        if not isinstance(sim_state, dict) or "O_F_ext_hat_K" not in sim_state or not (moving or self._peak):
            return  # the publish loop's 1 ms: nothing to do between motions
        if self._peak_log:
            self._note_peak(sim_state["O_F_ext_hat_K"], moving)
        if self.upper_force is None or not moving:
            return
        # plain floats: this runs in the 1 kHz publish loop, where numpy's per-call cost would show
        over = [abs(f) - u for f, u in zip(sim_state["O_F_ext_hat_K"], self.upper_force, strict=True)]
        if max(over) > 0:
            i = over.index(max(over))
            reason = (f"cartesian_reflex: external wrench {over[i] + self.upper_force[i]:.1f} on axis {i} above the "
                      f"threshold {self.upper_force[i]:g}")
            index = CARTESIAN_REFLEX_INDEX
        else:
            over = [abs(f) - u for f, u in zip(sim_state["tau_ext_hat_filtered"], self.upper_torque, strict=True)]
            if max(over) <= 0:
                return
            j = over.index(max(over))
            reason = (f"joint_reflex: external torque {over[j] + self.upper_torque[j]:.1f} N m on joint {j + 1} above "
                      f"the threshold {self.upper_torque[j]:g} N m")
            index = JOINT_REFLEX_INDEX
        with self._motion_lock:
            if self.robot_state.state["robot_mode"] == RobotMode.kMove:
                self._abort_with_error(index, reason, self._motion_generation)

    def _note_peak(self, F, moving: bool) -> None:
        """The largest estimated contact force of each motion, appended to ``$FRANKA_SIM_PEAK_LOG`` (one number in
        N a line) when it is set: what a seating loads the cone with, measured where the reflex judges it."""
        if moving:
            self._peak = max(self._peak, float(np.linalg.norm(np.asarray(F, float)[:3])))
            return
        peak, self._peak = self._peak, 0.0
        with open(self._peak_log, "a") as f:
            f.write(f"{peak:.2f}\n")

    # ---- impedance and stiffness frame ----------------------------------------------------------------------
    def handle_set_joint_impedance_command(self, client_socket, header, payload: bytes):
        with contextlib.suppress(struct.error):
            self.physics_sim.set_joint_impedance(struct.unpack("<7d", payload[:56]))
        super().handle_set_joint_impedance_command(client_socket, header, payload)

    def handle_set_cartesian_impedance_command(self, client_socket, header, payload: bytes):
        with contextlib.suppress(struct.error):
            self.physics_sim.set_cartesian_impedance(struct.unpack("<6d", payload[:48]))
        super().handle_set_cartesian_impedance_command(client_socket, header, payload)

    def handle_set_ee_to_k_command(self, client_socket, header, payload: bytes):
        with contextlib.suppress(struct.error):
            self.physics_sim.set_stiffness_frame(struct.unpack("<16d", payload[:128]))
        super().handle_set_ee_to_k_command(client_socket, header, payload)

    # ---- run ------------------------------------------------------------------------------------------------
    def serve(self, ready) -> None:
        """Bind, build the scene, say ready, serve (physics in this thread) until ``stop()``."""
        self._arm_shutdown()
        self.running = True
        self._bind_listener()
        self.physics_sim.initialize_simulation()
        threading.Thread(target=self.run_server, name="fci-accept", daemon=True).start()
        ready()
        self.physics_sim.running = True
        self.physics_sim.run_simulation()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="scene file written by station mock franka (JSON)")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--exit-with-parent", action="store_true")
    ap.add_argument("--ready-line", default=None, help="the line to print once serving (default: a short one)")
    ap.add_argument("--remove-dir", default=None, help="a folder to delete at exit (the scene's)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="franka-sim: %(name)s: %(message)s")
    if not a.verbose:
        logging.getLogger("franka_sim").setLevel(logging.ERROR)
    with open(a.scene, encoding="utf-8") as f:
        scene = json.load(f)
    # the URDF the robot serves over GetRobotModel: franka-sim's bundled FR3 (franka_description, no hand) unless
    # the scene names another
    scene["served_urdf"] = scene.get("served_urdf") or str(FrankaSimServer.DEFAULT_ARM_URDF)
    for key, path_key in (("true_urdf_text", "true_urdf"), ("served_urdf_text", "served_urdf")):
        with open(scene[path_key], encoding="utf-8") as f:
            scene[key] = f.read()
    with contextlib.suppress(OSError):  # the real controller is a computer of its own: where allowed, this
        os.nice(-10)  # process runs ahead of the host
    server = StationServer(scene, scene["host"])
    stop = threading.Event()

    def shutdown(*_):
        stop.set()
        server.physics_sim.running = False

    signal.signal(signal.SIGTERM, shutdown)
    signal.signal(signal.SIGINT, shutdown)
    signal.signal(signal.SIGUSR1, lambda *_: server.physics_sim.push())
    parent = os.getppid()

    def watch_parent():
        while not stop.wait(0.5):
            if a.exit_with_parent and os.getppid() != parent:
                shutdown()

    threading.Thread(target=watch_parent, daemon=True).start()

    def ready():
        print(a.ready_line or f"franka-sim ready on {scene['host']}:1337", flush=True)

    try:
        server.serve(ready)
    except OSError as e:
        print(f"franka-sim: cannot serve on {scene['host']}:1337: {e}", file=sys.stderr, flush=True)
        return 2
    finally:
        server.physics_sim.running = False
        with contextlib.suppress(Exception):  # teardown of a server that never started
            server.stop()
        if a.remove_dir:
            import shutil

            shutil.rmtree(a.remove_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
