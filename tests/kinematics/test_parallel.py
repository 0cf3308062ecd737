"""Parallel models: round trips against independent leg-length computations, analytic Jacobians against finite
differences, model files in both unit systems, one-line errors, and the simulated world holding a parallel truth."""


import numpy as np
import pytest
import yaml
from clirunner import station_main, station_proc

from station.kinematics import ModelFileError, dump_model, load_model, model_from_dict, se3
from station.kinematics.parallel import ParallelKinematicsError, planar_struts

RNG = np.random.default_rng(11)


def _legs(model, T, params=None):
    """Leg lengths of tool poses ``T``, computed here from the parameter names (independent of the model code)."""
    p = model.param_dict() if params is None else dict(zip(model.param_names, params, strict=True))
    if model.type == "planar-struts":
        c = np.array([[p[f"pivot.{k}.x"], p[f"pivot.{k}.y"]] for k in (1, 2)])
        off = np.array([p["strut.1.offset"], p["strut.2.offset"]])
        return np.linalg.norm(T[:, None, :2, 3] - c[None], axis=2) - off
    tool = se3.pose_to_matrix(np.array([p[f"tcp.{k}"] for k in ("x", "y", "z", "rx", "ry", "rz")]), "rpy")
    P = T @ np.linalg.inv(tool)
    out = np.zeros((len(T), 6))
    for k in range(6):
        b = np.array([p[f"anchor.base.{k + 1}.{a}"] for a in "xyz"])
        a_ = np.array([p[f"anchor.platform.{k + 1}.{a}"] for a in "xyz"])
        out[:, k] = np.linalg.norm(P[:, :3, 3] + P[:, :3, :3] @ a_ - b, axis=1) - p[f"leg.{k + 1}.offset"]
    return out


def _random_q(m, n):
    return m.lower + (m.upper - m.lower) * RNG.random((n, m.n_joints))


def _perturbed(m, scale=2e-4):
    p = m.params + scale * RNG.standard_normal(len(m.params))
    if m.type == "gough-stewart":
        p[m.index("tcp.x"):] += np.array([0.01, -0.02, 0.05, 0.1, -0.05, 0.2])  # a real tool frame
    return p


@pytest.mark.parametrize("name", ["hexapod", "struts2"])
def test_fk_puts_every_leg_at_its_length(name):
    m = load_model(name)
    p = _perturbed(m)
    q = _random_q(m, 200)
    T = m.fk(q, p)
    np.testing.assert_allclose(_legs(m, T, p), q, atol=1e-10)
    np.testing.assert_allclose(m.ik_closed(T, p)[0], q, atol=1e-10)  # IK o FK


def test_hexapod_ik_then_fk_returns_the_pose():
    m = load_model("hexapod")
    home = se3.pose_to_matrix(m.home, "rpy")
    d = np.column_stack([RNG.uniform(-0.02, 0.02, (100, 3)), RNG.uniform(-0.08, 0.08, (100, 3))])
    T = np.array([se3.pose_to_matrix(np.r_[home[:3, 3] + di[:3], 0, 0, 0], "rpy") @
                  se3.pose_to_matrix(np.r_[0, 0, 0, di[3:]], "rotvec") for di in d])
    q, ok, _ = m.ik_closed(T, check_limits=False)  # FK does not care about limits
    assert ok.all() and np.ptp(q) > 0.05
    np.testing.assert_allclose(m.fk(q), T, atol=1e-10)


def _pose_vec(T, T0):
    return np.concatenate([T[:, :3, 3], se3.orientation_error(T[:, :3, :3], T0[:, :3, :3])], axis=1)


def _fd(fun, x, h=1e-7):
    cols = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("name", ["hexapod", "struts2"])
def test_jacobians_match_finite_differences(name):
    m = load_model(name)
    p = _perturbed(m)
    q = m.lower + (m.upper - m.lower) * (0.2 + 0.6 * RNG.random((4, m.n_joints)))
    T0, Jq, Jp = m.jacobians(q, p)
    num_p = _fd(lambda x: _pose_vec(m.fk(q, x, guess=T0), T0), p)
    np.testing.assert_allclose(Jp, num_p, atol=2e-6)
    num_q = np.stack([_fd(lambda x, i=i: _pose_vec(m.fk(x[None], p, guess=T0[i:i + 1]), T0[i:i + 1])[0], q[i])
                      for i in range(len(q))])
    np.testing.assert_allclose(Jq, num_q, atol=2e-6)
    assert np.abs(Jq).max() > 0.1 and np.abs(Jp).max() > 0.1  # not trivially zero


