"""The real-data benchmark's mechanism end to end, small (bench/realdata.py runs the full version).

Ground truth: the simulated world (``station.mocks.world.realdata``): a 7-DOF arm with hidden geometry errors
and joint compliance seats a ball in two sockets 50 mm apart at two fixture positions. ONE ``station solve``
(URDF, ``full,compliance``, ``--distance``) on position 1, ``station fk --calibration`` predicts position 2."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import urdf_robots as robots
from clirunner import station_proc
from station.mocks.world.realdata import arm_world, consistency, two_socket_data

NOISE = 0.06e-3


def write(path: Path, q: np.ndarray, point=None) -> Path:
    lines = [",".join([f"q{i + 1}" for i in range(q.shape[1])] + (["point"] if point is not None else []))]
    for k, r in enumerate(q):
        lines.append(",".join([repr(float(v)) for v in r] + ([str(point[k])] if point is not None else [])))
    path.write_text("\n".join(lines) + "\n")
    return path


def fk(cwd, urdf, joints, cal=None) -> np.ndarray:
    args = ["fk", "--model", urdf, "--tip-link", "ball", "--joints", joints] + (["--calibration", cal] if cal else [])
    p = station_proc(*args, cwd=cwd, timeout=300)
    assert p.code == 0, p.err
    rows = list(csv.reader(ln for ln in p.out.splitlines() if not ln.startswith("#")))[1:]
    return np.array([[float(v) for v in r[:3]] for r in rows])


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("realdata")
    urdf = d / "arm7.urdf"
    urdf.write_text(robots.arm7_urdf())
    world = arm_world(str(urdf), 3)
    data = two_socket_data(world, np.random.default_rng(5), positions=2, per_socket=14, noise=NOISE)
    return d, urdf, world, data


def test_train_on_one_position_predict_another(case):
    d, urdf, world, data = case
    train, held = data.where("1"), data.where("2")
    write(d / "train.csv", data.q[train], data.point[train])
    write(d / "held.csv", data.q[held])
    p = station_proc("solve", "--model", urdf, "--tip-link", "ball", "--samples", "train.csv", "--identify",
                     "full,compliance", "--distance", "A,B=50mm", "--out", "cal.json", cwd=d, timeout=300)
    assert (d / "cal.json").exists(), p.err
    res = json.loads((d / "cal.json").read_text())
    (c,) = res["constraints"]
    assert c["kind"] == "distance" and abs(c["residual_m"]) < 4 * c["stated_std_m"]
    assert not any((r or "").startswith("scale") for r in res["unidentifiable"].values())  # the distance pins it
    # held out: the calibrated model predicts every touch of a socket at (nearly) one place
    cal = consistency(fk(d, urdf, "held.csv", "cal.json"), data.point[held])
    nom = consistency(fk(d, urdf, "held.csv"), data.point[held])
    theta = np.array([world.gravity.deflect(q) for q in data.q[held]])
    floor = consistency(world.truth.position(theta), data.point[held])  # the seating noise alone
    assert nom > 3 * floor  # the hidden errors are real
    assert cal < 0.5 * nom, (cal, nom)
    assert cal < 2.0 * floor, (cal, floor)
