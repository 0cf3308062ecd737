"""End to end ``dh_full``: a 6R arm (arm6) on emulated CiA 402 drives (python-can virtual channel, real canopen
library), hidden zero and link-geometry errors, three sockets at unknown positions.

What can be checked against the hidden truth: with unknown sockets a rotation about joint 1 and the overall
scale are not observable, link lengths along parallel axes combine, and a few directions are too weak for the
noise (docs/solver.md). The solver names those and holds them at nominal, so the identified parameters take
up whatever part of the dropped parameters' true errors they can mimic. The test therefore compares each
identified value with the TRUTH PROJECTED onto what the solver declared identifiable: the identified
parameters and points that, with every dropped parameter at its nominal value, best reproduce the true
robot's tip at the recorded poses, each model parameter paying its prior as the MAP estimate does
(linearised at the truth: the dropped errors are 1e-4 of the geometry, the
second-order rest is 1e-7 m). That projection uses only the world's truth and the kinematic model; the
agreement must hold within 4 sigma of the solver's reported uncertainty."""

from __future__ import annotations

import math
import uuid

import numpy as np
import pytest
import yaml
from station.mocks.canopen.emulator import CanopenEmulator
from station.mocks.world import World

from station.api import run as start

SEATING = 10e-6  # m per axis: where a compliant ball settles in a socket (the world's seating noise)
SOCKETS = [("A", [0.35, 0.0, 0.75]), ("B", [0.30, 0.35, 0.60]), ("C", [0.45, -0.30, 0.55])]
ERRORS = {"random": {"offsets": {"angle": math.radians(0.1)},
                     "dh": {"length": 0.2e-3, "angle": math.radians(0.02)}}}


def run_dh_full(tmp_path, edit_cell=None, serial: str = "DH-5", options: dict | None = None, report: bool = True):
    """dh_full on the arm6 world with three unknown sockets; ``edit_cell(doc, world)`` may add to the cell file,
    ``options`` go to the procedure (e.g. ``n_fit``), ``report=False`` skips the HTML report."""
    world = World.default(model="arm6", seed=5, time_mode="instant", errors=ERRORS, noise={"seating": SEATING},
                          cell={"points": [{"label": k, "kind": "socket", "position": p, "approach": [0, 0, 1]}
                                           for k, p in SOCKETS]})
    doc = world.station_cell()
    if edit_cell is not None:
        edit_cell(doc, world)
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump(doc))
    channel = f"dh{uuid.uuid4().hex[:8]}"
    emu = CanopenEmulator(world, "virtual", channel).start()
    try:
        out = start("dh_full", f"canopen+virtual://{channel}?nodes=1-6&model=arm6&serial={serial}", serial,
                    cell=cell, db=f"sqlite:///{tmp_path / 'records.db'}", options=options, report=report)
    finally:
        emu.stop()
    return world, out


