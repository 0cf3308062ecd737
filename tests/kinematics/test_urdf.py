"""URDF models: forward kinematics against an independent URDF evaluator (yourdfpy), chain selection and
refusals with one-line errors, hostile XML, export of nominal and calibrated robots, import to a model file,
and the CLI and world files taking a URDF wherever a model is accepted."""

import math
import time

import numpy as np
import pytest
import urdf_robots as robots
import yourdfpy
from clirunner import station_proc

from station.kinematics import ModelFileError, load_model
from station.kinematics.urdfexport import urdf_text

TOL = 1e-9  # m and rad: the bound for FK against an independent evaluator


def _evaluator(path):
    return yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)


def _q(m, n, rng):
    lo, hi = np.maximum(m.lower, -math.pi), np.minimum(m.upper, math.pi)
    return lo + (hi - lo) * rng.random((n, m.n_joints))


def _max_fk_error(m, path, tip, base=None, n=40, seed=0):
    """Largest |position| (m) and rotation-matrix entry difference between the station model and yourdfpy."""
    u = _evaluator(path)
    rng = np.random.default_rng(seed)
    err = 0.0
    names = [j.name for j in m.joints]
    for q in _q(m, n, rng):
        cfg = dict.fromkeys(u.actuated_joint_names, 0.0) | dict(zip(names, q, strict=True))
        u.update_cfg(cfg)
        W = u.get_transform(tip, base or u.base_link)
        T = m.fk(q)
        err = max(err, float(np.abs(W[:3, 3] - T[:3, 3]).max()), float(np.abs(W[:3, :3] - T[:3, :3]).max()))
    return err


@pytest.mark.parametrize("name", sorted(robots.ROBOTS))
def test_fk_matches_an_independent_urdf_evaluator(tmp_path, name):
    path = robots.write(tmp_path, name)
    tip = robots.ROBOTS[name][1]
    m = load_model(path, tip_link=tip)
    assert m.convention == "mdh"
    assert _max_fk_error(m, path, tip or "tool") < TOL


def test_urdf_from_the_published_ur5e_table_is_the_builtin_ur5e(tmp_path):
    m = load_model(robots.write(tmp_path, "ur5e"))  # default tip: tool0 (the 'base' leaf has no movable joint)
    (tx, ty, tz), (rr, rp, ry) = robots.UR5E_TOOL
    b = load_model("ur5e").with_params({"tcp.x": tx, "tcp.y": ty, "tcp.z": tz, "tcp.rx": rr, "tcp.ry": rp,
                                        "tcp.rz": ry})
    q = _q(m, 30, np.random.default_rng(3))
    np.testing.assert_allclose(m.fk(q), b.fk(q), atol=TOL)
    assert [j.name for j in m.joints] == [f"joint{i}" for i in range(1, 7)]
    # the UR's parallel shoulder/elbow/wrist-1 axes carry Hayati's beta in the link group
    assert {"mdh.j3.beta", "mdh.j4.beta"} <= set(m.groups["dh"]) and "mdh.j2.beta" not in m.groups["dh"]


def test_chain_from_a_chosen_base_link_and_to_an_inner_tip(tmp_path):
    path = robots.write(tmp_path, "arm7")
    m = load_model(path, tip_link="arm_link5", base_link="arm_link2")
    assert [j.name for j in m.joints] == ["arm_joint3", "arm_joint4", "arm_joint5"]
    assert _max_fk_error(m, path, "arm_link5", base="arm_link2") < TOL


def test_limits_soft_limits_continuous_velocity_and_calibration_tags(tmp_path):
    arm = load_model(robots.write(tmp_path, "arm7"), tip_link="ball")
    lo, hi = robots.ARM7_LIMITS[3]
    j4 = arm.joints[3]
    assert (j4.lower, j4.upper) == pytest.approx((lo + 0.01, hi - 0.01))  # the safety controller's soft limits
    assert j4.max_velocity == pytest.approx(2.175)
    rail = load_model(robots.write(tmp_path, "rail_scara"))
    assert [j.kind for j in rail.joints] == ["prismatic", "revolute", "revolute", "prismatic", "revolute"]
    assert (rail.joints[4].lower, rail.joints[4].upper) == (-2 * math.pi, 2 * math.pi)  # continuous
    assert (rail.joints[0].lower, rail.joints[0].upper, rail.joints[0].max_velocity) == (0, 1.5, 0.5)
    ur = load_model(robots.write(tmp_path, "ur5e"))
    assert ur.source["urdf"]["calibration"]["joint3"] == {"rising": pytest.approx(0.02)}


