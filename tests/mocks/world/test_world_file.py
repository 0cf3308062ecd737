"""Simulated world, world files: round trip, units, seeding, explicit and random errors, one-line errors."""

import copy
import math
import re

import numpy as np
import pytest
import yaml
from station.mocks.world import World, WorldFileError, default_doc
from station.mocks.world.example import example_text


def _doc(**sections):
    d = {"format": "station-world/1", "units": {"length": "mm", "angle": "deg"}, "seed": 4,
         "robot": {"model": "ur5e"}}
    d.update(sections)
    return d


def test_explicit_errors_in_file_units():
    w = World.from_dict(_doc(errors={"explicit": {"offset.j2": 0.05, "dh.j3.a": 0.3, "tcp.z": -1.5}}))
    h = w.hidden()
    assert set(h) == {"dh.j3.a", "tcp.z"} | {f"offset.j{i}" for i in range(1, 7)}  # offsets always listed
    assert set(w.errors()) == {"offset.j2", "dh.j3.a", "tcp.z"}
    assert h["offset.j1"] == 0.0
    np.testing.assert_allclose(w.true_offsets(), [0, math.radians(0.05), 0, 0, 0, 0])
    assert h["offset.j2"] == pytest.approx(math.radians(0.05))
    assert h["dh.j3.a"] == pytest.approx(w.nominal.param("dh.j3.a") + 0.3e-3)
    assert h["tcp.z"] == pytest.approx(-1.5e-3)
    assert w.errors()["dh.j3.a"] == pytest.approx(0.3e-3)
    # the truth model carries them, the nominal does not
    assert w.truth.param("offset.j2") == pytest.approx(math.radians(0.05))
    assert w.nominal.param("offset.j2") == 0.0


def test_mm_deg_and_m_rad_give_the_same_world():
    a = World.from_dict(_doc(errors={"explicit": {"offset.j1": 0.1, "dh.j2.d": 0.2},
                                     "random": {"dh": {"length": 0.2, "angle": 0.02}}},
                             cell={"capture_radius": 6, "points": [
                                 {"label": "A", "kind": "socket", "position": [450, 10, 50]}]},
                             noise={"seating": 0.01}, motion={"start": [0, -90, 90, -90, -90, 0]}))
    b = World.from_dict(a.to_dict())  # m, rad
    c = World.from_dict(a.to_dict("mm", "deg"))
    for w in (b, c):
        assert w.hidden().keys() == a.hidden().keys()
        for k, v in a.hidden().items():
            assert w.hidden()[k] == pytest.approx(v, abs=1e-12)
        np.testing.assert_allclose(w.points["A"].position, [0.45, 0.01, 0.05])
        assert w.points["A"].radius == pytest.approx(6e-3)
        assert w.spec.seating_sigma == pytest.approx(1e-5)
        np.testing.assert_allclose(w.encoder_q(), np.radians([0, -90, 90, -90, -90, 0]))


def test_round_trip_preserves_everything():
    w = World.default("scara", seed=12, time_mode="sim", noise={"seating": 2e-5, "survey": 1e-3},
                      joints={"backlash": {"j1": 1e-4}, "compliance": {"j2": 1e-5}, "payload": 1.0},
                      buses={"canopen": {"nodes": [1, 2, 3, 4]}})
    d = w.to_dict()
    w2 = World.from_dict(yaml.safe_load(yaml.safe_dump(d)))
    assert w2.to_dict() == d
    assert w2.hidden() == pytest.approx(w.hidden())
    assert w2.station_cell() == w.station_cell()
    assert w2.bus_config("canopen") == {"nodes": [1, 2, 3, 4]}
    assert w2.bus_config("dynamixel") == {}
    assert w2.time_mode == "sim"


def test_a_selector_that_selects_nothing_is_written_back_as_given():
    """The struts2 example's ``tcp`` selector selects nothing on that parallel robot: the world writes back the
    sigma the file gave (no quantity to infer from no parameters) and reads it back the same."""
    w = World.from_dict(yaml.safe_load(example_text("struts2")))
    d = w.to_dict()
    assert d["errors"]["random"]["tcp"] == {"angle": pytest.approx(math.radians(0.5))}  # 0.5 deg, written in rad
    w2 = World.from_dict(yaml.safe_load(yaml.safe_dump(d)))
    assert w2.to_dict() == d and w2.hidden() == pytest.approx(w.hidden())


def test_frozen_world_keeps_truth_without_seed():
    w = World.default("arm6", seed=21)
    d = w.to_dict(frozen=True)
    assert d["errors"]["random"] == {}
    d["seed"] = 99  # truth no longer depends on the seed
    w2 = World.from_dict(d)
    assert w2.hidden() == pytest.approx(w.hidden(), abs=1e-12)


