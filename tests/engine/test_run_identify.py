"""``station run --identify`` and what a FAIL says next: a procedure that solves nothing refuses the option before
the robot is opened; after a FAIL whose fit is above its limit, the group that explains the residual on the same
samples is named with the command to run (ground truth: a world whose only hidden error is the tool)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from clirunner import station_proc
from station.mocks.world import World

from station.cli.nextstep import suggest
from station.engine.cell import RefPoint
from station.engine.plan import generate_plan
from station.solver import Observations, solve


def station(*args):
    """``station ARGS`` as a child process: exit code, stdout, stderr lines."""
    r = station_proc(*args)
    return r.code, r.out, r.err_lines


@pytest.mark.parametrize("procedure", ["verify", "correction_map"])
def test_identify_is_refused_by_a_procedure_that_solves_nothing(tmp_path, monkeypatch, procedure):
    monkeypatch.setenv("STATION_HOME", str(tmp_path))  # no robot at that address: refused before it is opened
    rc, _, err = station("run", procedure, "--robot", "ur://127.0.0.250?model=ur5e", "--serial", "S1",
                         "--identify", "offsets,tcp", "-q")
    assert rc == 2 and len(err) == 1, err
    assert "--identify" in err[0] and "solves nothing" in err[0] and "zero_offsets" in err[0], err


def test_identify_must_name_groups(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path))
    rc, _, err = station("run", "zero_offsets", "--robot", "ur://127.0.0.250?model=ur5e", "--serial", "S1",
                         "--identify", "offsets,,tcp", "-q")
    assert rc == 2 and len(err) == 1 and "--identify" in err[0], err


def _fail_record(world: World, rng) -> SimpleNamespace:
    """A zero_offsets session on ``world``'s true arm: touches of socket A (the true tip exactly on it, 5 um of
    encoder noise), solved for the offsets alone on the nominal model, judged against the limits' fit_rms."""
    a = world.points["A"]
    ref = RefPoint("A", "socket", a.position, a.approach, a.radius)
    plan = generate_plan(world.truth, [ref], world.encoder_q(), identify="offsets,tcp", n_fit=24, n_holdout=4,
                         cone_deg=50.0, seed=3)
    q = np.array([p.q for p in plan.poses]) + rng.normal(0, 5e-6, (len(plan.poses), world.nominal.n_joints))
    sets = [p.set for p in plan.poses]
    fit = np.array([s == "fit" for s in sets])
    labels = np.array(["A"] * len(q), dtype=object)
    res = solve(world.nominal, Observations(q[fit], labels[fit], None), identify="offsets",
                holdout=Observations(q[~fit], labels[~fit], None))
    rms = res.residuals["rms_after_m"] * 1e3
    record = {"procedure": "zero_offsets", "result": res.to_dict(),
              "samples": [{"q": list(x), "point": "A", "set": s} for x, s in zip(q, sets, strict=True)],
              "verdict": {"passed": False, "measurements": [
                  {"name": "fit_rms", "value": rms, "unit": "mm", "high": 0.1, "passed": rms <= 0.1},
                  {"name": "holdout_rms", "value": None, "unit": "mm", "high": 0.15, "passed": True}]}}
    return SimpleNamespace(record=record, model=world.nominal)


def test_a_fail_names_the_group_that_explains_the_residual_and_the_command():
    rng = np.random.default_rng(4)
    world = World.default("arm6", seed=2, errors={"explicit": {"tcp.x": 0.6e-3, "tcp.y": -0.4e-3, "tcp.z": 0.5e-3}})
    out = _fail_record(world, rng)
    assert not out.record["verdict"]["measurements"][0]["passed"]  # the tool error is far above the limit
    lines = suggest(out, robot="canopen+socketcand://127.0.0.1:29536?channel=can0&nodes=1,2,3,4,5,6&model=arm6",
                    serial="A6-1", cell="cell.yaml", identify=None)
    assert len(lines) == 3, lines
    assert "above its limit 0.1 mm" in lines[0] and "--identify offsets does not model" in lines[0]
    assert "--identify offsets,tcp fits" in lines[1]
    assert lines[2] == ("station: next: station run zero_offsets --robot 'canopen+socketcand://127.0.0.1:29536?"
                        "channel=can0&nodes=1,2,3,4,5,6&model=arm6' --serial A6-1 --cell cell.yaml --identify "
                        "offsets,tcp")
    # a PASS, or a FAIL for another reason, says nothing more
    out.record["verdict"]["measurements"][0]["passed"] = True
    assert suggest(out, robot="x", serial="S", cell=None, identify=None) == []