def test_planar_forward_kinematics_errors_are_one_line():
    m = planar_struts("p", [[0, 0], [0.4, 0]], [[0.05, 0.6], [0.05, 0.6]])
    with pytest.raises(ParallelKinematicsError, match="cannot meet") as e:
        m.fk([0.1, 0.2])  # 0.1 + 0.2 < 0.4
    assert "\n" not in str(e.value)
    with pytest.raises(ParallelKinematicsError, match="singular"):
        m.fk([0.1, 0.3])  # both struts on the pivot line
    res = m.fk_solve(np.array([[0.1, 0.2], [0.3, 0.3], [0.1, 0.3]]))
    assert res.ok.tolist() == [False, True, False]
    # the branch: IK of a point below the pivot line is another assembly mode
    q, ok, why = m.ik_closed(np.array([[0.2, -0.1]]))
    assert not ok[0] and "other side of the pivot line" in why[0]


def test_hexapod_outside_the_workspace_is_one_line():
    m = load_model("hexapod")
    with pytest.raises(ParallelKinematicsError, match="cannot be assembled") as e:
        m.fk([0.1, 0.1, 0.1, 0.9, 0.9, 0.9])
    assert "\n" not in str(e.value) and "0.9" in str(e.value)


def test_units_and_export_round_trip():
    m = load_model("hexapod")
    doc_mm = yaml.safe_load(dump_model(m, "mm", "deg"))
    doc_m = yaml.safe_load(dump_model(m, "m", "rad"))
    a, b = model_from_dict(doc_mm), model_from_dict(doc_m)
    np.testing.assert_allclose(a.params, m.params, atol=1e-12)
    np.testing.assert_allclose(b.params, m.params, atol=1e-12)
    np.testing.assert_allclose(a.lower, m.lower)
    assert a.joints[0].encoder.counts_per_unit == m.joints[0].encoder.counts_per_unit
    # a calibrated model exports its calibrated values
    c = m.with_params({"anchor.base.3.y": m.param("anchor.base.3.y") + 1e-4, "leg.2.offset": 3e-4, "tcp.z": 0.05})
    back = model_from_dict(yaml.safe_load(dump_model(c, "mm", "deg")))
    np.testing.assert_allclose(back.params, c.params, atol=1e-12)


ISSUE_HEXAPOD = """
format: station-model/1
name: my-hexapod
kind: parallel
units: {length: mm, angle: deg}
parallel:
  type: gough-stewart
  base_anchors: [[289.778, 77.646, 0], [-77.646, 289.778, 0], [-212.132, 212.132, 0],
                 [-212.132, -212.132, 0], [-77.646, -289.778, 0], [289.778, -77.646, 0]]
  platform_anchors: [[141.421, 141.421, 0], [51.764, 193.185, 0], [-193.185, 51.764, 0],
                     [-193.185, -51.764, 0], [51.764, -193.185, 0], [141.421, -141.421, 0]]
  legs: {limits: [450, 600]}
  home: {x: 0, y: 0, z: 500, rx: 0, ry: 0, rz: 0}
tool: {x: 0, y: 0, z: 100, rx: 0, ry: 0, rz: 0}
"""

ISSUE_STRUTS = """
format: station-model/1
name: seed-struts
kind: parallel
units: {length: m, angle: rad}
parallel:
  type: planar-struts
  pivots: [[0, 0], [0.4, 0]]
  struts: {limits: [[0.3, 0.5], [0.3, 0.5]]}
  branch: -1
"""