def test_seeding_is_reproducible_and_seeds_differ():
    a, b, c = World.default("ur5e", seed=1), World.default("ur5e", seed=1), World.default("ur5e", seed=2)
    assert a.hidden() == b.hidden()
    assert a.hidden() != c.hidden()
    # random errors have the stated sigma: offsets 0.1 deg over many seeds
    offs = np.array([[v for k, v in World.default("ur5e", seed=s).errors().items() if k.startswith("offset")]
                     for s in range(40)]).ravel()
    assert offs.std() == pytest.approx(math.radians(0.1), rel=0.25)


def test_seating_draws_do_not_change_hidden_errors():
    """Independent random streams: the same seed gives the same truth whatever happened before."""
    a = World.default("omx", seed=3, noise={"survey": 1e-3})
    b = World.default("omx", seed=3, noise={"survey": 0.0})
    assert a.hidden() == b.hidden()


def test_random_error_selectors():
    w = World.from_dict(_doc(errors={"random": {"offsets": 0.1, "dh.j2.*": {"length": 0.5, "angle": 0.05}}}))
    names = set(w.errors())
    assert {f"offset.j{i}" for i in range(1, 7)} <= names
    assert any(n.startswith("dh.j2.") for n in names)
    assert not any(n.startswith(("dh.j1.", "tcp.", "base.")) for n in names)
    # the most specific selector sets the sigma, whatever the order; selector order never changes a draw
    a = World.from_dict(_doc(errors={"random": {"offsets": 0.1, "offset.j2": 0.0, "tcp": 0.5}}))
    b = World.from_dict(_doc(errors={"random": {"tcp": 0.5, "offset.j2": 0.0, "offsets": 0.1}}))
    assert a.errors() == b.errors() and "offset.j2" not in a.errors()
    c = World.from_dict(_doc(errors={"random": {"offsets": 0.1}}))
    assert all(c.errors()[k] == v for k, v in a.errors().items() if k.startswith("offset"))
    w2 = World.from_dict(_doc(errors={"random": {"offsets": 0.1}, "explicit": {"offset.j3": 1.0}}))
    assert w2.errors()["offset.j3"] == pytest.approx(math.radians(1.0))  # explicit replaces the draw


def test_model_file_path_relative_to_world_file(tmp_path):
    from station.kinematics import builtin_text

    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "myarm.yaml").write_text(builtin_text("omx"))
    doc = _doc(robot={"model": "models/myarm.yaml"}, errors={"explicit": {"offset.j1": 0.2}})
    (tmp_path / "w.yaml").write_text(yaml.safe_dump(doc))
    w = World.from_file(tmp_path / "w.yaml")
    assert w.nominal.n_joints == 4
    assert w.hidden()["offset.j1"] == pytest.approx(math.radians(0.2))


@pytest.mark.parametrize("model", ["ur5e", "ur3e", "ur10e", "omx", "arm6", "scara"])
def test_example_file_loads_and_is_complete(tmp_path, model):
    text = example_text(model, seed=5)
    f = tmp_path / "w.yaml"
    f.write_text(text)
    w = World.from_file(f)
    assert w.nominal.name == model and w.spec.seed == 5
    assert any(p.kind == "socket" for p in w.points.values())
    assert w.hidden()["offset.j2"] == pytest.approx(math.radians(0.05))
    doc = yaml.safe_load(text)
    assert set(doc) == {"format", "description", "units", "seed", "robot", "errors", "joints", "motion", "cell",
                        "noise", "buses"}
    assert "mm" in text and "deg" in text


