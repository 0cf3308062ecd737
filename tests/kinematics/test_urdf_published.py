"""Published robot descriptions this team did not write: the BSD-licensed ``example-robot-data`` collection
(a dev dependency: pyproject.toml installs it), Kinova's own Gen3 lite URDF (tests/data/urdf, BSD, with its
licence) and the URDFs of the public MUKCa real-data set (tests/data/mukca, MIT, with its licence).

Every serial chain of every file (every link that ends a chain of movable joints) loads with ``--tip-link``
and its FK equals an independent URDF library's (yourdfpy) to 1e-9 m/rad at random joint values. What urdfdom
accepts is accepted (limits on fixed and continuous joints ignored, zero velocity or equal limits on a moving
joint a warning); what makes a chain unusable is one line naming file, line and element."""

import math
import sysconfig
from pathlib import Path

import numpy as np
import pytest
import yourdfpy
from clirunner import station_proc

from station.kinematics import ModelFileError, load_model
from station.kinematics.urdf import chain_ends, read_urdf

DATA = Path(__file__).parents[1] / "data"
TOL = 1e-9


def corpus_root() -> Path:
    """The robots of the installed example-robot-data package (cmeel layout)."""
    root = Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
    assert root.is_dir(), "example-robot-data is a dev dependency (pip install -e '.[dev]')"
    return root


def corpus_files() -> list[Path]:
    return sorted(corpus_root().rglob("*.urdf")) + sorted((DATA / "urdf").rglob("*.urdf")) + sorted(
        (DATA / "mukca").glob("*.urdf"))


def erd(rel: str) -> Path:
    return corpus_root() / rel


def _yourdfpy(path):
    return yourdfpy.URDF.load(str(path), load_meshes=False, build_collision_scene_graph=False)


def _fk_error(path: Path, tip: str, u, rng, n=4, robot=None) -> float:
    """Largest position/rotation-entry difference between the station's chain to ``tip`` and yourdfpy, at ``n``
    random configurations of every actuated joint (a mimic joint on the chain takes the value it mimics).
    ``robot``: the file already read (``read_urdf``), as ``load_model`` would read it."""
    from station.kinematics.urdf import chain, model_from_chain

    m = load_model(path, tip_link=tip) if robot is None else model_from_chain(chain(robot, tip))
    base = m.source["urdf"]["base_link"]
    err = 0.0
    for _ in range(n):
        cfg = {name: float(rng.uniform(-1.2, 1.2)) for name in u.actuated_joint_names}
        q = []
        for j in m.joints:
            uj = u.joint_map[j.name]
            if uj.mimic is not None:
                q.append(cfg.get(uj.mimic.joint, 0.0) * (1.0 if uj.mimic.multiplier is None else uj.mimic.multiplier)
                         + (uj.mimic.offset or 0.0))
            else:
                q.append(cfg[j.name])
        u.update_cfg(cfg)
        W = u.get_transform(tip, base)
        T = m.fk(np.array(q))
        err = max(err, float(np.abs(W[:3, 3] - T[:3, 3]).max()), float(np.abs(W[:3, :3] - T[:3, :3]).max()))
    return err


@pytest.mark.slow
def test_every_serial_chain_of_every_published_urdf_loads_and_matches_yourdfpy():
    rng = np.random.default_rng(0)
    chains, refused, worst = 0, [], 0.0
    for path in corpus_files():
        try:
            robot = read_urdf(path)
        except ModelFileError as e:  # only files with nothing that moves may be refused
            assert "no joint" in str(e) and "\n" not in str(e), str(e)
            refused.append(path.name)
            continue
        u = _yourdfpy(path)
        for tip, _ in chain_ends(robot):
            err = _fk_error(path, tip, u, rng, n=3, robot=robot)
            assert err < TOL, f"{path.name} -> {tip}: {err:.3g}"
            worst = max(worst, err)
            chains += 1
    assert chains > 500  # 69 published files: humanoids, quadrupeds, hands, arms, flying arms
    assert sorted(refused) == ["quadrotor_base.urdf", "ur3.urdf"]  # a single link; an empty <robot>
    print(f"{chains} chains, worst FK difference to yourdfpy {worst:.2g}")