def test_full_group_is_every_geometric_parameter_a_position_sees(tmp_path):
    for m in (load_model(robots.write(tmp_path, "arm7"), tip_link="ball"), load_model("ur5e")):
        full = m.select("full")
        assert set(m.select("offsets,dh,tcp,base")) == set(full)
        assert not any(n.startswith(("compliance.", "tcp.r")) for n in full)
        assert len(full) == len(set(full))


def _fails(tmp_path, text, match, **kw):
    p = tmp_path / "bad.urdf"
    p.write_text(text)
    with pytest.raises(ModelFileError, match=match) as e:
        load_model(p, **kw)
    assert "\n" not in str(e.value)
    return str(e.value)


def test_ambiguous_or_unknown_links_are_one_line_errors_listing_candidates(tmp_path):
    msg = _fails(tmp_path, robots.arm7_urdf(), "several chain ends")
    # every chain end is named with its number of joints, the longest first
    assert "finger_left (8 joints), finger_right (8 joints), ball (7 joints)" in msg
    _fails(tmp_path, robots.arm7_urdf(), r"no link 'palm' for the tip link \(links: arm_link0", tip_link="palm")
    _fails(tmp_path, robots.arm7_urdf(), "base link 'hand' is not on the path to tip link 'arm_link3'",
           tip_link="arm_link3", base_link="hand")


def test_mimic_on_the_chain_is_a_joint_of_its_own_off_the_chain_ignored(tmp_path):
    p = tmp_path / "mimic.urdf"
    p.write_text(robots.arm7_urdf(mimic_on_chain=True))
    m = load_model(p, tip_link="ball")  # the joint state lists a mimic joint's reading: it is a column
    assert [j.name for j in m.joints][3] == "arm_joint4" and m.n_joints == 7
    (w,) = m.source["warnings"]
    assert w.startswith(f"{p}:") and "'arm_joint4' mimics 'arm_joint1'" in w and "\n" not in w
    u = _evaluator(p)  # the same transforms, the mimic joint at the value it mimics (multiplier 1)
    for q in _q(m, 10, np.random.default_rng(1)):
        q[3] = q[0]
        u.update_cfg(dict.fromkeys(u.actuated_joint_names, 0.0) | {j.name: v for j, v in zip(m.joints, q, strict=True)
                                                                    if j.name in u.actuated_joint_names})
        np.testing.assert_allclose(m.fk(q), u.get_transform("ball", u.base_link), atol=TOL)
    assert load_model(robots.write(tmp_path, "arm7"), tip_link="ball").source["warnings"] == []  # fingers: off