# (change, the field the error names, what the line it names holds: yaml.safe_dump's block layout)
BAD = [
    ({"format": "station-world/2"}, "format", "format: station-world/2"),
    ({"units": {"length": "inch", "angle": "deg"}}, "units.length", "length: inch"),
    ({"units": {"length": "mm"}}, "units", "units:"),
    ({"seed": -1}, "seed", "seed: -1"),
    ({"seed": "abc"}, "seed", "seed: abc"),
    ({"robot": {"model": "nosuchrobot"}}, "robot.model", "model: nosuchrobot"),
    ({"robot": {"model": "ur5e", "colour": "blue"}}, "robot", "colour: blue"),
    ({"errors": {"explicit": {"offset.j9": 0.1}}}, "errors.explicit.offset.j9", "offset.j9: 0.1"),
    ({"errors": {"explicit": {"offset.j2": "a lot"}}}, "errors.explicit.offset.j2", "offset.j2: a lot"),
    ({"errors": {"explicit": {"offset.j2": float("nan")}}}, "errors.explicit.offset.j2", "offset.j2: .nan"),
    ({"errors": {"random": {"nosuchgroup": 0.1}}}, "errors.random.nosuchgroup", "nosuchgroup: 0.1"),
    ({"errors": {"random": {"dh": 0.1}}}, "errors.random.dh", "dh: 0.1"),
    ({"errors": {"random": {"offsets": -0.1}}}, "errors.random.offsets", "offsets: -0.1"),
    ({"errors": {"random": {"dh": {"length": 0.1}}}}, "errors.random.dh", "dh:"),
    ({"joints": {"backlash": {"j7": 0.1}}}, "joints.backlash.j7", "j7: 0.1"),
    ({"joints": {"payload": -1}}, "joints.payload", "payload: -1"),
    ({"motion": {"time_mode": "fast"}}, "motion.time_mode", "time_mode: fast"),
    ({"motion": {"time_scale": 0}}, "motion.time_scale", "time_scale: 0"),
    ({"motion": {"start": [0, 0]}}, "motion.start", "start:"),
    ({"motion": {"start": [0, 0, 0, 0, 0, 400]}}, "motion.start[5]", "- 400"),
    ({"cell": {"points": [{"label": "A", "kind": "hole", "position": [0, 0, 0]}]}},
     "cell.points[0].kind", "kind: hole"),
    ({"cell": {"points": [{"label": "A", "kind": "socket"}]}},
     "cell.points[0]: expected key 'position'", "- kind: socket"),
    ({"cell": {"points": [{"label": "A", "kind": "socket", "position": [0, 0]}]}},
     "cell.points[0].position", "position:"),
    ({"cell": {"points": [{"label": "A", "kind": "socket", "position": [0, 0, 0]},
                          {"label": "A", "kind": "needle", "position": [1, 0, 0]}]}},
     "cell.points[1].label", "label: A"),
    ({"cell": {"points": [{"label": "A", "kind": "socket", "position": [0, 0, 0], "approach": [0, 0, 0]}]}},
     "cell.points[0].approach", "- approach:"),
    ({"cell": {"capture_radius": -8}}, "cell.capture_radius", "capture_radius: -8"),
    ({"noise": {"seating": -0.01}}, "noise.seating", "seating: -0.01"),
    ({"noise": {"jitter": 1}}, "noise", "jitter: 1"),
    ({"buses": ["dynamixel"]}, "buses", "buses:"),
    ({"colour": "blue"}, "colour", "colour: blue"),
]


@pytest.mark.parametrize("change,field,holds", BAD)
def test_malformed_world_file_one_line_error_naming_file_line_and_field(tmp_path, change, field, holds):
    doc = _doc()
    doc.update(change)
    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(doc))
    with pytest.raises(WorldFileError) as e:
        World.from_file(f)
    msg = str(e.value)
    assert "\n" not in msg
    m = re.match(rf"{re.escape(str(f))}:(\d+): ", msg)
    assert m, msg
    assert holds in f.read_text().splitlines()[int(m.group(1)) - 1], msg  # the line of the faulty field
    assert field in msg
    assert isinstance(e.value, ValueError)
    from station.mocks.errors import MockError

    assert isinstance(e.value, MockError)  # the station command prints it as one line, exit 2


def test_unreadable_and_invalid_yaml(tmp_path):
    with pytest.raises(WorldFileError, match="cannot read"):
        World.from_file(tmp_path / "missing.yaml")
    f = tmp_path / "broken.yaml"
    f.write_text("format: station-world/1\nunits: {length: mm\n")
    with pytest.raises(WorldFileError, match=r"broken.yaml:\d+: not valid YAML"):
        World.from_file(f)
    f.write_text("- just\n- a list\n")
    with pytest.raises(WorldFileError, match="not a mapping"):
        World.from_file(f)


def test_default_overrides():
    w = World.default("omx", seed=2, time_mode="sim", time_scale=2.0, start=[0.1, 0.2, 0.3, 0.4], enabled=False)
    assert w.time_mode == "sim" and w.time_scale == 2.0
    np.testing.assert_allclose(w.encoder_q(), [0.1, 0.2, 0.3, 0.4])
    assert not w.enabled().any()
    with pytest.raises(TypeError, match="unknown override"):
        World.default("omx", colour="blue")
    with pytest.raises(WorldFileError, match="unknown model"):
        World.default("nosuchrobot")
    d = default_doc("ur5e", 3)
    d2 = copy.deepcopy(d)
    World.from_dict(d)
    assert d == d2  # from_dict does not modify the caller's document


def test_example_for_a_model_file_keeps_its_path(tmp_path):
    from station.kinematics import builtin_text

    m = tmp_path / "arm.yaml"
    m.write_text(builtin_text("scara"))
    text = example_text(str(m))
    assert f"model: {m}" in text
    f = tmp_path / "w.yaml"
    f.write_text(text)
    assert World.from_file(f).nominal.n_joints == 4