# the files the issue names: a Kinova Gen3 lite, the Jaco arm of example-robot-data, a quadrotor, a humanoid
# hand, double pendulums
@pytest.mark.parametrize("rel,tip,n", [
    ("kinova_description/robots/kinova.urdf", "j2s6s200_end_effector", 6),
    ("allegro_hand_description/urdf/allegro_right_hand.urdf", "link_3.0_tip", 4),
    ("double_pendulum_description/urdf/double_pendulum.urdf", None, 2),
    ("double_pendulum_description/urdf/double_pendulum_continuous.urdf", None, 2),
    ("double_pendulum_description/urdf/double_pendulum_simple.urdf", None, 2),
    ("romeo_description/urdf/romeo_laas_small.urdf", "r_gripper", 9),  # near-intersecting axes, gimbal lock
])
def test_the_reported_refusals_now_load_and_match(rel, tip, n):
    path = erd(rel)
    m = load_model(path, tip_link=tip)
    assert m.n_joints == n
    ends = chain_ends(read_urdf(path))
    assert _fk_error(path, tip or ends[0][0], _yourdfpy(path), np.random.default_rng(1)) < TOL


def test_kinova_gen3_lite_urdfs_load_without_complaint():
    """Kinova's own file (a fixed joint with velocity 0 and limits 0 0) and the MUKCa data set's."""
    m = load_model(DATA / "urdf" / "kinova_gen3_lite" / "GEN3-LITE.urdf")
    assert m.n_joints == 6 and m.source["warnings"] == []
    g = load_model(DATA / "mukca" / "gen3lite.urdf", tip_link="ball_link")
    assert g.n_joints == 6 and g.source["warnings"] == []
    u = _yourdfpy(DATA / "urdf" / "kinova_gen3_lite" / "GEN3-LITE.urdf")
    assert _fk_error(DATA / "urdf" / "kinova_gen3_lite" / "GEN3-LITE.urdf", "DUMMY", u,
                     np.random.default_rng(2)) < TOL


def test_a_model_with_several_chain_ends_names_them():
    with pytest.raises(ModelFileError) as e:
        load_model(DATA / "mukca" / "panda.urdf")
    msg = str(e.value)
    assert "several chain ends: panda_leftfinger (8 joints), panda_rightfinger (8 joints), ball_link (7 joints)" in msg
    assert "--tip-link" in msg and "\n" not in msg
    with pytest.raises(ModelFileError, match=r"several chain ends: .* and \d+ more; choose one"):
        load_model(erd("pr2_description/urdf/pr2.urdf"))  # 30-odd ends: the longest twelve and a count


def test_links_only_says_what_it_found():
    with pytest.raises(ModelFileError) as e:
        load_model(erd("hector_description/robots/quadrotor_base.urdf"))
    assert "has 1 link(s) (base_link) and no joint" in str(e.value) and "quadrotor_base.urdf:" in str(e.value)


UR = """<robot name="r">
<link name="a"/><link name="b"/><link name="c"/><link name="t"/>
<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><origin xyz="0 0 0.1" rpy="0 0 0"/>
  <axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="2"/></joint>
<joint name="j2" type="revolute"><parent link="b"/><child link="c"/><origin xyz="0.3 0 0" rpy="0 0 0"/>
  <axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="1" velocity="2"/></joint>
<joint name="tool" type="fixed"><parent link="c"/><child link="t"/><origin xyz="0.2 0 0" rpy="0 0 0"/>
  <limit lower="0" upper="0" effort="0" velocity="0"/></joint>
</robot>
"""


def _write(tmp_path, text, name="r.urdf") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_limits_on_fixed_joints_are_ignored_moving_joints_without_range_or_speed_warn(tmp_path):
    assert load_model(_write(tmp_path, UR)).source["warnings"] == []  # the fixed joint's velocity 0: nothing
    cont = UR.replace('type="revolute"', 'type="continuous"', 1).replace('lower="-3" upper="3"', 'lower="0" upper="0"')
    m = load_model(_write(tmp_path, cont.replace('velocity="2"', 'velocity="0"', 1)))
    assert m.source["warnings"] == [] and m.joints[0].lower == -2 * math.pi  # continuous: <limit> ignored
    m = load_model(_write(tmp_path, UR.replace('lower="-2" upper="2" effort="1" velocity="2"',
                                               'lower="0" upper="0" effort="1" velocity="0"')))
    w = m.source["warnings"]
    assert len(w) == 2 and all(s.startswith(f"{tmp_path / 'r.urdf'}:") and "'j2'" in s for s in w)
    assert "no range" in w[0] and "velocity=0" in w[1]
    assert m.joints[1].max_velocity > 0 and m.joints[1].lower < m.joints[1].upper
    # simulators' "no limit" (+-1e16) on a revolute joint: unlimited, with a warning
    m = load_model(_write(tmp_path, UR.replace('lower="-3" upper="3"', 'lower="-1e16" upper="1e16"')))
    assert "beyond any physical range" in m.source["warnings"][0] and m.joints[0].upper == 2 * math.pi


