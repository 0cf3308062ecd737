"""The cell file's keep-out section (station-cell/1: mounting, keep_out) and the model file's link radii
(station-model/1: collision): units, defaults, one-line errors naming the field, round trips."""


import numpy as np
import pytest
import yaml
from clirunner import station_proc

from station.engine.cell import CellError, cell_from_dict, load_cell
from station.kinematics import ModelFileError, load_model, model_from_dict, model_to_dict
from station.kinematics.collision import Box, Checker, Plane

POINTS = [{"label": "A", "kind": "socket", "position": [450, 0, 50]}]


def _cell(units, **extra):
    return cell_from_dict({"format": "station-cell/1", "units": units, "points": POINTS, **extra}, "cell.yaml")


def test_a_cell_without_keep_out_forbids_what_is_below_the_base_plane():
    ko = _cell({"length": "mm"}).keep_out
    assert isinstance(ko.mounting, Plane) and ko.obstacles == ()
    np.testing.assert_allclose(ko.mounting.normal, [0, 0, 1])
    assert ko.mounting.offset == 0 and ko.mounting.clearance == pytest.approx(0.01)
    assert _cell({"length": "mm"}, mounting="none").keep_out.mounting is None


def test_mm_deg_and_m_rad_give_the_same_keep_out():
    mm = _cell({"length": "mm", "angle": "deg"}, mounting={"offset": -12, "clearance": 5}, keep_out=[
        {"name": "fixture", "box": {"min": [300, -400, 0], "max": [600, 400, 40]}},
        {"name": "mast", "box": {"center": [0, 500, 400], "size": [100, 100, 800], "rotation": {"rz": 30}},
         "clearance": 20},
        {"name": "wall", "plane": {"point": [0, -600, 0], "normal": [0, 2, 0]}},
        {"name": "back", "plane": {"normal": [-1, 0, 0], "offset": -800}}]).keep_out
    m = _cell({"length": "m", "angle": "rad"}, mounting={"offset": -0.012, "clearance": 0.005}, keep_out=[
        {"name": "fixture", "box": {"center": [0.45, 0, 0.02], "size": [0.3, 0.8, 0.04]}},
        {"name": "mast", "box": {"center": [0, 0.5, 0.4], "size": [0.1, 0.1, 0.8], "rotation": {"rz": np.pi / 6}},
         "clearance": 0.02},
        {"name": "wall", "plane": {"normal": [0, 1, 0], "offset": -0.6}},
        {"name": "back", "plane": {"point": [0.8, 0, 0], "normal": [-1, 0, 0]}}]).keep_out
    assert m.mounting.offset == pytest.approx(-0.012) and mm.mounting.offset == pytest.approx(-0.012)
    assert mm.mounting.clearance == pytest.approx(0.005) == m.mounting.clearance
    for a, b in zip(mm.obstacles, m.obstacles, strict=True):
        assert type(a) is type(b) and a.name == b.name and a.clearance == pytest.approx(b.clearance)
        if isinstance(a, Box):
            np.testing.assert_allclose([a.center, a.half], [b.center, b.half], atol=1e-12)
            np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-12)
        else:
            np.testing.assert_allclose(a.normal, b.normal, atol=1e-12)
            assert a.offset == pytest.approx(b.offset)
    assert [o.clearance for o in m.obstacles] == pytest.approx([0.01, 0.02, 0.01, 0.01])
    # the same configurations are refused with either file
    model = load_model("ur5e")
    q = np.random.default_rng(3).uniform(-np.pi, np.pi, (200, 6))
    np.testing.assert_array_equal(Checker(model, mm).clear(q), Checker(model, m).clear(q))


@pytest.mark.parametrize("extra, field", [
    ({"keep_out": [{"name": "f", "box": {"min": [0, 0, 0], "max": [100, -5, 40]}}]}, r"keep_out\[0\] \(f\)\.box: max"),
    ({"keep_out": [{"name": "f", "box": {"center": [0, 0, 0], "size": [0, 1, 1]}}]}, r"keep_out\[0\] \(f\)\.box\.size"),
    ({"keep_out": [{"name": "w", "plane": {"normal": [0, 0, 0], "offset": 3}}]}, r"keep_out\[0\] \(w\)\.plane\.normal"),
    ({"keep_out": [{"name": "w", "plane": {"normal": [0, 0, 1]}}]}, r"keep_out\[0\] \(w\)\.plane: give|a plane is"),
    ({"keep_out": [{"name": "w", "plane": {"normal": [0, 0, 1], "offset": 0}, "box": {}}]}, r"keep_out\[0\]"),
    ({"keep_out": [{"name": "a", "plane": {"normal": [0, 0, 1], "offset": 0}},
                   {"name": "a", "plane": {"normal": [0, 1, 0], "offset": 0}}]},
     r"keep_out\[1\]: name 'a' is used twice"),
    ({"keep_out": [{"name": "w", "plane": {"normal": [0, 0, 1], "offset": 0}, "clearance": -1}]}, r"clearance"),
    ({"keep_out": {"name": "w"}}, r"keep_out must be a list"),
    ({"mounting": None}, r"mounting: expected .* or the word none"),
    ({"mounting": {"offset": "low"}}, r"mounting\.offset"),
    ({"keep_out": [{"name": "m", "box": {"center": [0, 0, 0], "size": [1, 1, 1], "rotation": {"yaw": 3}}}]},
     r"rotation"),
])
def test_malformed_keep_out_is_one_line_naming_the_field(extra, field):
    with pytest.raises(CellError, match=field) as e:
        _cell({"length": "mm"}, **extra)
    assert str(e.value).startswith("cell.yaml: ") and "\n" not in str(e.value)


