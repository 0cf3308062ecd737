"""The solver's shortcuts change how fast it gets to the minimum, never which minimum or what it reports:
the same data solved with a far tighter stopping rule give the same estimates (to a small fraction of a
standard deviation), the same identified set and the same reasons; and the estimate is a minimum of the
MAP objective. Truth comes from a simulated UR5e with hidden offsets and tool (IK on the true model,
20 um touch noise)."""

import numpy as np
import pytest

import station.solver.estimator as est
from station.kinematics import load_model
from station.solver import solve
from station.solver.problem import Problem
from station.solver.simulate import touch_observations

UR_HOME = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


@pytest.fixture(scope="module")
def touches():
    nominal = load_model("ur5e").with_params({"tcp.x": 0.02, "tcp.y": -0.01, "tcp.z": 0.12})
    rng = np.random.default_rng(21)
    hidden = {f"offset.j{i}": rng.uniform(-0.005, 0.005) for i in range(2, 6)}
    truth = nominal.with_params({**hidden, "tcp.x": 0.0211, "tcp.y": -0.0092, "tcp.z": 0.1214})
    obs = touch_observations(truth, {"A": truth.position(UR_HOME)}, 30, rng, centre=UR_HOME, spread=0.35)
    return nominal, truth, obs


def _same(a, b, tol_std=1e-3):
    assert a.identified == b.identified
    assert a.unidentifiable == b.unidentifiable
    for n in a.identified:
        pa, pb = a.parameters[n], b.parameters[n]
        assert abs(pa.value - pb.value) <= tol_std * pa.std, n
        assert pb.std == pytest.approx(pa.std, rel=1e-4)
    assert a.rank == b.rank and a.converged and b.converged and a.trusted and b.trusted


def test_tight_stopping_rule_changes_nothing(touches, monkeypatch):
    nominal, truth, obs = touches
    fast = solve(nominal, obs, "offsets,tcp")
    assert set(fast.unidentifiable) == {"offset.j1", "offset.j6"}
    for n in ("offset.j2", "offset.j3", "tcp.z"):
        assert abs(fast.parameters[n].value - truth.param(n)) < 4 * fast.parameters[n].std
    monkeypatch.setattr(est, "STEP_TOL", 1e-9)  # every step evaluated, no linear last step
    monkeypatch.setattr(est, "SIGMA_TOL", 1e-6)  # refit until sigma stands still
    _same(fast, solve(nominal, obs, "offsets,tcp"))


def test_rest_of_the_way_is_below_the_tolerance(touches):
    """One more undamped Gauss-Newton step of the MAP objective from the returned estimate moves no
    parameter by more than STEP_TOL of its standard deviation."""
    nominal, _, obs = touches
    res = solve(nominal, obs, "offsets,tcp")
    prob = Problem(nominal, obs, est.select_names(nominal, "offsets,tcp"), "unknown")
    x = prob.x_nominal.copy()
    for i, n in enumerate(prob.names):
        if n in res.parameters and res.parameters[n].identifiable:
            x[i] = res.parameters[n].value
    act = [prob.names.index(n) for n in res.identified]
    r, J = prob.residual_jacobian(x)
    prior = np.array([res.parameters[prob.names[j]].prior_std or np.inf for j in act])
    lam = np.where(np.isfinite(prior), res.noise["sigma_m"] ** 2 / np.where(np.isfinite(prior), prior, 1) ** 2, 0)
    H = J[:, act].T @ J[:, act] + np.diag(lam)
    g = J[:, act].T @ r + lam * (x[act] - prob.x_nominal[act])
    du = -np.linalg.solve(H, g)
    std = res.noise["sigma_m"] * np.sqrt(np.diag(np.linalg.inv(H)))  # given what is kept (no prior spread)
    assert np.max(np.abs(du) / std) < 2 * est.STEP_TOL
