"""``station.solver.diagnose``: a unit slip that stays inside the joint limits is found and named (a column in
rad/1000, a row in degrees under a radian header), and noise-free data are not given a ± of 0."""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.kinematics import load_model
from station.solver import solve
from station.solver.diagnose import noise_free, unit_slip
from station.solver.simulate import touch_observations

Q0 = np.array([0.3, -1.2, 1.5, -1.9, -1.57, 0.4])


def _obs(noise=20e-6, seed=2):
    nominal = load_model("ur5e").with_params({"tcp.z": 0.1})
    truth = nominal.with_params({"offset.j2": 0.002, "offset.j3": -0.001})
    obs = touch_observations(truth, {"A": truth.position(Q0)}, 30, np.random.default_rng(seed), noise=noise,
                             centre=Q0, spread=0.4)
    return nominal, obs


def refit_of(model):
    return lambda o: solve(model, o, identify="offsets")


def test_a_column_in_thousandths_is_named():
    model, obs = _obs()
    bad = obs.q.copy()
    bad[:, 0] /= 1000.0  # q1 written in rad/1000: still inside the limits
    import dataclasses

    obs_bad = dataclasses.replace(obs, q=bad)
    res = solve(model, obs_bad, identify="offsets")
    slip = unit_slip(model, obs_bad, res, refit_of(model), None, "s.csv")
    assert slip is not None and slip.where == "s.csv: column q1" and slip.factor == 1000.0
    assert slip.rms_m < 1e-4 < slip.rms0_m and slip.message().endswith("fix the file's units")
    good = solve(model, obs, identify="offsets")
    assert unit_slip(model, obs, good, refit_of(model)) is None  # a good fit has nothing to explain


def test_one_row_of_radians_under_a_degree_header_is_named_with_its_line():
    """Row 7 holds radians but the header says degrees: read as degrees, its joints are 57 times too small
    (inside every limit); the row is named with its file line."""
    import dataclasses

    model, obs = _obs(seed=3)
    bad = obs.q.copy()
    bad[6] = np.radians(bad[6])
    obs_bad = dataclasses.replace(obs, q=bad)
    res = solve(model, obs_bad, identify="offsets")
    slip = unit_slip(model, obs_bad, res, refit_of(model), None, "s.csv", list(range(2, 2 + len(bad))))
    assert slip is not None and slip.where == "s.csv:8: row 7", slip
    assert slip.factor == pytest.approx(180 / math.pi) and "radians under a degree header" in slip.unit


def test_noise_free_data_get_no_plus_minus():
    model, obs = _obs(noise=0.0)
    res = solve(model, obs, identify="offsets")
    line = noise_free(res, None)
    assert line is not None and noise_free(res, 20e-6) is None  # a declared noise gives the ± its scale
    noisy = solve(model, _obs()[1], identify="offsets")
    assert noise_free(noisy, None) is None