def test_station_run_refuses_a_bad_keep_out_before_touching_the_robot(tmp_path):
    cell = tmp_path / "cell.yaml"
    cell.write_text(yaml.safe_dump({"format": "station-cell/1", "units": {"length": "mm"}, "points": POINTS,
                                    "keep_out": [{"name": "fixture", "box": {"min": [0, 0, 0], "max": [0, 1, 1]}}]}))
    r = station_proc("run", "zero_offsets", "--robot", "ur://127.0.0.1:1?model=ur5e", "--serial", "X1", "--cell",
                     cell, env={"STATION_HOME": str(tmp_path), "PATH": "/usr/bin:/bin"}, replace_env=True)
    assert r.code == 2, r.err
    assert r.err.strip().startswith("station: error: ") and "keep_out[0] (fixture).box: max" in r.err
    assert len(r.err_lines) == 1


def test_load_cell_reads_the_keep_out_from_yaml(tmp_path):
    p = tmp_path / "cell.yaml"
    p.write_text("format: station-cell/1\nunits: {length: mm, angle: deg}\n"
                 "points:\n  - {label: A, kind: socket, position: [450, 0, 50]}\n"
                 "mounting: {normal: [0, 0, 1], offset: 0, clearance: 15}\n"
                 "keep_out:\n  - {name: fixture plate, box: {min: [300, -400, 0], max: [600, 400, 40]}}\n")
    c = load_cell(p)
    assert c.keep_out.mounting.clearance == pytest.approx(0.015)
    assert [o.name for o in c.keep_out.obstacles] == ["fixture plate"]


# ---- model file: link radii ---------------------------------------------------------------------------------
def test_link_radii_in_mm_and_m_and_their_round_trip():
    doc = model_to_dict(load_model("ur5e"), "mm", "deg")
    assert doc["collision"] == {"link_radii": [75, 60, 50, 45, 45, 45], "tool_radius": 10, "tool_free": 20}
    m_mm = model_from_dict(doc, "ur5e-mm.yaml")
    m_m = model_from_dict(model_to_dict(m_mm, "m", "rad"), "ur5e-m.yaml")
    assert m_m.source["collision"]["link_radii"] == pytest.approx([0.075, 0.06, 0.05, 0.045, 0.045, 0.045])
    assert m_m.source["collision"]["tool_free"] == pytest.approx(0.02)
    # a calibrated copy (with_params) keeps its envelope
    assert m_m.with_params({"offset.j2": 0.01}).source["collision"] == m_m.source["collision"]


@pytest.mark.parametrize("collision, field", [
    ({"link_radii": [10, 10]}, "collision.link_radii: expected 6 radii"),
    ({"link_radii": [10, 10, 10, 10, 10, "x"]}, "collision.link_radii: expected a number"),
    ({"tool_radius": -1}, "must not be negative"),
    ({"radius": 3}, "collision: expected a mapping of link_radii, tool_radius, tool_free"),
])
def test_malformed_link_radii_name_the_field(collision, field):
    doc = model_to_dict(load_model("ur5e"), "mm", "deg")
    doc["collision"] = collision
    with pytest.raises(ModelFileError, match=field):
        model_from_dict(doc, "arm.yaml")


def test_a_model_file_without_radii_gets_a_size_based_default():
    doc = model_to_dict(load_model("ur10e"), "mm", "deg")
    del doc["collision"]
    m = model_from_dict(doc, "custom.yaml")
    from station.kinematics.collision import radii_of

    radii, tool_r, tool_free = radii_of(m)
    assert np.all(radii == radii[0]) and 0.015 <= radii[0] <= 0.08 and tool_r == 0.01 and tool_free == 0.02
