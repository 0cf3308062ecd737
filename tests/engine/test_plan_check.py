"""Plan-time check: before the robot moves, the station predicts from the planned poses what the
solve can identify and how well, and refuses a plan that cannot meet the procedure's limits in one line (exit 2)
instead of 24 poses of motion to find out. Emulated arm6 on CANopen (real canopen library, virtual bus)."""

import numpy as np
import pytest
import yaml
from station.mocks.launch import launch

from station.api import run
from station.cli.run_cmd import write_demo_files
from station.engine import read_journal
from station.kinematics import load_model
from station.solver import predict


def _limits(tmp_path, **zero_offsets) -> str:
    base = {"samples": {"low": 12, "unit": "count"}, "fit_rms": {"high": 0.10, "unit": "mm"}}
    doc = {"format": "station-limits/1", "version": "test-plan-check",
           "models": {"arm6": {"zero_offsets": {**base, **zero_offsets}}}}
    path = tmp_path / "limits.yaml"
    path.write_text(yaml.safe_dump(doc))
    return str(path)


@pytest.fixture
def arm6(tmp_path, monkeypatch):
    monkeypatch.setenv("STATION_HOME", str(tmp_path / "home"))
    world_path, cell_path, serial = write_demo_files("canopen", tmp_path, seed=23, time_mode="instant")
    with launch("canopen", world_path, serial=serial) as emu:
        yield emu, cell_path, serial


def _refused(tmp_path, arm6, limits):
    emu, cell_path, serial = arm6
    q_before = emu.world.snapshot().q.copy()
    out = run("zero_offsets", emu.url, serial, cell=cell_path, limits=limits, db=f"sqlite:///{tmp_path / 'r.db'}")
    assert out.status == "error" and out.exit_code == 2 and out.verdict == "ERROR"
    msg = str(out.error)
    assert "\n" not in msg and msg.startswith("plan: the planned poses cannot meet the limits, nothing moved")
    _, events = read_journal(out.folder / "journal.jsonl")
    assert not [e for e in events if e["type"] == "sample"]  # no pose was visited
    assert np.allclose(emu.world.snapshot().q, q_before, atol=1e-9)  # the arm never moved
    return msg


def test_a_plan_that_cannot_see_enough_offsets_is_refused_before_motion(tmp_path, arm6):
    # one socket, position unknown: the base axis (j1) and the tool axis (j6) cannot show their zeros
    msg = _refused(tmp_path, arm6, _limits(tmp_path, identified={"low": 6, "unit": "count"}))
    assert "can identify 4 parameter(s), the limits need 6" in msg
    assert "offset.j1" in msg and "offset.j6" in msg


def test_a_plan_too_weak_for_the_std_limit_is_refused_before_motion(tmp_path, arm6):
    msg = _refused(tmp_path, arm6, _limits(tmp_path, offset_std_max={"high": 1e-5, "unit": "deg"}))
    assert "offset_std_max would be at least" in msg and "limit 1e-05 deg" in msg


def test_the_prediction_matches_the_posterior_of_the_real_solve(tmp_path, arm6):
    """Independent check of what the refusal relies on: the std predicted from the planned poses at the noise
    the world draws equals, to within the scatter of a fitted noise, the std the solve then reports."""
    emu, cell_path, serial = arm6
    out = run("zero_offsets", emu.url, serial, cell=cell_path, db=f"sqlite:///{tmp_path / 'r.db'}")
    assert out.status == "completed", out.error
    _, events = read_journal(out.folder / "journal.jsonl")
    plan = next(e["plan"] for e in events if e["type"] == "plan")
    fit = [p for p in plan["poses"] if p["set"] == "fit"]
    res = out.record["result"]
    sigma = res["sigma_m"]  # the fitted touch noise of this run
    pred = predict(load_model("arm6"), np.array([p["q"] for p in fit]), [p["point"] for p in fit], "offsets",
                   "unknown", noise=sigma)
    got = {n: p for n, p in res["parameters"].items() if n.startswith("offset.") and p["identifiable"]}
    assert set(got) == {n for n, p in pred.parameters.items() if p.identifiable}
    for n, p in got.items():
        # planned vs. recorded joint values differ by the seating error only: a few percent on the std
        assert p["std"] == pytest.approx(pred.parameters[n].std, rel=0.15), n
