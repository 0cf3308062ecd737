"""Collision-aware pose plans: the UR5e demo plan (issue 15: 14 of 28 poses put the elbow up to 260 mm below the
mounting plane) must keep every link capsule above the plane with its clearance.

Ground truth for "below the plane" is computed here, independently of station.kinematics.collision: the elbow
is the origin of the frame before the elbow joint's rotation (on the elbow axis), read from the kinematic
chain's own frames; link capsules are checked against the plane from the DH frame origins by hand."""

import json
from pathlib import Path

import numpy as np
import pytest

from station.engine.cell import load_cell
from station.engine.plan import generate_plan
from station.kinematics import load_model
from station.kinematics.chain import forward
from station.kinematics.collision import Checker

UR_START = [0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, -np.pi / 2, 0.0]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The station side of `station demo` (UR5e): the cell file it writes and the model with the cell's tool."""
    from station.cli.run_cmd import write_demo_files

    _, cell_path, _ = write_demo_files("ur", tmp_path_factory.mktemp("demo"), 5, "instant")
    cell = load_cell(cell_path)
    m = load_model("ur5e")
    if cell.tool:
        m = m.with_params({f"tcp.{k}": v for k, v in cell.tool.items()})
    return m, cell


def _joint_points(model, q):
    """(N, n, 3): a point on each joint axis (the frame before the joint's rotation), straight from the chain."""
    _, prefix = forward(model.chain, np.atleast_2d(q), model.params, keep_prefix=True)
    ks = [int(np.flatnonzero(model.chain.joint == i)[0]) for i in range(model.n_joints)]
    return prefix[:, ks][:, :, :3, 3]


def _demo_plan(m, cell, **kw):
    # what zero_offsets asks for in the demo (procedures/zero_offsets.py DEFAULTS, seed 0)
    return generate_plan(m, cell.of_kind("socket"), UR_START, identify="offsets", n_holdout=4, cone_deg=50.0,
                         seed=0, **kw)


def test_the_checker_finds_every_elbow_below_the_base_in_the_plan_before_keepouts(demo):
    """The demo plan of the planner before this change (recorded: tests/data), as the issue saw it."""
    m, _ = demo
    rec = json.loads((Path(__file__).parent / "data" / "ur5e_demo_plan_before_keepout.json").read_text())
    q = np.array(rec["q"])
    elbow_z = _joint_points(m, q)[:, 2, 2]  # joint 3 (elbow) axis point, height above the base plane
    below = elbow_z < 0
    assert len(q) == 28 and below.sum() == 14 and -0.27 < elbow_z.min() < -0.25
    hits = Checker(m, None).hits(q)
    flagged = np.array([h is not None for h in hits])
    assert flagged[below].all()
    for h in (h for h, b in zip(hits, below, strict=True) if b):
        assert h.obstacle == "mounting plane" and h.link == 2 and h.distance < -0.2
        assert "link 2 (shoulder-elbow)" in h.describe() and "'mounting plane'" in h.describe()
    # the approach poses as well: they differ from the touch poses by 30 mm at the tool
    assert sum(h is not None for h in Checker(m, None).hits(np.array(rec["approach_q"]))) >= 14


def test_demo_plan_keeps_every_link_above_the_mounting_plane(demo):
    m, cell = demo
    plan = _demo_plan(m, cell)
    radii = np.array(m.source["collision"]["link_radii"])
    for which in ("q", "approach_q"):
        q = np.array([getattr(p, which) for p in plan.poses])
        P = _joint_points(m, q)  # shoulder, elbow, wrist points: capsule ends of the links that can go down
        z = P[:, 1:, 2] - np.maximum(radii[1:], radii[:-1])[None, :]
        assert z.min() >= 0.01 - 1e-9, f"{which}: a joint housing reaches {z.min() * 1e3:.0f} mm"
        assert all(h is None for h in Checker(m, None).hits(q))
