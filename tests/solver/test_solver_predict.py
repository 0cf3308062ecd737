"""The plan-time check ``station.solver.predict``: from planned poses and a declared noise, before motion.
Checked against what the solver then reports on simulated touches at those poses (truth: a perturbed robot,
independent noise), and against the structural fact that an omx cannot see its shoulder offset with an
unknown socket."""

import numpy as np
import pytest

from station.kinematics import load_model
from station.solver import Observations, SolverInputError, predict, solve
from station.solver.simulate import noisy_q, touch_q

NOISE = 50e-6


def _plan(model, rng):
    c = (model.lower + model.upper) / 2
    offs = [np.array([0.3, 0.2, 0.2, 0.1]), np.array([-0.4, 0.1, 0.4, 0.2])]
    pts = {chr(65 + i): model.position(c + o) for i, o in enumerate(offs)}
    q = np.vstack([touch_q(model, p, 12, rng, centre=c, spread=0.9) for p in pts.values()])
    labels = np.array([lb for lb in pts for _ in range(12)], dtype=object)
    return pts, q, labels


def test_prediction_matches_the_solvers_std_on_the_touches_that_follow():
    nominal = load_model("omx")
    rng = np.random.default_rng(3)
    pts, q, labels = _plan(nominal, rng)
    ident = "offset.j2,offset.j3,offset.j4"
    pred = predict(nominal, q, labels, ident, pts, noise=NOISE)
    assert pred.ok and set(pred.parameters) == {"offset.j2", "offset.j3", "offset.j4"}
    # the robot: small hidden offsets; the technician touches the same points near the planned poses
    truth = nominal.with_params({"offset.j2": 0.004, "offset.j3": -0.003, "offset.j4": 0.005})
    qt = np.vstack([touch_q(truth, pts[lb], 1, rng, centre=qi, spread=0.02) for qi, lb in zip(q, labels, strict=True)])
    res = solve(nominal, Observations(noisy_q(truth, qt, np.array([pts[lb] for lb in labels]), NOISE, rng), labels),
                ident, pts, noise=NOISE)
    assert res.trusted
    for n, p in pred.parameters.items():
        assert p.std == pytest.approx(res.parameters[n].std, rel=0.1), n


def test_unknown_socket_omx_cannot_see_its_shoulder_offset():
    nominal = load_model("omx")
    pts, q, labels = _plan(nominal, np.random.default_rng(4))
    pred = predict(nominal, q, labels, "offsets", "unknown", noise=NOISE)
    assert not pred.ok
    assert "offset.j1" in pred.missing and pred.parameters["offset.j1"].std is None
    assert all(pred.missing.values())  # every missing parameter comes with a reason
    with pytest.raises(SolverInputError):
        predict(nominal, q, labels, "offsets", "unknown", noise=-1.0)
