"""``station.solver.holdout``: held-out touches scored with the calibrated model fixed, against the simulated
truth: the calibrated error is at the touch noise, the nominal one is what the hidden errors make, a moved
fixture under its old label is named, a new label is scored by consistency."""

from __future__ import annotations

import numpy as np

from station.kinematics import load_model
from station.solver import solve
from station.solver.holdout import MOVED_M
from station.solver.simulate import touch_observations

Q0 = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])
HIDDEN = {"offset.j2": 0.004, "offset.j3": -0.003, "offset.j4": 0.005, "offset.j5": -0.002}
NOISE = 20e-6


def test_holdout_scores_against_the_truth():
    nominal = load_model("ur5e").with_params({"tcp.z": 0.1})
    truth = nominal.with_params(HIDDEN)
    a = truth.position(Q0)
    rng = np.random.default_rng(11)
    fit = touch_observations(truth, {"A": a}, 40, rng, noise=NOISE, centre=Q0, spread=0.4)
    moved = a + np.array([0.004, 0, 0])
    ho = touch_observations(truth, {"A": a, "B": a + [0.05, 0.05, 0.0]}, 8, rng, noise=NOISE, centre=Q0,
                            spread=0.4)
    res = solve(nominal, fit, identify="offsets", holdout=ho)
    h = res.holdout
    assert h["n_samples"] == 16
    assert h["rms_m"] < 3 * np.sqrt(3) * NOISE  # the calibrated model: touch noise
    # the nominal model's error on the same touches, computed here from the truth
    d_nom = np.linalg.norm(nominal.position(ho.q[:8]) - nominal.position(ho.q[:8]).mean(axis=0), axis=1)
    assert h["rms_nominal_m"] > 10 * h["rms_m"] and np.sqrt(np.mean(d_nom ** 2)) > 10 * h["rms_m"]
    assert h["points"]["A"]["reference"] == "fit" and h["points"]["B"]["reference"] == "new"
    assert h["points"]["A"]["moved_m"] < 1e-4 and not h["notes"]
    # the same fixture moved by 4 mm but touched under its old label: named
    ho2 = touch_observations(truth, {"A": moved}, 8, rng, noise=NOISE, centre=Q0, spread=0.4)
    h2 = solve(nominal, fit, identify="offsets", holdout=ho2).holdout
    assert abs(h2["points"]["A"]["moved_m"] - 0.004) < 1e-4 and MOVED_M < 0.004
    assert len(h2["notes"]) == 1 and "holdout point A is 4.0 mm from the fit's A" in h2["notes"][0]