@pytest.fixture
def run(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    return run_dh_full(tmp_path)


def _projected_truth(world: World, record: dict) -> dict[str, float]:
    """Identified parameters and points as the true robot makes them, with the dropped parameters at nominal."""
    params = record["result"]["parameters"]
    fit = [s for s in record["samples"] if s["set"] == "fit"]
    q = np.array([s["q"] for s in fit])
    model = world.truth
    ident = [n for n, p in params.items() if p["identifiable"] and not n.startswith("point.")]
    dropped = [n for n, p in params.items() if not p["identifiable"] and not n.startswith("point.")]
    labels = sorted({n.split(".")[1] for n, p in params.items() if n.startswith("point.") and p["identifiable"]})
    assert all(params[f"point.{k}.{a}"]["identifiable"] for k in labels for a in "xyz")
    # tip rows: d tip / d parameter (truth model at the recorded encoder positions), and -I for the sample's point
    J_id = model.jacobian_params(q, names=ident)[:, :3].reshape(-1, len(ident))
    J_pt = np.zeros((3 * len(fit), 3 * len(labels)))
    for i, s in enumerate(fit):
        k = labels.index(s["point"])
        J_pt[3 * i:3 * i + 3, 3 * k:3 * k + 3] = -np.eye(3)
    J_dr = model.jacobian_params(q, names=dropped)[:, :3].reshape(-1, len(dropped))
    move = np.array([world.nominal.param(n) - model.param(n) for n in dropped])  # truth -> nominal
    J = np.hstack([J_id, J_pt])
    # the estimate is maximum a posteriori: each identified model parameter also pays ((value - nominal) / prior)^2
    # in units of the noise (its prior as the result states it; none for a freed prior and for the points), so
    # its expectation is the regularised projection (the prior's pull matters where the data are weak)
    tau = np.array([params[n]["prior_std"] if params[n]["prior_share"] not in (None, 0.0) else np.inf
                    for n in ident] + [np.inf] * (3 * len(labels)))
    reg = np.diag(SEATING / tau)
    pull = np.array([model.param(n) - world.nominal.param(n) for n in ident] + [0.0] * (3 * len(labels)))
    A = np.vstack([J, reg])
    b = np.concatenate([J_dr @ move, reg @ pull])
    delta = -np.linalg.lstsq(A, b, rcond=None)[0]
    out = {n: model.param(n) + d for n, d in zip(ident, delta[:len(ident)], strict=True)}
    for k, label in enumerate(labels):
        for a, axis in enumerate("xyz"):
            out[f"point.{label}.{axis}"] = world.points[label].position[a] + delta[len(ident) + 3 * k + a]
    return out


def test_dh_full_recovers_identifiable_geometry(run):
    world, out = run
    assert out.status == "completed", out.error
    assert out.passed and out.exit_code == 0 and out.stored
    assert out.report is not None and out.report.is_file()  # the only test that renders a dh_full report
    res = out.record["result"]
    params = res["parameters"]

    # the world hides no tool error: the tool's unknowns explain nothing beyond chance, so dh_full keeps it nominal
    assert res["settings"]["identify"] == "offsets,dh"

    # what the geometry says cannot be seen is named, never guessed
    reasons = {n: p["reason"] for n, p in params.items() if not p["identifiable"]}
    assert "offset.j1" in reasons  # the unknown point moves with joint 1
    # the tip sits on the j6 axis but for the fitted 0.1-mm-class link errors: joint 6's zero is seen only through
    # that lever, so it is left at nominal or estimated with the prior carrying a real share of it
    assert "offset.j6" in reasons or params["offset.j6"]["prior_share"] > 0.05
    assert any("scale" in (r or "") for r in reasons.values())  # no known length among unknown sockets
    assert all(params[n]["value"] == params[n]["nominal"] for n in reasons if not n.startswith("point."))

    # residuals at the noise level: per-axis sigma of the fit is the seating noise, held-out touches as well
    n_fit, rank = res["n_residuals"], res["rank"]
    assert abs(res["sigma_m"] / SEATING - 1) < 4 / math.sqrt(2 * (n_fit - rank)) + 0.05, res["sigma_m"]
    hold = res["holdout"]
    assert hold["n_samples"] >= 6
    assert hold["rms_m"] < 1.5 * math.sqrt(3) * SEATING, hold  # chi2(18)/18 beyond 2.25: p < 0.3 %
    assert hold["rms_nominal_m"] > 20 * hold["rms_m"]  # the hidden errors were real

    # identified values against the projected truth, within 4 sigma; the hidden errors are well above sigma
    expected = _projected_truth(world, out.record)
    ratios = {}
    for name, want in expected.items():
        p = params[name]
        ratios[name] = (p["value"] - want) / p["std"]
    bad = {n: round(r, 1) for n, r in ratios.items() if abs(r) > 4}
    assert not bad, bad
    moved = [n for n in expected if not n.startswith("point.")
             and abs(world.truth.param(n) - world.nominal.param(n)) > 4 * params[n]["std"]]
    # the check has teeth: recovering nominal values would fail it (σ includes the consider covariance of the
    # parameters kept at nominal, so a few sub-4σ errors do not count)
    assert len(moved) >= 5, moved
