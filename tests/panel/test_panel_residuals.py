"""``station.panel.residuals``: the live residual plot's distances for the samples of a session, against tips
computed here from the nominal model and the truth the touches came from."""

from __future__ import annotations

import numpy as np
import pytest

from station.kinematics import load_model
from station.panel.residuals import live_residuals
from station.robot import Identity, JointSnapshot
from station.solver import solve
from station.solver.simulate import touch_observations
from station.tui.session import session_header, technician_session

Q0 = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


def test_nominal_then_calibrated_residuals(tmp_path):
    nominal = load_model("ur5e").with_params({"tcp.z": 0.1})
    truth = nominal.with_params({"offset.j2": 0.003, "offset.j3": -0.002})
    obs = touch_observations(truth, {"A": truth.position(Q0)}, 20, np.random.default_rng(1), noise=10e-6,
                             centre=Q0, spread=0.4)
    ident = Identity(vendor="UR", model="ur5e", serial="S-1", serial_source="robot")
    header = session_header(identity=ident, model_name="ur5e", serial="S-1", identify="offsets",
                            reference="unknown", url="ur://x")
    s = technician_session(None, header, folder=tmp_path / "jog", model=nominal)
    for i, q in enumerate(obs.q):
        s.add_sample(JointSnapshot(q, tuple(q), "tick", float(i)), "A", pose=i, status={"enabled": True})
    rows, which = live_residuals(s)
    assert which == "nominal" and [r["n"] for r in rows] == list(range(1, 21))
    tips = nominal.position(obs.q)
    expect = np.linalg.norm(tips - tips.mean(axis=0), axis=1) * 1e3  # spread about the touches' centroid
    assert [r["mm"] for r in rows] == pytest.approx(expect, abs=1e-5)
    assert expect.max() > 0.3  # the hidden offsets spread the nominal tips by tenths of a millimetre
    s.result = solve(nominal, obs, identify="offsets")
    rows, which = live_residuals(s)
    assert which == "calibrated"
    assert max(r["mm"] for r in rows) < 0.1 and [r["mm_nominal"] for r in rows] == pytest.approx(expect, abs=1e-5)
