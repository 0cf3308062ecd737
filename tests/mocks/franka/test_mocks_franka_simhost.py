"""``station.mocks.franka.simhost``, the simulator process, in the environment it runs in (franka-sim's: MuJoCo,
numpy 1.26, no station), by its pieces that need no server: the URDF made fit for MuJoCo's compiler, the
controller's own model (``O_T_EE`` and the Jacobian the external force is reported through), the robot-side
asynchronous generator and its velocity envelope, the socket frame. pytest runs this file again as a script
with that interpreter; the script prints what it computed and the test judges it against independent sources:
the station's FR3 model (Franka's published table) and libfranka's envelope constants
(``station.drivers.franka.limits``). The whole simulator: tests/drivers/franka/test_franka_driver.py."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[3]
Q = [[0.0, -0.3, 0.0, -2.2, 0.0, 2.0, 0.8], [0.4, 0.2, -0.3, -1.6, 0.5, 2.6, -0.4],
     [-1.0, 0.8, 0.9, -0.9, -1.2, 1.2, 2.0]]
VMAX = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5]


def _simhost():
    """The module under its import name where the station is installed with MuJoCo, else from its file (the
    franka-sim environment has no station package)."""
    try:
        from station.mocks.franka import simhost
    except ImportError:
        import importlib.util

        spec = importlib.util.spec_from_file_location("simhost", ROOT / "mocks" / "franka" / "simhost.py")
        simhost = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(simhost)
    return simhost


def _generate(sh, q0, q1, vmax):
    """Run the asynchronous generator from ``q0`` to ``q1`` in 1 ms steps: positions, velocities, arrival step."""
    gen = sh.AsyncGenerator(q0, vmax)
    gen.set_target(q1)
    p, v = [np.array(q0, float)], [np.zeros(7)]
    for _ in range(20000):
        pk, vk, _ = gen.step(0.001)
        p.append(pk.copy())
        v.append(vk.copy())
        if np.array_equal(pk, q1) and not vk.any():
            break
    return np.array(p), np.array(v)


def _child() -> dict:
    """In the franka-sim interpreter: what the pieces compute."""
    from franka_sim.franka_sim_server import FrankaSimServer

    sh = _simhost()
    served = Path(FrankaSimServer.DEFAULT_ARM_URDF).read_text()
    stripped = sh._strip_urdf(served)
    cm = sh.ControllerModel(served)
    poses, jacobians = [], []
    for q in Q:
        T = cm.flange_pose(q)
        poses.append(T.tolist())
        jacobians.append(cm.jacobian(T[:3, 3]).tolist())
    q0, q1 = np.array(Q[0]), np.array(Q[1])
    p, v = _generate(sh, q0, q1, VMAX)
    lo, up = sh.velocity_envelope(np.array(Q))
    F = sh._frame([0.2, -0.1, 1.0])
    return {"visual": "<visual" in stripped, "collision": "<collision" in stripped,
            "compiler": 'fusestatic="false"' in stripped, "poses": poses, "jacobians": jacobians,
            "gen_p": p.tolist(), "gen_v": v.tolist(), "env": [lo.tolist(), up.tolist()], "frame": F.tolist()}


def test_the_simulator_pieces_against_independent_sources(tmp_path):
    from station.drivers.franka import limits
    from station.mocks.franka.simenv import sim_python

    from station.kinematics import load_model

    run = subprocess.run([str(sim_python()), __file__], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert not got["visual"] and not got["collision"] and got["compiler"]  # meshes gone, frames kept
    # the controller's model is Franka's FR3: flange pose and Jacobian as the station's fr3 (tool = flange)
    fr3 = load_model("fr3")
    for q, T, J in zip(Q, got["poses"], got["jacobians"], strict=True):
        assert np.allclose(np.array(T), fr3.fk(np.array(q)), atol=1e-9)
        assert np.allclose(np.array(J), fr3.jacobian_q(np.array(q)).reshape(6, 7), atol=1e-9)
    # the generator: every joint arrives together, none faster than asked, accelerations within its cap
    p, v = np.array(got["gen_p"]), np.array(got["gen_v"])
    assert np.allclose(p[-1], Q[1], atol=0) and not v[-1].any()
    assert np.max(np.abs(v)) <= 0.5 + 1e-9
    dv = np.abs(np.diff(v, axis=0))
    assert np.max(dv[:-1]) / 0.001 <= 4.0 + 1e-6
    # the arrival step: a joint within one step of its target stops there (the generator's discrete braking law),
    # from the little speed it still had; the joint servo under it smooths that
    assert np.max(dv[-1]) < 0.1
    moving = np.abs(np.asarray(Q[1]) - Q[0]) > 1e-9
    arrive = [int(np.flatnonzero(np.abs(p[:, j] - Q[1][j]) > 1e-9).max()) for j in np.flatnonzero(moving)]
    assert max(arrive) - min(arrive) <= 2  # within 2 ms of each other
    # its envelope is libfranka's (the driver's minus its 1 mrad/s tolerance)
    lo, up = (np.array(x) for x in got["env"])
    dlo, dup = limits.velocity_envelope(np.array(Q))
    assert np.allclose(up, dup + limits.TOLERANCE) and np.allclose(lo, dlo - limits.TOLERANCE)
    # a socket's frame: orthonormal, right-handed, z along the approach
    F = np.array(got["frame"])
    assert np.allclose(F.T @ F, np.eye(3)) and np.linalg.det(F) > 0
    assert np.allclose(F[:, 2], np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0]))


if __name__ == "__main__":  # the franka-sim interpreter runs this file for the test above
    print(json.dumps(_child()))
    sys.exit(0)
