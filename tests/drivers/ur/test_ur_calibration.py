"""UR calibration files (calibration.conf, URDF, YAML) and ur:// URL checks: pure, no network."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from station.drivers.ur.calibration import (
    calibrated_table,
    controller_model,
    deltas_of,
    export_files,
    published_table,
    read_calibration_conf,
    table_fk,
    table_from_deltas,
    table_from_rows,
    urdf_chain_fk,
)

from station.kinematics import load_model
from station.robot import ConfigError, open_robot

DELTAS = {"delta_theta": [1e-4, -2e-4, 3e-4, -1e-4, 5e-5, 0.0],
          "delta_a": [0.0, 3e-4, -2e-4, 0.0, 0.0, 0.0],
          "delta_d": [1e-4, 0.0, 0.0, -3e-4, 2e-4, 1e-4],
          "delta_alpha": [2e-4, -1e-4, 0.0, 1e-4, 0.0, 0.0]}

# KinematicsInfo of a real UR10 as UR's ur_calibration documents it (doc/algorithm.rst): plain DH with the
# compensating hundreds of metres on the nearly parallel joints 2-4
REAL_UR10 = {"theta": [-2.4147806894359e-07, 1.60233952386695, -1.68607190752171, 0.0837331147700119,
                       -1.01260355871158e-07, 3.91986209186124e-08],
             "a": [2.12234865571206e-05, 0.0193171326277006, -0.569251663611088, -4.61409023720934e-05,
                   -6.39280053471802e-05, 0.0],
             "d": [0.180539811714259, 439.140974079901, -446.027059806332, 7.0603368964236, 0.119811341150314,
                   0.115670917257426],
             "alpha": [1.57014608044242, 0.0013941666682559, 0.00693818880325995, 1.56998468543761,
                       -1.57038520649543, 0.0]}


def test_real_controller_rows_convert_to_a_model_with_the_same_fk_and_no_hundreds_of_metres():
    """The one conversion (ur_calibration's re-intersection) on a real controller's table: FK of the converted
    model equals FK of the raw rows to 1e-9 m at random joints, and no length in it is beyond a metre."""
    catalog = load_model("ur10e")
    table = table_from_rows(catalog, **{k: REAL_UR10[k] for k in ("theta", "a", "d", "alpha")})
    model = controller_model(catalog, table)
    q = np.random.default_rng(4).uniform(-np.pi, np.pi, size=(200, 6))
    want, got = table_fk(catalog, table, q), model.fk(q)
    assert np.max(np.linalg.norm(want[:, :3, 3] - got[:, :3, 3], axis=1)) < 1e-9
    assert np.max(np.abs(want[:, :3, :3] - got[:, :3, :3])) < 1e-9
    lengths = [model.param(n) for n in model.param_names if n.endswith((".a", ".d"))]
    assert max(abs(v) for v in lengths) < 1.0, lengths  # the 439 m are gone
    assert abs(model.param("dh.j2.beta")) > 1e-5 and model.param("dh.j2.d") == catalog.param("dh.j2.d")
    # and back: the plain rows of the converted model are the controller's
    back = calibrated_table(catalog, model)
    np.testing.assert_allclose(back.fk(q), table.fk(q), atol=1e-9)


def test_conf_and_controller_rows_are_one_conversion(tmp_path):
    """A copied calibration.conf is the controller's rows minus the published table: both paths give the same
    model, and an export of a model reads back to it."""
    catalog = load_model("ur5e")
    from_conf = controller_model(catalog, table_from_deltas(catalog, DELTAS))
    pub = published_table(catalog)
    rows = {k: getattr(pub, k) + np.asarray(DELTAS[f"delta_{k}"]) for k in ("theta", "a", "d", "alpha")}
    from_rows = controller_model(catalog, table_from_rows(catalog, **rows))
    q = np.random.default_rng(5).uniform(-3, 3, size=(50, 6))
    np.testing.assert_allclose(from_conf.fk(q), from_rows.fk(q), atol=1e-12)
    calibrated = from_conf.with_params({"offset.j2": 0.002, "dh.j2.beta": 3e-4, "dh.j3.beta": -2e-4})
    paths = export_files(catalog, calibrated, tmp_path, serial="20235512345")
    back = read_calibration_conf(paths[0])
    assert max(abs(v) for v in back["delta_d"]) > 100  # a tilt between parallel axes: the controller's metres
    again = controller_model(catalog, table_from_deltas(catalog, back))
    np.testing.assert_allclose(again.fk(q), calibrated.fk(q), atol=1e-9)
    assert again.param("offset.j2") == pytest.approx(0.002, abs=1e-9)
    np.testing.assert_allclose(deltas_of(catalog, table_from_deltas(catalog, DELTAS))["delta_d"], DELTAS["delta_d"],
                               atol=1e-15)


def test_export_round_trips_and_urdf_matches_model(tmp_path):
    catalog = load_model("ur5e")
    calibrated = controller_model(catalog, table_from_deltas(catalog, DELTAS))
    paths = export_files(catalog, calibrated, tmp_path, serial="20235512345")
    back = read_calibration_conf(paths[0])
    for key, vals in DELTAS.items():
        np.testing.assert_allclose(back[key], vals, atol=1e-12)
    text = paths[0].read_text()
    assert "[mounting]" in text and "rad" in text and "does NOT change the robot" in text
    rng = np.random.default_rng(3)
    for q in rng.uniform(-3, 3, size=(5, 6)):
        np.testing.assert_allclose(urdf_chain_fk(paths[2], q), calibrated.fk(q), atol=1e-9)
    doc = yaml.safe_load(paths[1].read_text())
    assert doc["units"] == {"length": "m", "angle": "rad"} and list(doc["kinematics"]) == [
        "shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3"]
    assert doc["dh"][1]["a"] == pytest.approx(catalog.param("dh.j2.a") + 3e-4, abs=1e-12)


def test_urdf_model_takes_the_controller_rows_by_fit():
    """A model in another convention (MDH from a URDF-like description): the rows are fitted with the model's
    own Jacobian, exact to 1e-9 m."""
    from station.kinematics import from_mdh
    from station.kinematics.dhtable import dh_table

    catalog = load_model("ur5e")
    mdh = _mdh_twin(catalog, from_mdh)
    pub = dh_table(mdh.with_params({f"tcp.{k}": 0.0 for k in ("x", "y", "z", "rx", "ry", "rz")}))
    table = table_from_deltas(mdh, DELTAS)
    model = controller_model(mdh, table)
    q = np.random.default_rng(6).uniform(-3, 3, size=(40, 6))
    np.testing.assert_allclose(model.fk(q)[:, :3, 3], table_fk(mdh, table, q)[:, :3, 3], atol=1e-9)
    assert np.allclose(pub.base, published_table(mdh).base)


def _mdh_twin(catalog, from_mdh):
    """The UR5e as modified DH (Craig) with the same joints."""
    links = []
    prev_a, prev_alpha = 0.0, 0.0
    for i in range(6):
        j = f"j{i + 1}"
        links.append({"alpha": prev_alpha, "a": prev_a, "d": catalog.param(f"dh.{j}.d"), "theta": 0.0})
        prev_a, prev_alpha = catalog.param(f"dh.{j}.a"), catalog.param(f"dh.{j}.alpha")
    m = from_mdh("ur5e_mdh", list(catalog.joints), links, tool={"x": prev_a, "rx": prev_alpha})
    q = np.random.default_rng(1).uniform(-3, 3, size=(5, 6))
    np.testing.assert_allclose(m.fk(q), catalog.fk(q), atol=1e-12)
    return m


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
