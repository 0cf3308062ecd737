"""The model the robot serves, checked against the station's model before anything moves.

libfranka >= 0.18 builds its kinematics and dynamics model client-side from the URDF the robot serves
(``GetRobotModel``, FCI server version 10; pylibfranka ``Robot.load_model``). pylibfranka does not hand out
that URDF, but the model built from it answers ``zero_jacobian`` for any joint position: the Jacobian of the
end-effector frame (flange x ``F_T_EE``) in the base frame, linear rows first. Its columns are the joint axes
and their lever arms to the end effector, so equal Jacobians at a spread of joint positions mean the same
kinematic chain. The station's model must give the same (to ``JACOBIAN_TOL``) with its tool set to
``F_T_EE``; and the pose the controller reports (``O_T_EE``, from its own model at the measured joints) must
be the station model's forward kinematics there (to ``POSE_TOL_M``/``POSE_TOL_RAD``: the state travels as
32-bit floats)."""

from __future__ import annotations

import numpy as np

from station.robot.errors import IdentityMismatch

JACOBIAN_TOL = 1e-6  # m (linear rows), rad/rad (angular rows)
POSE_TOL_M, POSE_TOL_RAD = 1e-5, 1e-5
PROBES = 8  # joint positions the Jacobians are compared at


def with_flange_to_ee(model, F_T_EE: np.ndarray):
    """``model`` (its tool = the flange) with the tool moved to ``flange @ F_T_EE``."""
    from station.kinematics.se3 import matrix_to_rpy

    tool = _tool(model) @ F_T_EE
    r = matrix_to_rpy(tool[:3, :3])
    vals = dict(zip(("tcp.x", "tcp.y", "tcp.z"), tool[:3, 3], strict=True))
    vals.update(zip(("tcp.rx", "tcp.ry", "tcp.rz"), r, strict=True))
    return model.with_params({k: float(v) for k, v in vals.items() if k in model.param_names})


def _tool(model) -> np.ndarray:
    from station.kinematics.se3 import rpy_to_matrix

    T = np.eye(4)
    names = model.param_names
    if "tcp.rx" in names:
        T[:3, :3] = rpy_to_matrix(np.array([model.param("tcp.rx"), model.param("tcp.ry"), model.param("tcp.rz")]))
    if "tcp.x" in names:
        T[:3, 3] = [model.param("tcp.x"), model.param("tcp.y"), model.param("tcp.z")]
    return T


def column_major(a) -> np.ndarray:
    return np.asarray(a, float).reshape(4, 4).T


def check_served_model(where: str, model, served, state) -> float:
    """Compare the served model's end-effector Jacobians with ``model``'s at ``PROBES`` joint positions (the
    current one and a fixed spread within the limits). Returns the largest difference; raises
    ``IdentityMismatch`` naming the worst joint when it exceeds ``JACOBIAN_TOL``."""
    ee = with_flange_to_ee(model, column_major(state.F_T_EE))
    rng = np.random.default_rng(26)
    lo, hi = model.lower, model.upper
    Q = np.vstack([np.asarray(state.q, float)[None], lo + (hi - lo) * rng.uniform(0.1, 0.9, (PROBES - 1, 7))])
    _, Jq, _ = ee.jacobians(Q)
    worst, where_worst = 0.0, (0, 0)
    q_orig = list(state.q)
    try:
        for k, q in enumerate(Q):
            state.q = q.tolist()
            J = np.asarray(served.zero_jacobian(state), float).reshape(7, 6).T
            d = np.abs(J - Jq[k])
            if d.max() > worst:
                worst, where_worst = float(d.max()), np.unravel_index(int(np.argmax(d)), d.shape)
    finally:
        state.q = q_orig
    if worst > JACOBIAN_TOL:
        row, joint = where_worst
        raise IdentityMismatch(f"{where}: the robot serves a kinematic model other than {model.name!r}: their "
                               f"Jacobians differ by {worst:.3g} ({'linear' if row < 3 else 'angular'} row, joint "
                               f"{joint + 1}); give the URL the robot's model (model=...)")
    return worst


def check_reported_pose(where: str, model, state) -> tuple[float, float]:
    """``O_T_EE`` against the station model's forward kinematics at the reported joints."""
    from station.kinematics.se3 import orientation_error

    ee = with_flange_to_ee(model, column_major(state.F_T_EE))
    T = column_major(state.O_T_EE)
    mine = ee.fk(np.asarray(state.q, float))
    dp = float(np.linalg.norm(T[:3, 3] - mine[:3, 3]))
    dr = float(np.linalg.norm(orientation_error(T[None, :3, :3], mine[None, :3, :3])[0]))
    if dp > POSE_TOL_M or dr > POSE_TOL_RAD:
        raise IdentityMismatch(f"{where}: the controller puts the end effector {dp * 1e3:.3f} mm / "
                               f"{np.degrees(dr):.4f} deg from where model {model.name!r} does at the same joints; "
                               "the station's model is not the controller's (model=..., or the end effector set in "
                               "Desk)")
    return dp, dr