def test_issue_file_forms_load(tmp_path):
    h = tmp_path / "h.yaml"
    h.write_text(ISSUE_HEXAPOD)
    m = load_model(h)
    assert m.name == "my-hexapod" and m.n_joints == 6
    assert m.param("anchor.platform.2.y") == pytest.approx(0.193185)
    np.testing.assert_allclose(m.fk(m.home_q)[:3, 3], [0, 0, 0.6], atol=1e-10)  # tool 100 mm above the platform
    s = tmp_path / "s.yaml"
    s.write_text(ISSUE_STRUTS)
    m = load_model(s)
    assert m.fk([0.4, 0.4])[1, 3] < 0  # branch -1: right of pivot1 -> pivot2


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["parallel"].update(base_anchors=d["parallel"]["base_anchors"][:5]), "base_anchors: expected 6"),
    (lambda d: d["parallel"].update(type="delta"), "parallel.type"),
    (lambda d: d["parallel"]["legs"].update(limits=[600, 450]), "legs.limits"),
    (lambda d: d["parallel"]["home"].update(z=900), "parallel.home: leg 1"),
    (lambda d: d["parallel"]["platform_anchors"][2].append(1), "platform_anchors[2]"),
    (lambda d: d.update(kind="hybrid"), "kind must be serial or parallel"),
    (lambda d: d["parallel"].update(pivots=[[0, 0], [1, 0]]), "unknown keys ['pivots']"),
    # found by the reader fuzz in CI: a list as the encoder direction was a TypeError traceback
    (lambda d: d["parallel"]["legs"].update(encoder={"counts_per_m": 1e6, "direction": []}), "encoder.direction"),
    (lambda d: d["parallel"]["legs"].update(encoder={"counts_per_m": 1e6, "gear": 0}), "must be > 0"),
    (lambda d: d["parallel"]["legs"].update(encoder={"counts_per_m": 1e6, "dir": -1}), "unknown keys ['dir']"),
])
def test_bad_parallel_files_fail_in_one_line(tmp_path, edit, message):
    doc = yaml.safe_load(ISSUE_HEXAPOD)
    edit(doc)
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(ModelFileError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_model(f)
    r = station_main("model", "show", f)
    rc, lines = r.code, r.err_lines
    assert rc == 2
    assert len(lines) == 1 and lines[0].startswith("station: error:") and str(f) in lines[0], lines


@pytest.mark.slow
def test_installed_command_shows_parallel_models():
    for name in ("hexapod", "struts2"):
        p = station_proc("model", "show", name)
        assert p.code == 0, p.err
        assert "kind: parallel" in p.out and "# actuators at home" in p.out
    rc, out, _ = station_main("model", "list")
    assert rc == 0 and "hexapod" in out and "struts2" in out


def test_parametric_solve_refuses_a_parallel_model_in_one_line(tmp_path):
    f = tmp_path / "s.csv"
    f.write_text("q1,q2,q3,q4,q5,q6,x,y,z\n" + "0.52,0.52,0.52,0.52,0.52,0.52,0,0,0.5\n" * 30)
    r = station_main("solve", "--model", "hexapod", "--samples", f)
    rc, lines = r.code, r.err_lines
    assert rc == 2 and len(lines) == 1 and "station map" in lines[0], lines


def test_world_holds_a_parallel_truth():
    from station.mocks.world import World

    w = World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"},
                         "robot": {"model": "hexapod"},
                         "errors": {"explicit": {"anchor.base.2.x": 0.5, "anchor.platform.3.z": -0.4,
                                                 "leg.1.offset": 0.3}}})
    assert w.errors() == pytest.approx({"anchor.base.2.x": 5e-4, "anchor.platform.3.z": -4e-4, "leg.1.offset": 3e-4})
    q = w.nominal.home_q + np.array([0.01, -0.02, 0.0, 0.015, 0.0, -0.01])
    w.command_q(q)
    T = w.tip_pose_true()
    legs = _legs(w.truth, T[None])[0]
    np.testing.assert_allclose(legs, q, atol=1e-10)  # the true platform sits on the true legs
    assert np.linalg.norm(T[:3, 3] - w.nominal.fk(q)[:3, 3]) > 1e-4  # and the nominal model does not know it
    s = World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"},
                         "robot": {"model": "struts2"},
                         "errors": {"explicit": {"pivot.2.y": 0.2, "strut.2.offset": -0.1}}})
    s.command_q([0.4, 0.45])
    tip = s.tip_true()
    assert np.linalg.norm(tip[:2] - np.array([0.4, 2e-4])) == pytest.approx(0.45 - 1e-4, abs=1e-12)
    with pytest.raises(ValueError, match="no such parameter"):
        World.from_dict({"format": "station-world/1", "units": {"length": "mm", "angle": "deg"},
                         "robot": {"model": "hexapod"}, "errors": {"explicit": {"leg.7.offset": 1}}})


@pytest.mark.parametrize("name", ["hexapod", "struts2"])
def test_world_example_and_show_for_parallel_robots(tmp_path, name):
    rc, text, err = station_main("mock", "world", "example", "--model", name)
    assert rc == 0, err
    f = tmp_path / "w.yaml"
    f.write_text(text)
    rc, out, err = station_main("mock", "world", "show", f)
    assert rc == 0, err
    assert f"model {name} (parallel)" in out and ".offset" in out