@pytest.mark.parametrize("old,new,element", [
    ('<origin xyz="0.3 0 0"', '<origin xyz="1e308 0 0"', "<origin xyz='1e308 0 0'>"),
    ('<axis xyz="0 1 0"/>', '<axis xyz="0 0 -1e308"/>', "<axis xyz='0 0 -1e308'>"),
    ('<origin xyz="0.3 0 0" rpy="0 0 0"/>', '<origin xyz="0.3 0 0" rpy="0 1e300 0"/>', "<origin rpy='0 1e300 0'>"),
    ('<origin xyz="0.3 0 0"', '<origin xyz="inf 0 0"', "<origin xyz='inf 0 0'>"),
    ('<link name="c"/>', '<link name="c"><inertial><mass value="1e30"/></inertial></link>', "<mass value='1e30'>"),
    ('<axis xyz="0 1 0"/>', '<axis xyz="0 1e-300 0"/>', "zero axis"),
])
def test_numbers_beyond_physical_bounds_are_one_line_naming_file_line_element(tmp_path, old, new, element):
    text = UR.replace(old, new, 1)
    p = _write(tmp_path, text)
    line = next(i for i, s in enumerate(text.splitlines(), 1) if new in s)
    with pytest.raises(ModelFileError) as e:
        load_model(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}:{line}:") and element in msg and "\n" not in msg, msg


def test_a_urdf_in_millimetres_is_refused_naming_the_unit(tmp_path):
    mm = UR.replace('xyz="0 0 0.1"', 'xyz="0 0 100"').replace('xyz="0.3 0 0"', 'xyz="300 0 0"').replace(
        'xyz="0.2 0 0"', 'xyz="200 0 0"')
    with pytest.raises(ModelFileError, match=r"reaches 500 m .*URDF lengths are metres - were these millimetres"):
        load_model(_write(tmp_path, mm))


def test_cli_prints_each_warning_as_one_line_on_stderr(tmp_path):
    p = _write(tmp_path, UR.replace('lower="-2" upper="2" effort="1" velocity="2"',
                                    'lower="0" upper="0" effort="1" velocity="0"'))
    (tmp_path / "q.csv").write_text("q1,q2\n0.1,0.2\n")
    r = station_proc("fk", "--model", p, "--joints", "q.csv", cwd=tmp_path, timeout=60)
    assert r.code == 0, r.err
    lines = r.err_lines
    assert len(lines) == 2 and all(s.startswith("station: warning: ") for s in lines)
    assert "x[m]" in r.out and "warning" not in r.out


def test_a_chain_whose_tip_sits_on_its_only_axis_solves(tmp_path):
    """A quadcopter rotor (one joint, the tip on its axis): nothing moves the tip, which the solve must say (it
    divided by the tip's zero motion before)."""
    from station.kinematics.urdf import chain as urdf_chain

    path = erd("iris_description/robots/iris.urdf")
    ch = urdf_chain(read_urdf(path), "iris__rotor_0")
    rng = np.random.default_rng(3)
    q = rng.uniform(-3, 3, (12, 1))
    xyz = np.array([ch.fk(v)[:3, 3] for v in q]) + rng.normal(0, 2e-5, (12, 3))
    (tmp_path / "s.csv").write_text("q1,x,y,z\n" + "\n".join(",".join(repr(float(v)) for v in (*a, *b))
                                                              for a, b in zip(q, xyz, strict=True)) + "\n")
    p = station_proc("solve", "--model", path, "--tip-link", "iris__rotor_0", "--samples", "s.csv",
                     "--instrument-frame", "base", "--identify", "offsets,tcp", cwd=tmp_path, timeout=60)
    assert p.code == 0, p.err
    assert "offset.j1: the TCP is free" in p.out
