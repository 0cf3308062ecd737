"""Deliberately redundant parameter sets (full POE local frames, every DH parameter): the rank analysis
must keep the solve well-posed, name every parameter it drops, and the calibrated model must predict
held-out poses of the TRUE robot to the noise level (a check that does not depend on how the redundant
parameters were split)."""

import numpy as np

from station.kinematics import from_poe, load_model, screws_of
from station.solver import Observations, solve
from station.solver.simulate import random_q

NOISE = 20e-6
UR_HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


def _poe_twin(dh):
    screws, home = screws_of(dh)
    tool = {k: dh.param(f"tcp.{k}") for k in ("x", "y", "z", "rx", "ry", "rz")}
    return from_poe("ur5e-poe", list(dh.joints), screws, home, tool=tool)


def _check(nominal, truth, identify, rng):
    q = random_q(nominal, 80, rng, spread=0.7, centre=UR_HOME)
    qh = random_q(nominal, 30, rng, spread=0.7, centre=UR_HOME)
    frame = {"base.x": 0.8, "base.y": 0.5, "base.z": -0.1, "base.rz": -0.4}
    t = truth.with_params(frame)
    obs = Observations(q, measured=t.position(q) + rng.normal(0, NOISE, (len(q), 3)))
    ho = Observations(qh, measured=t.position(qh) + rng.normal(0, NOISE, (len(qh), 3)))
    res = solve(nominal, obs, identify, holdout=ho)
    assert res.converged
    assert res.rank < res.n_parameters  # the set is redundant
    for p in res.parameters.values():
        assert p.identifiable == (p.std is not None)
        assert p.identifiable or p.reason
    # prediction of unseen poses at the noise level (3-D RMS of N(0, s^2 I3) is s*sqrt(3))
    assert res.holdout["rms_m"] < 1.5 * np.sqrt(3) * NOISE
    assert res.holdout["rms_nominal_m"] > 20 * res.holdout["rms_m"]
    return res


def test_full_poe_frames_with_offsets():
    dh = load_model("ur5e").with_params({"tcp.x": 0.02, "tcp.z": 0.12})
    nominal = _poe_twin(dh)
    rng = np.random.default_rng(31)
    names = nominal.select("dh,offsets,tcp")
    hidden = {n: nominal.param(n) + rng.normal(0, 1e-3 if n.endswith(("x", "y", "z")) else 2e-3) for n in names
              if not n.startswith("tcp.r")}
    res = _check(nominal, nominal.with_params(hidden), "offsets,dh,tcp", rng)
    # a joint offset and the rotation of its own local frame about the same axis are one thing
    assert "offset.j3" in res.unidentifiable["poe.j3.rz"]


def test_every_dh_parameter():
    nominal = load_model("ur5e").with_params({"tcp.x": 0.02, "tcp.z": 0.12})
    rng = np.random.default_rng(32)
    names = nominal.select("dh,offsets")
    hidden = {n: nominal.param(n) + rng.normal(0, 1e-3 if n.endswith((".a", ".d")) else 1e-3) for n in names}
    res = _check(nominal, nominal.with_params(hidden), "offsets,dh,tcp,beta", rng)
    assert "offset.j1" in res.unidentifiable
