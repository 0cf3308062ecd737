"""Plausibility at the edges: duplicate keys in a JSON input are refused with the key and line (JSON keeps the
last one silently); calibration values beyond physical bounds are refused; a model file whose lengths are
impossible for its stated unit is refused naming the likely unit."""

import json
from pathlib import Path

import pytest
from clirunner import station_proc

from station.kinematics import ModelFileError, load_model
from station.safeio import DuplicateKeyError, loads_strict


def one_error(p, *needles):
    assert p.code == 2, (p.out, p.err)
    lines = p.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("station: error: "), p.err
    for n in needles:
        assert n in lines[0], lines[0]


def test_duplicate_keys_name_the_key_and_its_line():
    text = '{"a": 1,\n "p": {"x": 1, "y": {"x": 2}},\n "q": {"x": 1,\n  "x": 2}}'
    with pytest.raises(DuplicateKeyError, match=r"^f.json:4: key 'x' is given twice in one object"):
        loads_strict(text, "f.json")
    assert loads_strict('{"a": "b:c", "s": "\\"}", "x": [{"x": 1}, {"x": 2}]}')["x"][1]["x"] == 2


def _calibration(tmp_path, edit) -> Path:
    res = {"format": "station-calibration/1", "units": "SI (m, rad)", "model": "ur5e",
           "parameters": {"offset.j2": {"value": 0.001, "std": 1e-5, "identifiable": True, "nominal": 0.0,
                                        "kind": "model", "unit": "rad"}},
           "residuals": {}, "rank": 1, "n_parameters": 1, "converged": True, "iterations": 1}
    text = edit(json.dumps(res, indent=1))
    p = tmp_path / "cal.json"
    p.write_text(text)
    (tmp_path / "q.csv").write_text("q1,q2,q3,q4,q5,q6\n0,0,0,0,0,0\n")
    return p


def test_a_calibration_with_a_duplicated_key_is_refused(tmp_path):
    cal = _calibration(tmp_path, lambda t: t.replace('"value": 0.001,', '"value": 0.001, "value": 0.5,'))
    line = next(i for i, s in enumerate(cal.read_text().splitlines(), 1) if '"value": 0.5' in s)
    one_error(station_proc("fk", "--model", "ur5e", "--joints", "q.csv", "--calibration", cal, cwd=tmp_path),
              f"cal.json:{line}: key 'value' is given twice")


@pytest.mark.parametrize("value,unit,needle", [(1e6, "rad", "beyond half a turn"), (-3.5, "rad", "beyond half a turn"),
                                               (1.5, "m", "more than 1 m")])
def test_calibration_values_beyond_physical_bounds_are_refused(tmp_path, value, unit, needle):
    name = "offset.j2" if unit == "rad" else "tcp.z"

    def edit(t):
        d = json.loads(t)
        d["parameters"] = {name: {"value": value, "std": 1e-5, "identifiable": True, "nominal": 0.0, "kind": "model",
                                  "unit": unit}}
        return json.dumps(d)

    cal = _calibration(tmp_path, edit)
    one_error(station_proc("fk", "--model", "ur5e", "--joints", "q.csv", "--calibration", cal, cwd=tmp_path),
              f"parameters.{name}", needle)


UR5E_M = """format: station-model/1
name: ur5e-copy
convention: dh
units: {length: m, angle: deg}
joints:
  - {name: j1, limits: [-360, 360], dh: {a: 0, d: 162.5, alpha: 90, theta: 0}}
  - {name: j2, limits: [-360, 360], dh: {a: -425, d: 0, alpha: 0, theta: 0}}
  - {name: j3, limits: [-360, 360], dh: {a: -392.2, d: 0, alpha: 0, theta: 0}}
  - {name: j4, limits: [-360, 360], dh: {a: 0, d: 133.3, alpha: 90, theta: 0}}
  - {name: j5, limits: [-360, 360], dh: {a: 0, d: 99.7, alpha: -90, theta: 0}}
  - {name: j6, limits: [-360, 360], dh: {a: 0, d: 99.6, alpha: 0, theta: 0}}
"""


def test_a_model_file_in_millimetres_under_a_metre_header_is_refused(tmp_path):
    p = tmp_path / "ur5e.yaml"
    p.write_text(UR5E_M)
    with pytest.raises(ModelFileError, match=r"reaches 1\.3\d* km.*millimetres.*length: mm"):
        load_model(p)
    p.write_text(UR5E_M.replace("length: m,", "length: mm,"))
    assert load_model(p).n_joints == 6  # the same numbers in mm: a UR5e
    # metres under a millimetre header: a 1.3 mm arm
    p.write_text(UR5E_M.replace("length: m,", "length: mm,").replace("162.5", "0.1625").replace("-425", "-0.425")
                 .replace("-392.2", "-0.3922").replace("133.3", "0.1333").replace("99.7", "0.0997")
                 .replace("99.6", "0.0996"))
    with pytest.raises(ModelFileError, match=r"reaches 1\.3\d* mm.*metres.*length: m"):
        load_model(p)