def test_closed_loops_and_bad_joints_are_refused_with_file_and_line(tmp_path):
    ur = robots.ur5e_urdf()
    loop = ur.replace("</robot>", '<joint name="loop" type="fixed"><parent link="link5"/><child link="link2"/>'
                                  "</joint></robot>")
    msg = _fails(tmp_path, loop, r"closed loop: link 'link2' is the child of joints 'joint2' \(line \d+\) and 'loop'")
    assert f"bad.urdf:{loop.splitlines().index(next(s for s in loop.splitlines() if 'loop' in s)) + 1}:" in msg
    cycle = ('<robot name="c"><link name="a"/><link name="b"/>'
             '<joint name="ab" type="fixed"><parent link="a"/><child link="b"/></joint>'
             '<joint name="ba" type="fixed"><parent link="b"/><child link="a"/></joint></robot>')
    _fails(tmp_path, cycle, "closed loop")
    _fails(tmp_path, ur.replace('type="revolute"', 'type="floating"', 1), "floating joint cannot be part")
    # a moving joint without a range is accepted (urdfdom does), with a warning naming the element
    p = tmp_path / "norange.urdf"
    p.write_text(ur.replace('lower="-6.283185307179586" upper="6.283185307179586"', "", 1))
    m = load_model(p)
    assert (m.joints[0].lower, m.joints[0].upper) == (-2 * math.pi, 2 * math.pi)
    assert any("gives the joint no range" in w and w.startswith(f"{p}:") for w in m.source["warnings"])
    _fails(tmp_path, ur.replace('<axis xyz="0 0 1"/>', '<axis xyz="0 0 0"/>', 1), "zero axis")
    _fails(tmp_path, ur.replace('rpy="0 0 3.141592653589793"', 'rpy="0 0 pi"', 1), r":\d+: <origin rpy='0 0 pi'>")
    _fails(tmp_path, ur.replace('<child link="link3"/>', '<child link="link33"/>'),
           "child link 'link33' is not defined")
    _fails(tmp_path, ur.replace('type="revolute"', 'type="screw"', 1), "type 'screw' is not one of")
    _fails(tmp_path, ur.replace("<robot", "<robt").replace("</robot>", "</robt>"), "root element is <robot>")
    _fails(tmp_path, ur.replace('<joint name="joint4"', '<joint name="joint3"'), "joint 'joint3' is defined twice")
    _fails(tmp_path, ur[: len(ur) // 2], r"bad.urdf:\d+: not well-formed XML")


def test_hostile_xml_is_refused_at_once(tmp_path, monkeypatch):
    laughs = ('<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
              + "".join(f'<!ENTITY lol{i} "{("&lol" + (str(i - 1) if i > 1 else "") + ";") * 10}">'
                        for i in range(1, 10))
              + ']><robot name="x"><link name="&lol9;"/></robot>')
    t0 = time.perf_counter()
    _fails(tmp_path, laughs, r"bad.urdf:1: document type declarations \(<!DOCTYPE>\) are not accepted")
    external = ('<?xml version="1.0"?><!DOCTYPE r [<!ENTITY e SYSTEM "file:///etc/passwd">]>'
                '<robot name="&e;"/>')
    _fails(tmp_path, external, "are not accepted")
    _fails(tmp_path, '<robot name="&undefined;"/>', "not well-formed XML")
    assert time.perf_counter() - t0 < 2.0
    import station.kinematics.urdfxml as ux

    monkeypatch.setattr(ux, "MAX_BYTES", 1000)
    _fails(tmp_path, robots.ur5e_urdf(), "larger than")
    p = tmp_path / "robot.urdf.xacro"
    p.write_text(robots.ur5e_urdf())
    with pytest.raises(ModelFileError, match="expand it first"):
        load_model(p)


def _perturbed(m, rng, scale=0.01):
    vals = {n: v + scale * rng.standard_normal() for n, v in m.param_dict().items()
            if not n.startswith("compliance.")}
    return m.with_params(vals)


@pytest.mark.parametrize("name", sorted(robots.ROBOTS))
def test_exported_urdf_of_nominal_and_calibrated_robot(tmp_path, name):
    src = robots.write(tmp_path, name)
    tip = robots.ROBOTS[name][1] or "tool"
    m = load_model(src, tip_link=tip)
    cal = _perturbed(m, np.random.default_rng(5))
    for label, model in (("nominal", m), ("calibrated", cal)):
        out = tmp_path / f"{name}_{label}.urdf"
        out.write_text(urdf_text(model, f"test {label}"))
        assert _max_fk_error(model, out, tip) < TOL, label
        back = load_model(out, tip_link=tip)  # and the station reads its own export
        q = _q(model, 10, np.random.default_rng(1))
        np.testing.assert_allclose(back.fk(q), model.fk(q), atol=TOL)
    text = (tmp_path / f"{name}_calibrated.urdf").read_text()
    original = src.read_text()
    for tag in ("<visual>", "<inertial>", "<calibration", "<mimic"):  # everything off the origins is kept
        assert text.count(tag) == original.count(tag)


def test_exported_urdf_when_the_tip_is_the_last_joints_own_link(tmp_path):
    path = robots.write(tmp_path, "ur5e")
    m = load_model(path, tip_link="link6")
    cal = _perturbed(m, np.random.default_rng(6))
    out = tmp_path / "cal.urdf"
    out.write_text(urdf_text(cal))
    assert _max_fk_error(cal, out, "station_tool") < TOL  # the changed tool is a fixed joint of its own
    rigid = cal.fk(np.zeros(6))
    u = _evaluator(out)
    np.testing.assert_allclose(u.get_transform("station_tool", "base_link"), rigid, atol=TOL)


@pytest.mark.parametrize("name", ["ur5e", "scara", "omx", "arm6"])
def test_generated_urdf_of_builtin_models(tmp_path, name):
    m = load_model(name).with_payload(0.5, (0.0, 0.0, 0.02))
    cal = _perturbed(m, np.random.default_rng(7))
    out = tmp_path / f"{name}.urdf"
    out.write_text(urdf_text(cal))
    assert _max_fk_error(cal, out, "tool0") < TOL
    assert "point mass" in out.read_text()


def test_cli_import_export_show_and_fk_take_a_urdf(tmp_path):
    path = robots.write(tmp_path, "arm7")
    r = station_proc("model", "import", path, "--tip-link", "ball", "--out", tmp_path / "arm7.yaml")
    assert r.code == 0, r.err
    imported = load_model(tmp_path / "arm7.yaml")
    m = load_model(path, tip_link="ball")
    q = _q(m, 20, np.random.default_rng(2))
    np.testing.assert_allclose(imported.fk(q), m.fk(q), atol=1e-9)
    np.testing.assert_allclose(imported.gravity_torque(q), m.gravity_torque(q), atol=1e-9)  # masses kept
    assert imported.name == m.name == "arm7" and imported.convention == "mdh"
    # fk from the URDF and from the imported file
    joints = tmp_path / "q.csv"
    joints.write_text("q1,q2,q3,q4,q5,q6,q7\n" + "\n".join(",".join(f"{x:.12f}" for x in row) for row in q) + "\n")
    for model_args in (["--model", path, "--tip-link", "ball"], ["--model", tmp_path / "arm7.yaml"]):
        r = station_proc("fk", *model_args, "--joints", joints)
        assert r.code == 0, r.err
        xyz = np.loadtxt(r.out.splitlines()[2:], delimiter=",")[:, :3]
        np.testing.assert_allclose(xyz, m.position(q), atol=2e-9)
    r = station_proc("fk", "--model", path, "--joints", joints)
    assert r.code == 2 and r.err.startswith("station: error: ") and "several chain ends" in r.err
    assert len(r.err.strip().splitlines()) == 1
    r = station_proc("model", "show", path, "--tip-link", "ball")
    assert r.code == 0 and "chain world -> ball" in r.out and "compliance.j2" in r.out
    r = station_proc("model", "export", path, "--tip-link", "ball", "--format", "urdf", "--out", tmp_path / "o.urdf")
    assert r.code == 0, r.err
    assert _max_fk_error(m, tmp_path / "o.urdf", "ball") < TOL
    r = station_proc("model", "export", "ur5e", "--tip-link", "x")
    assert r.code == 2 and "URDF model only" in r.err


def test_cli_export_of_a_calibrated_urdf_robot(tmp_path):
    from station.solver.result import CalibrationResult, ParameterEstimate

    path = robots.write(tmp_path, "ur5e")
    m = load_model(path)
    true = {"offset.j2": 0.002, "mdh.j3.a": m.param("mdh.j3.a") + 0.0004, "tcp.z": m.param("tcp.z") + 0.001}
    params = {n: ParameterEstimate(n, v, m.param(n), 1e-6, True) for n, v in true.items()}
    res = CalibrationResult(m.name, params, {"rms_before_m": 0, "rms_after_m": 0, "max_after_m": 0}, 3, 3, True, 1)
    (tmp_path / "cal.json").write_text(__import__("json").dumps(res.to_dict()))
    r = station_proc("model", "export", path, "--format", "urdf", "--calibration", tmp_path / "cal.json",
                     "--out", tmp_path / "cal.urdf")
    assert r.code == 0, r.err
    assert _max_fk_error(m.with_params(true), tmp_path / "cal.urdf", "tool0") < TOL
    assert _max_fk_error(m, tmp_path / "cal.urdf", "tool0") > 1e-4  # and it is not the nominal robot
    r = station_proc("model", "export", path, "--format", "urdf", "--out", path)
    assert r.code == 2 and "the model being read" in r.err


def test_world_file_with_a_urdf_robot(tmp_path):
    from station.mocks.world import World

    path = robots.write(tmp_path, "arm7")
    doc = {"format": "station-world/1", "units": {"length": "m", "angle": "rad"},
           "robot": {"model": path.name, "tip_link": "ball"}, "cell": {"points": []},
           "motion": {"start": [0, -0.3, 0, -1.5, 0, 1.2, 0]}}
    (tmp_path / "world.yaml").write_text(__import__("yaml").safe_dump(doc))
    w = World.from_file(tmp_path / "world.yaml")
    assert w.nominal.n_joints == 7 and w.nominal.source["urdf"]["tip_link"] == "ball"
    u = _evaluator(path)
    q = np.array([0.3, -0.5, 0.2, -1.8, 0.4, 1.5, -0.6])
    w.command_q(q)
    u.update_cfg(dict.fromkeys(u.actuated_joint_names, 0.0) | {f"arm_joint{i + 1}": x for i, x in enumerate(q)})
    np.testing.assert_allclose(w.tip_true(), u.get_transform("ball", "world")[:3, 3], atol=TOL)
    again = World.from_dict(w.to_dict(), str(tmp_path / "again.yaml"))
    assert again.nominal.source["urdf"]["tip_link"] == "ball"
    bad = dict(doc, robot={"model": path.name})
    (tmp_path / "bad.yaml").write_text(__import__("yaml").safe_dump(bad))
    with pytest.raises(ValueError, match="robot.model: .*several chain ends"):
        World.from_file(tmp_path / "bad.yaml")


def test_mdh_conversion_handles_arbitrary_axes(tmp_path):
    """Random joint origins and axes (some parallel, some intersecting, some anti-parallel) stay exact."""
    rng = np.random.default_rng(11)
    for trial in range(12):
        s = ['<robot name="rand">', '<link name="l0"/>']
        for i in range(6):
            xyz = rng.normal(0, 0.2, 3) * (rng.random() > 0.3)
            rpy = rng.normal(0, 1.0, 3) * (rng.random() > 0.4)
            axis = [(0, 0, 1), (0, 0, -1), (1, 0, 0), tuple(rng.normal(size=3))][rng.integers(4)]
            axis = np.array(axis) / np.linalg.norm(axis)  # URDF: "the vector should be normalized"
            kind = "prismatic" if rng.random() < 0.2 else "revolute"
            xyz, rpy, axis = (" ".join(map(str, v)) for v in (xyz, rpy, axis))
            s.append(f'<link name="l{i + 1}"/><joint name="j{i + 1}" type="{kind}"><parent link="l{i}"/>'
                     f'<child link="l{i + 1}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>'
                     '<limit lower="-3" upper="3" velocity="1" effort="1"/></joint>')
        s.append('<link name="tip"/><joint name="t" type="fixed"><parent link="l6"/><child link="tip"/>'
                 f'<origin xyz="{" ".join(map(str, rng.normal(0, 0.1, 3)))}" rpy="0.3 0.2 0.1"/></joint></robot>')
        p = tmp_path / f"rand{trial}.urdf"
        p.write_text("".join(s))
        m = load_model(p)
        assert _max_fk_error(m, p, "tip", n=20) < TOL, trial
        assert np.isfinite(m.params).all()



def test_near_parallel_axes_use_hayati_beta(tmp_path):
    """Axes 1 deg apart: the common normal would be metres long; beta keeps every parameter small."""
    tilt = math.radians(1.0)
    text = f"""<robot name="planar"><link name="b"/><link name="l1"/><link name="l2"/><link name="l3"/>
      <joint name="j1" type="revolute"><parent link="b"/><child link="l1"/><origin xyz="0 0 0.1"/>
        <axis xyz="0 0 1"/><limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
      <joint name="j2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.4 0 0.02" rpy="{tilt} 0 0"/>
        <axis xyz="0 0 1"/><limit lower="-3" upper="3" velocity="1" effort="1"/></joint>
      <joint name="j3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.3 0 0" rpy="0 {-tilt} 0"/>
        <axis xyz="0 0 1"/><limit lower="-3" upper="3" velocity="1" effort="1"/></joint></robot>"""
    p = tmp_path / "planar.urdf"
    p.write_text(text)
    m = load_model(p)
    assert _max_fk_error(m, p, "l3") < TOL
    # a tilt about the common x is alpha, about y beta (up to the small turn of x towards the crossing point)
    assert abs(m.param("mdh.j2.beta")) < 0.01 * tilt
    assert abs(m.param("mdh.j2.alpha")) == pytest.approx(tilt, rel=1e-3)
    assert abs(m.param("mdh.j3.beta")) == pytest.approx(tilt, rel=1e-2)
    assert "mdh.j2.beta" in m.groups["dh"] and "mdh.j3.beta" in m.groups["dh"]
    lengths = [abs(m.param(n)) for n in m.param_names if n.endswith((".a", ".d"))]
    assert max(lengths) < 0.5
