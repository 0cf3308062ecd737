"""UR calibration files (calibration.conf, URDF, YAML) and ur:// URL checks: pure, no network."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from station.drivers.ur.calibration import (
    apply_deltas,
    deltas_from_values,
    export_files,
    read_calibration_conf,
    urdf_chain_fk,
)

from station.kinematics import load_model
from station.robot import ConfigError, open_robot

DELTAS = {"delta_theta": [1e-4, -2e-4, 3e-4, -1e-4, 5e-5, 0.0],
          "delta_a": [0.0, 3e-4, -2e-4, 0.0, 0.0, 0.0],
          "delta_d": [1e-4, 0.0, 0.0, -3e-4, 2e-4, 1e-4],
          "delta_alpha": [2e-4, -1e-4, 0.0, 1e-4, 0.0, 0.0]}


def test_export_round_trips_and_urdf_matches_model(tmp_path):
    catalog = load_model("ur5e")
    paths = export_files(catalog, DELTAS, tmp_path, serial="20235512345")
    back = read_calibration_conf(paths[0])
    for key, vals in DELTAS.items():
        np.testing.assert_allclose(back[key], vals, atol=1e-15)
    text = paths[0].read_text()
    assert "[mounting]" in text and "rad" in text and "does NOT change the robot" in text
    calibrated = apply_deltas(catalog, DELTAS)
    rng = np.random.default_rng(3)
    for q in rng.uniform(-3, 3, size=(5, 6)):
        np.testing.assert_allclose(urdf_chain_fk(paths[2], q), calibrated.fk(q), atol=1e-8)
    doc = yaml.safe_load(paths[1].read_text())
    assert doc["units"] == {"length": "m", "angle": "rad"} and list(doc["kinematics"]) == [
        "shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"]
    assert doc["dh"][1]["a"] == pytest.approx(catalog.param("dh.j2.a") + 3e-4, abs=1e-12)


def test_values_to_deltas_keep_base_and_name_what_ur_cannot_store():
    catalog = load_model("ur5e")
    values = {"offset.j2": 0.002, "dh.j3.a": catalog.param("dh.j3.a") + 1e-4, "dh.j2.beta": 1e-4, "tcp.x": 0.1}
    deltas, dropped = deltas_from_values(catalog, values, base=DELTAS)
    assert deltas["delta_theta"][1] == pytest.approx(0.002)
    assert deltas["delta_a"][2] == pytest.approx(1e-4, abs=1e-12)
    assert deltas["delta_d"] == DELTAS["delta_d"]  # untouched entries keep the existing calibration
    assert sorted(dropped) == ["dh.j2.beta", "tcp.x"]
    with pytest.raises(ConfigError, match="not finite"):
        deltas_from_values(catalog, {"offset.j1": float("nan")})


def test_bad_calibration_conf_names_file_and_line(tmp_path):
    bad = tmp_path / "calibration.conf"
    bad.write_text("[mounting]\ndelta_theta = [ 0.1, 0.2, zz, 0, 0, 0 ]\n")
    with pytest.raises(ConfigError, match=r"calibration.conf line 2: delta_theta"):
        read_calibration_conf(bad)
    bad.write_text("[mounting]\ndelta_a = [ 0.1, 0.2 ]\n")
    with pytest.raises(ConfigError, match="needs 6 finite values"):
        read_calibration_conf(bad)
    bad.write_text("[other]\nx = 1\n")
    with pytest.raises(ConfigError, match="no \\[mounting\\]"):
        read_calibration_conf(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        read_calibration_conf(tmp_path / "missing.conf")


@pytest.mark.parametrize("url, message", [
    ("ur://", "needs the controller's address"),
    ("ur://127.0.0.1:30004", "takes no port"),
    ("ur://127.0.0.1?bogus=1", "unknown option"),
    ("ur://127.0.0.1?contact_bit=x", r"contact_bit='x' is not a valid value \(expected integer 0\.\.63\)"),
    ("ur://127.0.0.1?speed=9", "must be in"),
    ("ur://127.0.0.1?tool_speed=0.3", r"tool_speed='0.3' is not a valid value \(expected number in \(0, 0.25\] m/s\)"),
    ("ur://127.0.0.1?model=nosuchrobot", "model 'nosuchrobot'"),
])
def test_bad_ur_urls_are_config_errors(url, message):
    with pytest.raises(ConfigError, match=message):
        open_robot(url)
